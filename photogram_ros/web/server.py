"""HTTP server of the ground station's web page (the standard library's ThreadingHTTPServer).

Routes (GET):
  /                              the map page (static/index.html: Leaflet, shipped in static/leaflet)
  /static/...                    the page's files
  /status.json                   every drone's figures (provider.status())
  /tiles/DRONE/Z/X/Y.png         the live ortho tiles (XYZ / Web Mercator) a drone streamed
  /drones/DRONE/coverage.geojson the drone's gaps and survey area (GeoJSON, WGS84)
  /drones/DRONE/track.geojson    its keyframe track
  /drones/DRONE/targets.geojson  its check points and GCPs with their residuals
  /drones/DRONE/refly.plan       a QGroundControl plan re-flying its gaps
The provider (the ground station node) answers with a document or None (404); every answer is
built under the provider's own lock, the server only serialises it.
"""

from __future__ import annotations

import json
import mimetypes
import re
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from photogram_ros.errors import ConfigError

STATIC = Path(__file__).resolve().parent / 'static'
_TILE = re.compile(r'^/tiles/([A-Za-z0-9_.-]+)/(\d{1,2})/(\d{1,10})/(\d{1,10})\.png$')   # longer numbers: no tile (404)
_DRONE = re.compile(r'^/drones/([A-Za-z0-9_.-]+)/(coverage|track|targets)\.geojson$')
_PLAN = re.compile(r'^/drones/([A-Za-z0-9_.-]+)/refly\.plan$')


def parse_host_port(text: str) -> tuple[str, int]:
    """'HOST:PORT' (or ':PORT' for every interface) -> (host, port)."""
    host, sep, port = text.rpartition(':')
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f'--web {text!r}: give HOST:PORT, e.g. 127.0.0.1:8080 (or :8080 for every interface)')
    return host or '0.0.0.0', int(port)


class _Handler(BaseHTTPRequestHandler):
    provider = None   # set per server class

    def log_message(self, fmt, *args):   # the station prints its own progress
        pass

    def _send(self, code: int, body: bytes, ctype: str) -> None:
        self.send_response(code)
        self.send_header('Content-Type', ctype)
        self.send_header('Content-Length', str(len(body)))
        self.send_header('Cache-Control', 'no-cache')
        self.end_headers()
        self.wfile.write(body)

    def _json(self, doc, ctype='application/json') -> None:
        if doc is None:
            self._send(404, b'not found\n', 'text/plain')
        else:
            self._send(200, json.dumps(doc).encode(), ctype)

    def do_GET(self):  # noqa: N802 (http.server's name)
        path = self.path.split('?', 1)[0]
        try:
            if path in ('/', '/index.html'):
                return self._static('index.html')
            if path.startswith('/static/'):
                return self._static(path[len('/static/'):])
            if path == '/status.json':
                return self._json(self.provider.status())
            m = _TILE.match(path)
            if m:
                png = self.provider.tile(m.group(1), int(m.group(2)), int(m.group(3)), int(m.group(4)))
                return self._send(200, png, 'image/png') if png else self._send(404, b'', 'text/plain')
            m = _DRONE.match(path)
            if m:
                return self._json(self.provider.geojson(m.group(1), m.group(2)), 'application/geo+json')
            m = _PLAN.match(path)
            if m:
                return self._json(self.provider.refly_plan(m.group(1)))
            self._send(404, b'not found\n', 'text/plain')
        except (BrokenPipeError, ConnectionResetError):
            pass

    def _static(self, rel: str) -> None:
        p = (STATIC / rel).resolve()
        if STATIC not in p.parents or not p.is_file():
            return self._send(404, b'not found\n', 'text/plain')
        ctype = mimetypes.guess_type(p.name)[0] or 'application/octet-stream'
        self._send(200, p.read_bytes(), ctype)


class WebServer:
    """Serve the page for `provider` on host:port in a daemon thread (port 0: a free port)."""

    def __init__(self, provider, host: str = '127.0.0.1', port: int = 8080):
        handler = type('Handler', (_Handler,), {'provider': provider})
        try:
            self.httpd = ThreadingHTTPServer((host, port), handler)
        except OSError as exc:
            raise ConfigError(f'cannot serve the ground-station page on {host}:{port}: {exc}') from exc
        self.httpd.daemon_threads = True
        self.thread = threading.Thread(target=self.httpd.serve_forever, name='ground_station_web', daemon=True)

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f'http://{host}:{port}/'

    def start(self) -> 'WebServer':
        self.thread.start()
        return self

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
