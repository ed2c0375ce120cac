"""The ground station's page (web/server.py, web/static) in a real headless Chromium.

The server runs against a stand-in provider (what GroundStationNode answers: status, tiles, GeoJSON,
plan), so this test needs no ROS; tests/test_ground_station.py serves the page from the real node.
Chromium renders the page; the test looks at the screenshot (not blank, the ortho tile drawn where
its XYZ address says, the gap drawn) and at the rendered DOM (the go / no-go verdict).
"""

import json
import shutil
import subprocess
import tempfile
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from photogram_ros.core.ortho_tiles import TILE_PX
from photogram_ros.web.server import WebServer, parse_host_port

CHROMIUM = shutil.which('chromium') or shutil.which('chromium-browser')
Z, X, Y = 19, 274589, 183553          # the tile over the sample flight's origin
TILE_BGR = (40, 160, 40)              # a green tile: easy to find in the screenshot


def _tile_png() -> bytes:
    img = np.zeros((TILE_PX, TILE_PX, 4), np.uint8)
    img[..., :3] = TILE_BGR
    img[..., 3] = 255
    return cv2.imencode('.png', img)[1].tobytes()


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
        return {'limits': {'max_check_rmse_h_m': 0.05}, 'drones': {'drone1': {
            'ns': '/drone1', 'key': 'drone1', 'clouds': 3, 'points': 100, 'keyframes': 12, 'health': {},
            'ortho': {'tiles': 1, 'bytes_received': 1000, 'zoom': Z},
            'coverage': {'coverage_share': 0.91, 'largest_gap_m2': 448.0, 'forward_overlap_median': 0.85,
                         'side_overlap_min': 0.65, 'gap_list': [{'kind': 'coverage', 'area_m2': 448.0,
                                                                 'min_views': 0, 'centroid': self.gap[0]}]},
            'accuracy': {'check_rmse_h_m': 0.038, 'check_rmse_v_m': 0.015, 'check_count': 4,
                         'gcp_rmse': {'horizontal_m': 0.008, 'vertical_m': 0.002, 'count': 4},
                         'fix_share': {'rtk_fixed': 1.0, 'rtk_float': 0.0, '3d': 0.0}, 'gnss_bias_enu_m': None,
                         'control': {'gcps': 5, 'gcps_held': 1, 'gcps_full': 2, 'gcps_horizontal_only': 1,
                                     'gcps_rejected': 1, 'gcps_not_seen': 0, 'control_detections_rejected': 0,
                                     'faults': ['GCP GCP02 not used: its surveyed position is 29.78 m from <here>']}},
            'go_no_go': {'verdict': 'NO-GO', 'checks': [], 'reasons': ['largest gap (m²): 448 (<= 25)']}}}}

    def tile(self, key, z, x, y):
        return _tile_png() if (key, z, x, y) == ('drone1', Z, X, Y) else None

    def geojson(self, key, kind):
        if key != 'drone1':
            return None
        feats = {'coverage': [
            {'type': 'Feature', 'properties': {'role': 'gap', 'kind': 'coverage', 'area_m2': 448.0},
             'geometry': {'type': 'Polygon', 'coordinates': [self.gap]}},
            {'type': 'Feature', 'properties': {'role': 'survey_area'},
             'geometry': {'type': 'Polygon', 'coordinates': [self.area]}}],
            'track': [{'type': 'Feature', 'properties': {}, 'geometry': {
                'type': 'LineString', 'coordinates': [self.area[0], self.area[2]]}}],
            'targets': [{'type': 'Feature', 'geometry': {'type': 'Point', 'coordinates': self.gap[2]},
                         'properties': {'name': 'CHK01', 'role': 'check', 'residual_h_m': 0.02,
                                        'residual_v_m': 0.01, 'images': 5}}]}[kind]
        return {'type': 'FeatureCollection', 'features': feats}

    def refly_plan(self, key):
        return {'fileType': 'Plan'} if key == 'drone1' else None


@pytest.fixture
def server():
    srv = WebServer(Provider(), '127.0.0.1', 0).start()
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
    assert _get(server.url + 'static/leaflet/leaflet.js')[2].startswith(b'/* @preserve')
    for bad in (f'tiles/drone1/{Z}/{X}/{Y + 1}.png', 'drones/nobody/track.geojson', 'static/../server.py'):
        with pytest.raises(urllib.error.HTTPError) as e:
            _get(server.url + bad)
        assert e.value.code == 404
    assert parse_host_port(':8080') == ('0.0.0.0', 8080)


def chromium(url: str, out_png: Path | None, size=(1200, 800), dump_dom=False) -> str:
    profile = tempfile.mkdtemp()
    args = [CHROMIUM, '--headless', '--no-sandbox', '--disable-gpu', '--disable-background-networking',
            '--disable-component-update', '--disable-sync', '--no-first-run', f'--user-data-dir={profile}',
            '--hide-scrollbars', f'--window-size={size[0]},{size[1]}', '--virtual-time-budget=6000']
    args += ['--dump-dom'] if dump_dom else [f'--screenshot={out_png}']
    try:
        res = subprocess.run(args + [url], capture_output=True, text=True, timeout=120)
    finally:
        shutil.rmtree(profile, ignore_errors=True)
    return res.stdout


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
    dom = chromium(server.url, None, dump_dom=True)
    assert 'id="verdict-drone1"' in dom and 'NO-GO' in dom and '448' in dom
    assert '3.8 cm (4)' in dom and '91.0 %' in dom
    assert '2 / 1 / 1 / 1 of 5' in dom and 'control: GCP GCP02 not used' in dom and '&lt;here&gt;' in dom
