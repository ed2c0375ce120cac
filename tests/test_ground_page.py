"""The ground station's page (web/server.py, web/basemap.py, web/static) in a real headless Chromium.

The server runs against a stand-in provider (what GroundStationNode answers: status, tiles, GeoJSON,
plan), so this test needs no ROS; tests/test_ground_station.py serves the page from the real node.
Chromium renders the page; the test looks at the screenshot (not blank, the ortho tile drawn where
its XYZ address says over the base map of an MBTiles file made here, the gap drawn) and at the rendered
DOM (the go / no-go verdict; target, drone and fault names holding HTML shown as text). The server's
limits: the token for other machines, idle and half-open connections closed, the connection cap.
"""

import json
import shutil
import socket
import sqlite3
import subprocess
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from photogram_ros.core.ortho_tiles import TILE_PX
from photogram_ros.web.basemap import open_basemap
from photogram_ros.web.server import WebLimits, WebServer, parse_host_port

CHROMIUM = shutil.which('chromium') or shutil.which('chromium-browser')
Z, X, Y = 19, 274589, 183553          # the tile over the sample flight's origin
TILE_BGR = (40, 160, 40)              # a green tile: easy to find in the screenshot
BASE_BGR = (200, 120, 60)             # the base map: blue-grey, everywhere around the flight
EVIL = '<img src=x onerror="document.body.dataset.pwned=1">'
SCRIPT = '<script>document.body.dataset.pwned=2</script>'
QUOTES = '"\'><svg onload=document.body.dataset.pwned=3>'
LONG = 'CHK' + 'Ω✓ü' * 400                # 1,203 characters of unicode


# Opens every tooltip of the map -> {tips: [{text, elements}], pwned}: what a name in a tooltip became.
TOOLTIPS_JS = """(() => { const out = [];
  map.eachLayer(l => { if (l.getTooltip && l.getTooltip()) l.openTooltip(
      l.getLatLng ? l.getLatLng() : l.getBounds().getCenter()); });
  document.querySelectorAll('.leaflet-tooltip').forEach(t => out.push(
    {text: t.textContent, elements: t.querySelectorAll('*').length}));
  return {tips: out, pwned: document.body.dataset.pwned || null}; })()"""


def _tile_png(bgr=TILE_BGR) -> bytes:
    img = np.zeros((TILE_PX, TILE_PX, 4), np.uint8)
    img[..., :3] = bgr
    img[..., 3] = 255
    return cv2.imencode('.png', img)[1].tobytes()


def make_mbtiles(path: Path, zooms=(15, 16, 17, 18, 19)) -> Path:
    """An MBTiles file (TMS rows) of plain BASE_BGR tiles over the 5 x 5 tiles around the test tile's area."""
    db = sqlite3.connect(path)
    db.execute('CREATE TABLE metadata (name TEXT, value TEXT)')
    db.execute('CREATE TABLE tiles (zoom_level INTEGER, tile_column INTEGER, tile_row INTEGER, tile_data BLOB)')
    db.executemany('INSERT INTO metadata VALUES (?, ?)', [('name', 'test base'), ('format', 'png'),
                                                          ('minzoom', str(zooms[0])), ('maxzoom', str(zooms[-1])),
                                                          ('attribution', '<b>test</b> tiles')])
    png = _tile_png(BASE_BGR)
    for z in zooms:
        x0, y0 = X >> (Z - z), Y >> (Z - z)
        for x in range(x0 - 2, x0 + 3):
            for y in range(y0 - 2, y0 + 3):
                db.execute('INSERT INTO tiles VALUES (?, ?, ?, ?)', (z, x, 2 ** z - 1 - y, png))
    db.commit()
    db.close()
    return path


def make_xyz(path: Path, zooms=(15, 16, 17, 18, 19)) -> Path:
    """The tiles of make_mbtiles as an XYZ folder, Z/X/Y.png (y down from the north)."""
    png = _tile_png(BASE_BGR)
    for z in zooms:
        x0, y0 = X >> (Z - z), Y >> (Z - z)
        for x in range(x0 - 2, x0 + 3):
            (path / str(z) / str(x)).mkdir(parents=True, exist_ok=True)
            for y in range(y0 - 2, y0 + 3):
                (path / str(z) / str(x) / f'{y}.png').write_bytes(png)
    return path


class Provider:
    def __init__(self):
        import morecantile
        b = morecantile.tms.get('WebMercatorQuad').bounds(morecantile.Tile(X, Y, Z))
        self.bounds = b
        w, s, e, n = b.left, b.bottom, b.right, b.top
        cx, cy = (w + e) / 2, (s + n) / 2
        self.gap = [[cx, cy], [e + (e - w) * 0.3, cy], [e + (e - w) * 0.3, n], [cx, n], [cx, cy]]
        self.area = [[w, s], [e + (e - w), s], [e + (e - w), n], [w, n], [w, s]]

    def status(self):
        return {'limits': {'max_check_rmse_h_m': 0.05}, 'unknown_drones': {'/intruder': {
                    '/intruder/map/control_points': ['/intruder/' + SCRIPT]}},
                'security': {'enabled': False, 'headline': 'DDS traffic NOT authenticated, NOT encrypted: test',
                             'summary': 'NOT AVAILABLE: test'}, 'drones': {'drone1': {
            'ns': '/drone1' + EVIL, 'key': 'drone1', 'clouds': 3, 'points': 100, 'keyframes': 12,
            'health': {'/drone1/tracker_node': [1, 'tracking lost' + SCRIPT], '/drone1/map_node': [0, 'OK']},
            'ortho': {'tiles': 1, 'bytes_received': 1000, 'zoom': Z}, 'updated_unix_s': time.time(),
            'versions': {'coverage': 1, 'track': 1, 'targets': 1},
            'unknown_publishers': {'/map/control_points': ['/fake' + SCRIPT]}, 'not_counted': {'/map/control_points': 3},
            'coverage': {'coverage_share': 0.91, 'largest_gap_m2': 448.0, 'forward_overlap_median': 0.85,
                         'side_overlap_min': 0.65, 'gap_list': [{'kind': 'coverage' + SCRIPT, 'area_m2': 448.0,
                                                                 'min_views': 0, 'centroid': self.gap[0]}]},
            'accuracy': {'check_rmse_h_m': 0.038, 'check_rmse_v_m': 0.015, 'check_count': 4,
                         'gcp_rmse': {'horizontal_m': 0.008, 'vertical_m': 0.002, 'count': 4},
                         'fix_share': {'rtk_fixed': 1.0, 'rtk_float': 0.0, '3d': 0.0}, 'gnss_bias_enu_m': None,
                         'control': {'gcps': 5, 'gcps_held': 1, 'gcps_full': 2, 'gcps_horizontal_only': 1,
                                     'gcps_rejected': 1, 'gcps_not_seen': 0, 'control_detections_rejected': 0,
                                     'faults': ['GCP GCP02 not used: its surveyed position is 29.78 m from <here>',
                                                f'GCP {QUOTES} not seen', f'GCP {LONG} not seen']}},
            'go_no_go': {'verdict': 'NO-GO', 'checks': [{'name': 'largest gap, any kind (m²)', 'value': 448.0,
                                                         'state': 'NO-GO', 'status': 'measured'}],
                         'reasons': ['largest gap, any kind (m²): 448 (<= 25)'],
                         'warnings': ['forward overlap 22 % between two keyframes of a line, below the target: '
                                      '1530 m² between them']}}}}

    def tiles_since(self, key, seq):
        return (1, [[Z, X, Y]][seq:]) if key == 'drone1' else (0, [])

    def tile(self, key, z, x, y):
        return _tile_png() if (key, z, x, y) == ('drone1', Z, X, Y) else None

    def geojson(self, key, kind):
        if key != 'drone1':
            return None
        feats = {'coverage': [
            {'type': 'Feature', 'properties': {'role': 'gap', 'kind': 'coverage' + EVIL, 'area_m2': 448.0},
             'geometry': {'type': 'Polygon', 'coordinates': [self.gap]}},
            {'type': 'Feature', 'properties': {'role': 'survey_area'},
             'geometry': {'type': 'Polygon', 'coordinates': [self.area]}}],
            'track': [{'type': 'Feature', 'properties': {}, 'geometry': {
                'type': 'LineString', 'coordinates': [self.area[0], self.area[2]]}}],
            'targets': [{'type': 'Feature', 'geometry': {'type': 'Point', 'coordinates': self.gap[2]},
                         'properties': {'name': 'CHK01' + EVIL, 'role': 'check', 'residual_h_m': 0.02,
                                        'residual_v_m': 0.01, 'images': 5}},
                        {'type': 'Feature', 'geometry': {'type': 'Point', 'coordinates': self.gap[1]},
                         'properties': {'name': 'CHK02' + QUOTES, 'role': 'check', 'residual_h_m': 0.03,
                                        'residual_v_m': 0.01, 'images': 5}},
                        {'type': 'Feature', 'geometry': {'type': 'Point', 'coordinates': self.gap[0]},
                         'properties': {'name': LONG, 'role': 'gcp', 'residual_h_m': 0.01,
                                        'residual_v_m': 0.01, 'images': 5}}]}[kind]
        return {'type': 'FeatureCollection', 'features': feats}

    def refly_plan(self, key):
        return {'fileType': 'Plan'} if key == 'drone1' else None


@pytest.fixture(params=['mbtiles', 'xyz'])
def server(tmp_path, request):
    """The page's server over an offline base map made here: an MBTiles file, or an XYZ tile folder."""
    base = make_mbtiles(tmp_path / 'base.mbtiles') if request.param == 'mbtiles' else make_xyz(tmp_path / 'xyz')
    srv = WebServer(Provider(), '127.0.0.1', 0, basemap=open_basemap(base)).start()
    yield srv
    srv.stop()


def _get(url):
    with urllib.request.urlopen(url, timeout=5) as r:
        return r.status, r.headers.get('Content-Type'), r.read()


def test_routes(server):
    code, ctype, body = _get(server.url + 'status.json')
    assert code == 200 and ctype == 'application/json'
    d = json.loads(body)['drones']['drone1']
    assert d['coverage']['gap_list'][0]['area_m2'] == 448.0 and d['accuracy']['check_rmse_h_m'] == 0.038
    code, ctype, body = _get(server.url + f'tiles/drone1/{Z}/{X}/{Y}.png')
    assert ctype == 'image/png' and body[:4] == b'\x89PNG'
    assert _get(server.url + 'static/vendor/leaflet/leaflet.js')[2].startswith(b'/* @preserve')
    for bad in (f'tiles/drone1/{Z}/{X}/{Y + 1}.png', 'drones/nobody/track.geojson', 'static/../server.py'):
        with pytest.raises(urllib.error.HTTPError) as e:
            _get(server.url + bad)
        assert e.value.code == 404
    assert _get(server.url + f'basemap/17/{X >> 2}/{Y >> 2}')[2][:4] == b'\x89PNG'     # MBTiles: rows flipped
    for bad in (f'basemap/17/{X >> 2}/{(Y >> 2) + 3}', 'basemap/40/0/0'):
        with pytest.raises(urllib.error.HTTPError):
            _get(server.url + bad)
    assert parse_host_port(':8080') == ('127.0.0.1', 8080)     # this machine unless told otherwise
    assert parse_host_port('0.0.0.0:8080') == ('0.0.0.0', 8080)
    code, ctype, body = _get(server.url)
    assert "script-src 'self'" in urllib.request.urlopen(server.url, timeout=5).headers['Content-Security-Policy']


def chromium(url: str, out_png: Path | None, size=(1200, 800), dump_dom=False, settle_s: float = 3.0,
             ready_js: str = 'document.body.dataset.updated', script: str | None = None, timeout_s: float = 90.0):
    """Load `url` in headless Chromium driven over the DevTools protocol: wait until `ready_js` is truthy
    (the page applied a pushed status), then `settle_s` for the tiles; run `script` (JS) if given; save a
    screenshot to `out_png` and return the rendered DOM (dump_dom) or the script's value."""
    import asyncio
    import base64
    import re as _re

    import aiohttp
    profile = tempfile.mkdtemp()
    args = [CHROMIUM, '--headless', '--no-sandbox', '--disable-gpu', '--disable-background-networking',
            '--disable-component-update', '--disable-sync', '--no-first-run', f'--user-data-dir={profile}',
            '--hide-scrollbars', f'--window-size={size[0]},{size[1]}', '--remote-debugging-port=0',
            '--remote-allow-origins=*', 'about:blank']
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    async def drive(port):
        async with aiohttp.ClientSession() as http:
            async with http.get(f'http://127.0.0.1:{port}/json/list') as r:
                page = next(t for t in await r.json() if t['type'] == 'page')
            async with http.ws_connect(page['webSocketDebuggerUrl'], max_msg_size=0) as ws:
                n = 0

                async def call(method, **params):
                    nonlocal n
                    n += 1
                    await ws.send_json({'id': n, 'method': method, 'params': params})
                    while True:
                        m = await ws.receive_json(timeout=timeout_s)
                        if m.get('id') == n:
                            if 'error' in m:
                                raise RuntimeError(f'{method}: {m["error"]}')
                            return m['result']

                async def js(expr):
                    r = await call('Runtime.evaluate', expression=expr, returnByValue=True, awaitPromise=True)
                    return r['result'].get('value')

                await call('Emulation.setDeviceMetricsOverride', width=size[0], height=size[1], deviceScaleFactor=1,
                           mobile=False)
                await call('Page.enable')
                await call('Page.navigate', url=url)
                t0 = time.monotonic()
                while time.monotonic() - t0 < timeout_s / 2:
                    if await js(f'Boolean(document.body && ({ready_js}))'):
                        break
                    await asyncio.sleep(0.2)
                await asyncio.sleep(settle_s)
                value = await js(script) if script else None
                if out_png is not None:
                    shot = await call('Page.captureScreenshot', format='png')
                    Path(out_png).write_bytes(base64.b64decode(shot['data']))
                if dump_dom:
                    return await js('document.documentElement.outerHTML')
                return value

    try:
        t0 = time.monotonic()
        port = None
        while port is None and time.monotonic() - t0 < 60:
            line = proc.stderr.readline()
            m = _re.search(r'DevTools listening on ws://[^:]+:(\d+)/', line)
            if m:
                port = int(m.group(1))
            elif not line and proc.poll() is not None:
                raise RuntimeError('chromium ended before it listened')
        threading.Thread(target=proc.stderr.read, daemon=True).start()   # keep its stderr pipe drained
        return asyncio.run(asyncio.wait_for(drive(port), timeout_s))
    finally:
        proc.kill()
        proc.wait(30)
        shutil.rmtree(profile, ignore_errors=True)


@pytest.mark.skipif(CHROMIUM is None, reason='chromium is not installed (apt-get install chromium)')
def test_page_renders_tiles_gap_and_verdict_in_chromium(server, tmp_path):
    png = tmp_path / 'page.png'
    chromium(server.url, png)
    img = cv2.imread(str(png))
    assert img is not None and img.shape[:2] == (800, 1200)
    assert img.std() > 10   # not blank
    mapped = img[:, :1200 - 340]
    tile = np.all(np.abs(mapped.astype(int) - TILE_BGR) <= 12, axis=-1)
    # Leaflet fits the survey area (2 tiles wide) into the map: the tile is a large square block.
    assert tile.sum() > 20000, tile.sum()
    rows, cols = np.nonzero(tile)
    assert 0.7 < np.ptp(rows) / max(np.ptp(cols), 1) < 1.4
    # The gap (red, half transparent) covers the tile's north-east quarter and beyond.
    m = mapped.astype(int)
    gap = (m[..., 2] > m[..., 1] + 40) & (m[..., 2] > m[..., 0] + 40)
    assert gap.sum() > 2000
    assert np.mean(np.nonzero(gap)[1]) > np.mean(cols) and np.mean(np.nonzero(gap)[0]) < np.mean(rows)
    # The base map (MBTiles made here) under the ortho: around the tile, not on it.
    base = np.all(np.abs(mapped.astype(int) - BASE_BGR) <= 12, axis=-1)
    assert base.sum() > 50000, base.sum()
    assert not (base & tile).any()
    dom = chromium(server.url, None, dump_dom=True)
    assert 'id="verdict-drone1"' in dom and 'NO-GO' in dom and '448' in dom
    assert '3.8 cm (4)' in dom and '91.0 %' in dom
    assert '2 / 1 / 1 / 1 of 5' in dom and 'control: GCP GCP02 not used' in dom and '&lt;here&gt;' in dom
    # Names holding HTML from the network are text on the page: nothing ran, no element was made of them.
    assert 'data-pwned' not in dom
    assert '/drone1&lt;img src=x onerror=' in dom and '&lt;script&gt;document.body' in dom
    assert '<img src="x"' not in dom and '<img src=x' not in dom
    assert 'unknown drone /intruder (not counted)' in dom and 'unknown publisher /fake' in dom
    assert '<svg onload' not in dom and 'GCP "\'&gt;&lt;svg onload=' in dom and f'GCP {LONG} not seen' in dom
    assert 'DDS traffic NOT authenticated, NOT encrypted' in dom
    assert 'drone1/tracker_node WARN: tracking lost&lt;script&gt;' in dom and 'map_node WARN' not in dom
    assert 'WARN 1' in dom and 'WARN: forward overlap 22 % between two keyframes of a line' in dom
    assert ('base map: base.mbtiles (mbtiles, zoom 15–19)' in dom or 'base map: xyz (xyz, zoom 15–19)' in dom)
    assert 'drone data' in dom


@pytest.mark.skipif(CHROMIUM is None, reason='chromium is not installed (apt-get install chromium)')
def test_tooltips_hold_names_as_text(server):
    """Leaflet's tooltips take HTML: the page escapes the target and gap names it gives them. Every tooltip
    is opened; their text holds the names, and no element came of them."""
    got = chromium(server.url, None, script=TOOLTIPS_JS)
    texts = [t['text'] for t in got['tips']]
    assert got['pwned'] is None
    assert any(t.startswith('CHK01<img src=x onerror=') for t in texts), texts
    assert any(t.startswith('coverage<img src=x') for t in texts), texts
    assert any(t.startswith('CHK02' + QUOTES) for t in texts), texts
    assert any(t.startswith(LONG[:79] + '…:') for t in texts), texts     # a long name cut in its tooltip
    assert all(t['elements'] == 0 for t in got['tips'])


def _served(srv, url, headers=None):
    req = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=5) as r:
            return r.status
    except urllib.error.HTTPError as e:
        return e.code


def _lan_address() -> str | None:
    """An address of this machine other than loopback (requests to it come from a non-loopback peer)."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(('192.0.2.1', 9))        # no packet is sent: this only picks the outgoing interface
            addr = s.getsockname()[0]
    except OSError:
        return None
    return None if addr.startswith('127.') else addr


def test_every_interface_needs_the_token():
    """0.0.0.0 without a token given: one is generated; a request from another address is refused
    without it and served with it (query once, then the cookie; or a bearer header); loopback is served."""
    srv = WebServer(Provider(), '0.0.0.0', 0).start()
    try:
        assert srv.token and len(srv.token) >= 20 and not srv.local_only
        assert _served(srv, f'http://127.0.0.1:{srv.port}/status.json') == 200
        # A loopback peer naming another host (DNS rebinding of a web page) is not this machine's user.
        assert _served(srv, f'http://127.0.0.1:{srv.port}/status.json', {'Host': 'evil.example:80'}) == 403
        lan = _lan_address()
        if lan is None:
            pytest.skip('no non-loopback address on this machine')
        base = f'http://{lan}:{srv.port}/'
        assert _served(srv, base + 'status.json') == 403
        assert _served(srv, base) == 403
        assert _served(srv, base + 'status.json?token=wrong') == 403
        assert _served(srv, base + 'status.json', {'Authorization': f'Bearer {srv.token}'}) == 200
        assert _served(srv, base + 'status.json', {'Cookie': f'gs_token={srv.token}'}) == 200
        opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor())
        with opener.open(base + f'?token={srv.token}', timeout=5) as r:   # redirected to / with the cookie
            assert r.status == 200 and r.url == base and b'leaflet.js' in r.read()
        with opener.open(base + 'status.json', timeout=5) as r:
            assert r.status == 200
        assert srv.refused_requests >= 4
    finally:
        srv.stop()
    from photogram_ros.errors import ConfigError
    for weak in ('abc', 'x' * 11, 'with blanks in it'):
        with pytest.raises(ConfigError):
            WebServer(Provider(), '0.0.0.0', 0, token=weak)
    local = WebServer(Provider(), '127.0.0.1', 0).start()
    try:
        assert local.token is None and local.local_only
    finally:
        local.stop()


def test_idle_half_open_connections_are_closed_and_capped():
    """150 connections that send half a request line and then nothing: with an idle timeout of 2 s every one
    is closed by the server within a few seconds, the cap (100) closes the 50 beyond it at once, no thread
    is started per connection, and the page is still served."""
    srv = WebServer(Provider(), '127.0.0.1', 0, limits=WebLimits(idle_timeout_s=2.0, max_connections=100)).start()
    threads0 = threading.active_count()
    socks, opened = [], []
    try:
        for _ in range(150):
            s = socket.create_connection(('127.0.0.1', srv.port), timeout=10)
            s.sendall(b'GET /status.json HT')
            socks.append(s)
            opened.append(time.monotonic())
        time.sleep(0.3)
        open_now = srv.connections
        assert open_now <= 100 and srv.refused_connections >= 50, (open_now, srv.refused_connections)
        assert threading.active_count() <= threads0 + 1
        lifetimes = []
        for s, t_open in zip(socks, opened):
            s.settimeout(max(0.1, t_open + 15 - time.monotonic()))
            try:
                if s.recv(100) == b'':
                    lifetimes.append(time.monotonic() - t_open)
            except ConnectionResetError:
                lifetimes.append(time.monotonic() - t_open)
            except socket.timeout:
                pass
        closed = len(lifetimes)
        held = sorted(lifetimes)[-100:]
        print(f'150 half-open: {open_now} held, {srv.refused_connections} refused at once; all {closed} closed, the '
              f'held ones {min(held):.1f}-{max(held):.1f} s after they opened (idle timeout 2 s)')
        assert closed == 150 and srv.connections == 0
        assert _served(srv, srv.url + 'status.json') == 200
    finally:
        for s in socks:
            s.close()
        srv.stop()
    assert WebLimits().idle_timeout_s <= 30    # the default closes an idle connection well within 60 s


def test_websocket_pushes_status_and_new_tiles():
    """A page's WebSocket gets the status at once, then a push after notify() with the tiles that changed."""
    import asyncio

    import aiohttp

    prov = Provider()
    srv = WebServer(prov, '127.0.0.1', 0).start()

    async def talk():
        async with aiohttp.ClientSession() as s:
            async with s.ws_connect(srv.url + 'ws') as ws:
                first = json.loads((await ws.receive(timeout=10)).data)
                prov.tiles_since = lambda key, seq: (2, [[Z, X, Y + 1]])
                srv.notify()
                second = json.loads((await ws.receive(timeout=10)).data)
                return first, second

    try:
        first, second = asyncio.run(talk())
    finally:
        srv.stop()
    assert first['type'] == 'status' and first['status']['drones']['drone1']['keyframes'] == 12
    assert first['tiles']['drone1'] == [[Z, X, Y]]          # everything on connect
    assert second['tiles']['drone1'] == [[Z, X, Y + 1]]     # what changed since


def test_xyz_folder_base_map_and_bad_paths(tmp_path):
    """A folder of Z/X/Y tiles (png, jpg) serves its tiles with their type; what it lacks, or what no XYZ
    address can be, is None; a missing path or an empty folder is refused when opened."""
    from photogram_ros.errors import ConfigError
    (tmp_path / 'xyz' / '17' / '5').mkdir(parents=True)
    (tmp_path / 'xyz' / '17' / '5' / '7.png').write_bytes(_tile_png(BASE_BGR))
    (tmp_path / 'xyz' / '17' / '5' / '8.jpg').write_bytes(cv2.imencode('.jpg', np.zeros((8, 8, 3), np.uint8))[1])
    bm = open_basemap(tmp_path / 'xyz')
    assert bm.info()['kind'] == 'xyz' and (bm.minzoom, bm.maxzoom) == (17, 17)
    assert bm.tile(17, 5, 7)[1] == 'image/png' and bm.tile(17, 5, 8)[1] == 'image/jpeg'
    assert bm.tile(17, 5, 9) is None and bm.tile(3, 9, 0) is None and bm.tile(40, 0, 0) is None
    for bad in (tmp_path / 'none.mbtiles', tmp_path / 'xyz' / '17' / '5'):
        with pytest.raises(ConfigError):
            open_basemap(bad)


def test_websocket_from_another_origin_is_refused(server):
    req = urllib.request.Request(server.url + 'ws', headers={
        'Origin': 'http://evil.example', 'Connection': 'Upgrade', 'Upgrade': 'websocket', 'Sec-WebSocket-Version': '13',
        'Sec-WebSocket-Key': 'dGhlIHNhbXBsZSBub25jZQ=='})
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(req, timeout=5)
    assert e.value.code == 403


def test_bad_paths_are_refused_with_4xx_and_no_traceback(server, caplog, capfd):
    """Tile and base-map addresses with huge or impossible numbers, path traversal (plain, %-encoded, overlong
    UTF-8), a NUL byte, an over-long file name or request line: each gets 4xx, nothing outside the page's
    files is served, and no traceback is logged or printed."""
    import http.client
    import logging
    caplog.set_level(logging.DEBUG)
    paths = [f'/tiles/drone1/99/{X}/{Y}.png', '/tiles/drone1/999999999999/1/1.png', '/tiles/drone1/-1/1/1.png',
             '/basemap/99/1/1', '/basemap/24/99999999999/1', '/basemap/17/1/1', '/static/../server.py',
             '/static/%2e%2e/server.py', '/static/..%2fserver.py', '/static/vendor/../../server.py',
             '/static/%c0%ae%c0%ae/server.py', '/static//etc/passwd', '//etc/passwd', '/static/%00',
             '/static/index.html%00.js', '/static/' + 'a' * 5000, '/drones/drone1/..%2f..%2fx.geojson',
             '/tiles/..%2f..%2f/1/1/1.png', '/%ff%fe', '/static/.hidden', '/' + 'x' * 20000]
    got = {}
    for p in paths:
        c = http.client.HTTPConnection('127.0.0.1', server.port, timeout=5)
        c.request('GET', p)
        r = c.getresponse()
        got[p[:60]] = (r.status, r.read())
        c.close()
    print({k: v[0] for k, v in got.items()})
    assert all(400 <= code < 500 for code, _ in got.values()), got
    assert not any(b'import' in body or b'root:' in body for _, body in got.values())
    out, err = capfd.readouterr()
    assert 'Traceback' not in out + err + caplog.text
    assert not [r for r in caplog.records if r.exc_info], [r.getMessage()[:200] for r in caplog.records]
    assert _get(server.url + 'static/vendor/leaflet/leaflet.css')[0] == 200     # the page's own files still are


def test_a_silent_websocket_is_closed():
    """A client that opens the page's WebSocket and then answers nothing (no pong: a half-open peer) is closed
    by the server's heartbeat: within 3 idle timeouts here (2 s), within 60 s with the defaults (20 s)."""
    import base64
    import os
    srv = WebServer(Provider(), '127.0.0.1', 0, limits=WebLimits(idle_timeout_s=2.0)).start()
    try:
        s = socket.create_connection(('127.0.0.1', srv.port), timeout=10)
        key = base64.b64encode(os.urandom(16)).decode()
        s.sendall(f'GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{srv.port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n'
                  f'Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n'.encode())
        s.settimeout(3 * 2.0)
        got, closed = b'', False
        try:
            while True:                      # the status, then pings this client never answers
                chunk = s.recv(65536)
                if not chunk:
                    closed = True
                    break
                got += chunk
        except ConnectionResetError:
            closed = True
        except socket.timeout:
            pass
        s.close()
        assert got.startswith(b'HTTP/1.1 101') and closed
        assert srv.connections == 0
    finally:
        srv.stop()
    assert 3 * WebLimits().idle_timeout_s <= 60
