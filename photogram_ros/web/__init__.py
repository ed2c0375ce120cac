"""The ground station's web page: a small HTTP server (web/server.py) and its static files (web/static/)."""
