"""The ground station's page shows each drone's live position and GNSS track, in a real headless Chromium.

The server runs against tests/test_ground_page.py's stand-in provider (what GroundStationNode answers), given two
drones with a live position (status 'position', /drones/KEY/live.geojson as ground_station.geojson writes it:
a LineString 'track' and a Point 'position'); tests/test_ground_live_position.py checks that the node fills them
from each drone's gps/fix. Here: the marker and the track are on the map where their coordinates say, the marker
is drawn in the screenshot, and each drone's panel gives its position."""

from __future__ import annotations

import copy

import cv2
import numpy as np
import pytest

from test_ground_page import CHROMIUM, Provider, chromium, make_mbtiles

from photogram_ros.web.basemap import open_basemap
from photogram_ros.web.server import WebServer

MARKER_BGR = (0, 61, 255)      # app.js: the position marker's fill, #ff3d00

LIVE_JS = """(() => { const out = {};
  for (const [key, l] of Object.entries(layers)) {
    const got = {points: [], lines: []};
    l.live.eachLayer(x => {
      if (x.getLatLngs) got.lines.push(x.getLatLngs().map(p => [p.lng, p.lat]));
      else { const ll = x.getLatLng(); const c = map.latLngToContainerPoint(ll);
             got.points.push({lonlat: [ll.lng, ll.lat], in_view: map.getBounds().contains(ll), px: [c.x, c.y]}); }
    });
    out[key] = got;
  }
  return out; })()"""


class LiveProvider(Provider):
    """Two drones, each with a live position and a GNSS track of 6 fixes (drone2 further east)."""

    def __init__(self):
        super().__init__()
        (w, s), (e, n) = self.area[0], self.area[2]
        self.live = {}
        for i, key in enumerate(('drone1', 'drone2')):
            track = [[w + (e - w) * (0.1 + 0.12 * k), s + (n - s) * (0.3 + 0.4 * i + 0.02 * k)] for k in range(6)]
            self.live[key] = track

    def status(self):
        st = super().status()
        d1 = st['drones']['drone1']
        d1['versions']['live'] = 1
        d2 = copy.deepcopy(d1)
        d2.update(ns='/drone2', key='drone2')
        st['drones']['drone2'] = d2
        for key, d in st['drones'].items():
            lon, lat = self.live[key][-1]
            d['position'] = {'lat_deg': lat, 'lon_deg': lon, 'h_m': 562.25, 'status': 2, 'stamp_ns': 0,
                             'received_unix_s': 0.0, 'age_s': 1.2, 'track_points': len(self.live[key])}
        return st

    def geojson(self, key, kind):
        if kind != 'live':
            return super().geojson('drone1', kind)
        if key not in self.live:
            return None
        track = self.live[key]
        return {'type': 'FeatureCollection', 'features': [
            {'type': 'Feature', 'properties': {'role': 'track', 'fixes': len(track)},
             'geometry': {'type': 'LineString', 'coordinates': track}},
            {'type': 'Feature', 'properties': {'role': 'position', 'h_m': 562.25, 'status': 2, 'drone': key},
             'geometry': {'type': 'Point', 'coordinates': track[-1]}}]}


@pytest.fixture
def live_server(tmp_path):
    srv = WebServer(LiveProvider(), '127.0.0.1', 0, basemap=open_basemap(make_mbtiles(tmp_path / 'base.mbtiles')))
    srv.start()
    yield srv
    srv.stop()


@pytest.mark.skipif(CHROMIUM is None, reason='chromium is not installed (apt-get install chromium)')
def test_page_shows_each_drones_live_position_and_track(live_server, tmp_path):
    png = tmp_path / 'page.png'
    got = chromium(live_server.url, png, script=LIVE_JS)
    want = LiveProvider().live
    img = cv2.imread(str(png))
    for key in ('drone1', 'drone2'):
        [pt] = got[key]['points']
        assert pt['lonlat'] == pytest.approx(want[key][-1], abs=1e-9) and pt['in_view'], (key, pt)
        [line] = got[key]['lines']
        assert np.allclose(line, want[key], atol=1e-9), key
        # The marker drawn where the map puts it: its fill around that pixel in the screenshot.
        x, y = (int(round(v)) for v in pt['px'])
        patch = img[y - 5:y + 6, x - 5:x + 6].astype(int)
        fill = np.all(np.abs(patch - MARKER_BGR) <= 40, axis=-1)
        assert fill.sum() >= 40, (key, fill.sum(), patch[5, 5])
    dom = chromium(live_server.url, None, dump_dom=True)
    for key in ('drone1', 'drone2'):
        lon, lat = want[key][-1]
        assert f'{lat:.6f}° N {lon:.6f}° E, 562.3 m, 1 s ago, track 6 points' in dom, key
