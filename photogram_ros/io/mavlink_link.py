"""Where MAVLink comes from: live links (serial, UDP, TCP) through pymavlink's transports, or a file."""

from __future__ import annotations

import contextlib
import io
import os

from photogram_ros.errors import MavlinkError

_URL_PREFIXES = ('udpin:', 'udpout:', 'udp:', 'udpbcast:', 'tcp:', 'tcpin:')


def is_live_url(url: str) -> bool:
    return url.startswith(_URL_PREFIXES) or url.startswith('/dev/') or url.upper().startswith('COM')


class Link:
    """A live byte link opened through pymavlink's transports; read() hands back raw bytes."""

    def __init__(self, url: str, baud: int = 57600):
        from pymavlink import mavutil
        if not is_live_url(url):
            raise MavlinkError(f'{url!r} is not a link: use udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, '
                               'tcpin:HOST:PORT or a serial device such as /dev/ttyUSB0')
        self.url = url
        if url.startswith('/dev/') and not os.path.exists(url):
            raise MavlinkError(f'cannot open MAVLink link {url}: no such device (is the autopilot or radio plugged in?)')
        said = io.StringIO()
        try:
            # pymavlink prints its retries ("... sleeping") on stdout, where `fixes` writes its rows.
            with contextlib.redirect_stdout(said):
                self.conn = mavutil.mavlink_connection(url, baud=baud, autoreconnect=True, source_system=255,
                                                       source_component=191)
        except ModuleNotFoundError as exc:
            raise MavlinkError(f'cannot open MAVLink link {url}: serial links need the pyserial package '
                               f'({exc})') from exc
        except Exception as exc:   # pymavlink raises socket, serial and OS errors alike
            raise MavlinkError(f'cannot open MAVLink link {url}: {exc}') from exc

    def read(self, timeout_s: float = 0.2) -> bytes:
        if not self.conn.select(timeout_s):
            return b''
        data = self.conn.recv()
        return bytes(data) if data else b''

    def close(self) -> None:
        try:
            self.conn.close()
        except Exception:
            pass


def file_kind(path: str) -> str:
    low = str(path).lower()
    if low.endswith(('.bin', '.log')) and os.path.isfile(path):
        with open(path, 'rb') as f:
            head = f.read(3)
        if head[:2] == b'\xa3\x95':
            return 'dataflash'
    if os.path.isdir(path) or low.endswith(('.db3', '.mcap', '.bag')):
        return 'bag'
    return 'tlog'
