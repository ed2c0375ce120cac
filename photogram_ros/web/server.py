"""Web server of the ground station's page (aiohttp, in a thread of its own with its own event loop).

Routes (GET):
  /                              the map page (static/index.html: Leaflet, shipped in static/vendor/leaflet)
  /static/...                    the page's files
  /ws                            WebSocket: the server pushes {'type': 'status', 'status': ..., 'tiles': ...}
                                 on connect and whenever the provider calls notify() (at most twice a second,
                                 at least every `push_period_s`); 'tiles' lists the ortho tiles changed since
                                 the last push per drone, [[z, x, y], ...]
  /status.json                   every drone's figures (provider.status())
  /tiles/DRONE/Z/X/Y.png         the live ortho tiles (XYZ / Web Mercator) a drone streamed
  /basemap/Z/X/Y                 the offline base map's tiles (web/basemap.py), when one is given
  /drones/DRONE/coverage.geojson the drone's gaps and survey area (GeoJSON, WGS84)
  /drones/DRONE/track.geojson    its keyframe track
  /drones/DRONE/targets.geojson  its check points and GCPs with their residuals
  /drones/DRONE/live.geojson     its live position (its latest gps/fix) and GNSS track
  /drones/DRONE/refly.plan       a QGroundControl plan re-flying its gaps
The provider (the ground station node) answers with a document or None (404); every answer is built
under the provider's own lock, the server only serialises it.

Trust: a request is served when it comes from a loopback address naming a loopback host (no DNS
rebinding), or when it carries the token (`?token=` once: the answer sets an HttpOnly cookie; or
`Authorization: Bearer TOKEN`); anything else gets 403. Every answer carries a Content-Security-Policy
that allows no inline script. Limits: at most `max_connections` open connections (the next is closed at
once); a connection that has not completed a request for `idle_timeout_s` is closed (a half-open or
trickling client included); a request's answer must be written within `request_timeout_s`.
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import json
import logging
import math
import mimetypes
import re
import secrets
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from aiohttp import WSMsgType, web

from photogram_ros.errors import ConfigError
from photogram_ros.params import param

STATIC = Path(__file__).resolve().parent / 'static'
_NAME = r'([A-Za-z0-9_.-]+)'
_TILE = re.compile(rf'^/tiles/{_NAME}/(\d{{1,2}})/(\d{{1,10}})/(\d{{1,10}})\.png$')   # longer numbers: no tile (404)
_BASEMAP = re.compile(r'^/basemap/(\d{1,2})/(\d{1,10})/(\d{1,10})$')
_DRONE = re.compile(rf'^/drones/{_NAME}/(coverage|track|targets|live)\.geojson$')
_PLAN = re.compile(rf'^/drones/{_NAME}/refly\.plan$')
_STATIC = re.compile(r'^(?:[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}/){0,4}[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}$')
COOKIE = 'gs_token'
MIN_TOKEN_CHARS = 12          # a token given by the user: shorter ones are guessed too easily
LOOPBACK_NAMES = {'localhost', '127.0.0.1', '::1', '[::1]'}
HEADERS = {'X-Content-Type-Options': 'nosniff', 'X-Frame-Options': 'DENY', 'Referrer-Policy': 'no-referrer',
           'Cache-Control': 'no-cache',
           'Content-Security-Policy': "default-src 'self'; script-src 'self'; img-src 'self' data: blob:; "
                                      "style-src 'self' 'unsafe-inline'; connect-src 'self'; object-src 'none'; "
                                      "base-uri 'none'; frame-ancestors 'none'"}


@dataclass
class WebLimits:
    """How long and how many: the server's protection against idle and slow clients."""
    idle_timeout_s: float = param(20.0, 'Close a connection that has not completed a request for this long, s',
                                  min=0.5, max=3600.0)
    request_timeout_s: float = param(30.0, 'Longest a request may take to be answered, s', min=0.5, max=3600.0)
    max_connections: int = param(64, 'Open connections at most (the next is closed at once)', min=1, max=100000)
    push_period_s: float = param(5.0, 'Status pushed to the page at least this often, s', min=0.5, max=3600.0)


def parse_host_port(text: str) -> tuple[str, int]:
    """'HOST:PORT' (or ':PORT' for 127.0.0.1; '0.0.0.0:PORT' for every interface) -> (host, port)."""
    host, sep, port = text.rpartition(':')
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f'--web {text!r}: give HOST:PORT, e.g. 127.0.0.1:8080 (0.0.0.0:8080 for every interface, '
                          'which needs the token)')
    return host.strip('[]') or '127.0.0.1', int(port)


def is_loopback_host(host: str) -> bool:
    """Is `host` (an address or name to bind or a Host header's name) this machine only?"""
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip('[]')).is_loopback
    except ValueError:
        return False


def _host_name(host_header: str | None) -> str:
    """'name:port' / '[::1]:port' / 'name' -> the name."""
    h = (host_header or '').strip()
    if h.startswith('['):
        return h[: h.find(']') + 1] if ']' in h else h
    return h.rsplit(':', 1)[0] if h.count(':') == 1 else h


class _Guard(asyncio.Protocol):
    """Wraps aiohttp's protocol of one connection: counts it against the cap and tracks when it last
    completed a request (the server's sweep closes idle ones)."""

    def __init__(self, server: 'WebServer', inner):
        self.server, self.inner = server, inner
        self.transport = None
        self.refused = False
        self.busy = 0
        self.last_done = time.monotonic()

    def connection_made(self, transport):
        srv = self.server
        if len(srv.open_conns) >= srv.limits.max_connections:
            self.refused = True
            srv.refused_connections += 1
            transport.abort()
            return
        self.transport = transport
        srv.open_conns[transport] = self
        self.inner.connection_made(transport)

    def data_received(self, data):
        if not self.refused:
            self.inner.data_received(data)

    def eof_received(self):
        return None if self.refused else self.inner.eof_received()

    def connection_lost(self, exc):
        if self.refused:
            return
        self.server.open_conns.pop(self.transport, None)
        self.inner.connection_lost(exc)

    def pause_writing(self):
        self.inner.pause_writing()

    def resume_writing(self):
        self.inner.resume_writing()


class WebServer:
    """Serve the page for `provider` on host:port in a daemon thread (port 0: a free port).

    host: a loopback address serves this machine only; any other needs the token, which is `token` or,
    when None, a generated one (`.token`). basemap: a web.basemap.BaseMap or None.
    """

    def __init__(self, provider, host: str = '127.0.0.1', port: int = 8080, token: str | None = None,
                 limits: WebLimits | None = None, basemap=None):
        self.provider, self.host, self.port = provider, host, port
        self.limits = limits or WebLimits()
        self.basemap = basemap
        self.local_only = is_loopback_host(host)
        if token and (len(token) < MIN_TOKEN_CHARS or not token.isprintable() or ' ' in token):
            raise ConfigError(f'--web-token: give at least {MIN_TOKEN_CHARS} printable characters without blanks '
                              '(or none: the station generates one)')
        self.token = token or (None if self.local_only else secrets.token_urlsafe(18))
        self.refused_connections = 0
        self.refused_requests = 0
        self.closed_idle = 0
        self.open_conns: dict = {}   # transport -> its guard (the connection limit)
        self._clients: set = set()
        self._tile_seq: dict = {}
        self._loop = asyncio.new_event_loop()
        self._changed: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._runner = self._server = None
        self.thread = threading.Thread(target=self._run, name='ground_station_web', daemon=True)

    # --- life ------------------------------------------------------------------------------------

    @property
    def url(self) -> str:
        host = f'[{self.host}]' if ':' in self.host else self.host
        return f'http://{host}:{self.port}/'

    def url_with_token(self) -> str:
        return self.url + (f'?token={self.token}' if self.token else '')

    def start(self) -> 'WebServer':
        self.thread.start()
        self._ready.wait(30)
        if self._error is not None:
            raise ConfigError(f'cannot serve the ground-station page on {self.host}:{self.port}: {self._error}')
        return self

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._open())
        except BaseException as exc:   # noqa: BLE001 (reported by start())
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        self._loop.run_forever()

    async def _open(self) -> None:
        app = web.Application(middlewares=[self._guard_mw], client_max_size=64 * 1024)
        app.router.add_get('/ws', self._ws)
        app.router.add_get('/{tail:.*}', self._get)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False, logger=_QUIET,
                                     keepalive_timeout=self.limits.idle_timeout_s, shutdown_timeout=1.0)
        await self._runner.setup()
        factory = self._runner.server
        self._server = await self._loop.create_server(lambda: _Guard(self, factory()), self.host, self.port,
                                                      backlog=128)
        self.port = self._server.sockets[0].getsockname()[1]
        self._changed = asyncio.Event()
        self._tasks = [self._loop.create_task(self._sweep()), self._loop.create_task(self._broadcast())]

    def notify(self) -> None:
        """Something changed (any thread): push the status to the connected pages soon."""
        if self._changed is not None and self._loop.is_running():
            self._loop.call_soon_threadsafe(self._changed.set)

    def stop(self) -> None:
        if not self.thread.is_alive():
            return
        fut = asyncio.run_coroutine_threadsafe(self._close(), self._loop)
        try:
            fut.result(10)
        except Exception:   # noqa: BLE001 (closing: nothing more to do)
            pass
        self._loop.call_soon_threadsafe(self._loop.stop)
        self.thread.join(10)

    async def _close(self) -> None:
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for ws in list(self._clients):
            await ws.close()
        self._server.close()
        await self._runner.cleanup()

    @property
    def connections(self) -> int:
        return len(self.open_conns)

    # --- limits and trust ------------------------------------------------------------------------

    async def _sweep(self) -> None:
        """Close connections that completed no request for idle_timeout_s."""
        period = min(1.0, self.limits.idle_timeout_s / 4)
        while True:
            await asyncio.sleep(period)
            now = time.monotonic()
            for tr, g in list(self.open_conns.items()):
                if not g.busy and now - g.last_done > self.limits.idle_timeout_s:
                    self.closed_idle += 1
                    tr.abort()

    def authorised(self, request: web.Request) -> bool:
        """A loopback peer that names a loopback host, or the token (cookie, bearer header or ?token=)."""
        try:
            ip = ipaddress.ip_address((request.remote or '').split('%')[0])
            local_peer = (getattr(ip, 'ipv4_mapped', None) or ip).is_loopback
        except ValueError:
            local_peer = False
        if local_peer and is_loopback_host(_host_name(request.headers.get('Host'))):
            return True
        if not self.token:
            return False
        auth = request.headers.get('Authorization', '')
        given = [request.cookies.get(COOKIE, ''), request.query.get('token', ''),
                 auth[7:] if auth.startswith('Bearer ') else '']
        return any(g and hmac.compare_digest(g.encode(), self.token.encode()) for g in given)

    @web.middleware
    async def _guard_mw(self, request: web.Request, handler):
        g = self.open_conns.get(request.transport)
        if g is not None:
            g.busy += 1
        try:
            if request.method not in ('GET', 'HEAD'):
                resp = web.Response(status=405, text='only GET\n')
            elif not self.authorised(request):
                self.refused_requests += 1
                resp = web.Response(status=403, text='this station serves other machines only with its token '
                                                     '(the URL the station printed, ?token=...)\n')
            elif request.path == '/ws':
                return await handler(request)
            else:
                try:
                    resp = await asyncio.wait_for(handler(request), self.limits.request_timeout_s)
                except asyncio.TimeoutError:
                    resp = web.Response(status=503, text='the answer took too long\n')
                except Exception as exc:   # noqa: BLE001 (one line in the log, no traceback to the client)
                    _LOG.warning('%s %r: %s: %s', request.method, request.path[:200], type(exc).__name__,
                                 ' '.join(str(exc).split())[:200])
                    resp = web.Response(status=500, text='internal error\n')
            resp.headers.update(HEADERS)
            if request.query.get('token') and resp.status == 200 and self.token and request.path == '/':
                # The token comes once in the page's URL; from then on the cookie carries it (not in the history).
                resp = web.Response(status=302, headers={**HEADERS, 'Location': '/'})
                resp.set_cookie(COOKIE, self.token, httponly=True, samesite='Strict', path='/')
            return resp
        finally:
            if g is not None:
                g.busy -= 1
                g.last_done = time.monotonic()

    # --- routes ----------------------------------------------------------------------------------

    async def _get(self, request: web.Request) -> web.StreamResponse:
        path = request.path
        p = self.provider
        if path in ('/', '/index.html'):
            return self._static('index.html')
        if path.startswith('/static/'):
            return self._static(path[len('/static/'):])
        if path == '/status.json':
            return self._json(p.status())
        m = _TILE.match(path)
        if m:
            png = p.tile(m.group(1), int(m.group(2)), int(m.group(3)), int(m.group(4)))
            return web.Response(body=png, content_type='image/png') if png else _not_found()
        m = _BASEMAP.match(path)
        if m and self.basemap is not None:
            got = self.basemap.tile(int(m.group(1)), int(m.group(2)), int(m.group(3)))
            return web.Response(body=got[0], content_type=got[1]) if got else _not_found()
        m = _DRONE.match(path)
        if m:
            return self._json(p.geojson(m.group(1), m.group(2)), 'application/geo+json')
        m = _PLAN.match(path)
        if m:
            return self._json(p.refly_plan(m.group(1)))
        return _not_found()

    @staticmethod
    def _json(doc, ctype='application/json') -> web.Response:
        if doc is None:
            return _not_found()
        return web.Response(body=json.dumps(finite(doc)).encode(), content_type=ctype)

    @staticmethod
    def _static(rel: str) -> web.Response:
        # Names of the page's own files only: no '..', no empty, hidden or over-long parts, no NUL.
        if not _STATIC.match(rel):
            return _not_found()
        p = (STATIC / rel).resolve()
        if STATIC not in p.parents or not p.is_file():
            return _not_found()
        ctype = mimetypes.guess_type(p.name)[0] or 'application/octet-stream'
        return web.Response(body=p.read_bytes(), content_type=ctype)

    # --- push ------------------------------------------------------------------------------------

    def _payload(self, all_tiles: bool) -> str:
        status = self.provider.status()
        if self.basemap is not None:
            status['basemap'] = self.basemap.info()
        tiles = {}
        for key in status.get('drones', {}):
            since = 0 if all_tiles else self._tile_seq.get(key, 0)
            seq, changed = self.provider.tiles_since(key, since) if hasattr(self.provider, 'tiles_since') else (0, [])
            if not all_tiles:
                self._tile_seq[key] = seq
            tiles[key] = changed
        return json.dumps(finite({'type': 'status', 'status': status, 'tiles': tiles,
                                  'server_time_unix_s': time.time()}))

    async def _ws(self, request: web.Request) -> web.WebSocketResponse:
        origin = request.headers.get('Origin')
        if origin and origin.split('://', 1)[-1] != request.headers.get('Host'):
            self.refused_requests += 1
            raise web.HTTPForbidden(text='WebSocket from another origin\n')
        ws = web.WebSocketResponse(heartbeat=max(1.0, self.limits.idle_timeout_s / 2), max_msg_size=4096)
        await ws.prepare(request)
        self._clients.add(ws)
        try:
            for key in self.provider.status().get('drones', {}):   # the page loads what exists; pushes say what changes
                self._tile_seq.setdefault(key, self.provider.tiles_since(key, 0)[0]
                                          if hasattr(self.provider, 'tiles_since') else 0)
            await asyncio.wait_for(ws.send_str(self._payload(all_tiles=True)), self.limits.request_timeout_s)
            async for msg in ws:   # the page sends nothing; a close or an error ends the loop
                if msg.type in (WSMsgType.ERROR, WSMsgType.CLOSE):
                    break
        except (asyncio.TimeoutError, ConnectionError):
            pass
        finally:
            self._clients.discard(ws)
        return ws

    async def _broadcast(self) -> None:
        while True:
            try:
                await asyncio.wait_for(self._changed.wait(), self.limits.push_period_s)
            except asyncio.TimeoutError:
                pass
            await asyncio.sleep(0.5)      # gather a burst of changes into one push
            self._changed.clear()
            if not self._clients:
                continue
            try:
                text = self._payload(all_tiles=False)
            except Exception as exc:      # noqa: BLE001 (the page says so; the server goes on)
                text = json.dumps({'type': 'error', 'message': f'{type(exc).__name__}: {exc}'})
            for ws in list(self._clients):
                try:
                    await asyncio.wait_for(ws.send_str(text), self.limits.request_timeout_s)
                except (asyncio.TimeoutError, ConnectionError, RuntimeError):
                    self._clients.discard(ws)
                    await ws.close()


class _OneLine(logging.Filter):
    """aiohttp's connection errors (a malformed or over-long request: it answers 400) as one line, without the
    traceback it attaches."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.exc_info and record.exc_info[1] is not None:
            exc = record.exc_info[1]
            text = ' '.join(str(exc).split())[:200]      # one line: the client's bytes may hold line breaks
            record.msg = f'{record.getMessage()}: {type(exc).__name__}: {text}'
            record.args, record.exc_info, record.exc_text = (), None, None
            record.levelno, record.levelname = logging.INFO, 'INFO'
        return True


_LOG = logging.getLogger('photogram_ros.web')
_QUIET = logging.getLogger('photogram_ros.web.connections')
_QUIET.addFilter(_OneLine())


def _not_found() -> web.Response:
    return web.Response(status=404, text='not found\n')


def finite(obj):
    """A JSON document with NaN / infinite numbers as null and numpy scalars as Python numbers (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if hasattr(obj, 'item') and not isinstance(obj, (str, bytes)):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
