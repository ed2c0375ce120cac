"""Files and links: MAVLink, bags, exports."""
