"""Time of the survey products of a map folder with the filled DSM, its band 2 and the DTM, against the
products as they were before (a measured-only DSM, no DTM), in the same run on the same map.

The baseline is export_map with DsmParams(fill=False) and without 'dtm': the DSM of the measured cells
and the ortho draped on it, as the products were made before the fill and the DTM. Each variant runs
`--repeat` times, alternating, and the best time of each is kept. Prints JSON lines; target: the
products within 2x their time before.

    .venv/bin/python bench/products_time.py OUT/map_final [OUT/map_final ...] [--repeat 2]

(a replay's map_final, e.g. `photogram-ros replay ../shared/data/photos/brighton_beach/images --out OUT`)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))

from photogram_ros.core.geodesy import utm_epsg  # noqa: E402
from photogram_ros.io.export import DsmParams, export_map  # noqa: E402
from photogram_ros.io.map_store import MapStore  # noqa: E402

BEFORE = ('las', 'laz', 'ply', 'dsm', 'ortho')
NOW = ('las', 'laz', 'ply', 'dsm', 'dtm', 'ortho')


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('maps', nargs='+', help='map folders (a replay\'s OUT/map_final)')
    ap.add_argument('--repeat', type=int, default=2)
    a = ap.parse_args()
    for m in a.maps:
        store = MapStore(m)
        crs = f'EPSG:{utm_epsg(store.origin.lat_deg, store.origin.lon_deg)}'
        best = {'before': float('inf'), 'now': float('inf')}
        shares = {}
        with tempfile.TemporaryDirectory() as tmp:
            for _ in range(a.repeat):
                for name, products, dsm in (('before', BEFORE, DsmParams(fill=False)), ('now', NOW, DsmParams())):
                    t0 = time.perf_counter()
                    r = export_map(store, os.path.join(tmp, name), crs, products=products, min_pairs=2, dsm=dsm)
                    best[name] = min(best[name], time.perf_counter() - t0)
                    shares[name] = {'dsm': r.dsm.get('camera_hull'), 'ortho': (r.ortho or {}).get('camera_hull')}
        print(json.dumps({'bench': 'products_time', 'map': m, 'before_s': round(best['before'], 2),
                          'now_s': round(best['now'], 2), 'ratio': round(best['now'] / best['before'], 2),
                          'camera_hull_before': shares['before'], 'camera_hull_now': shares['now'],
                          'load': round(os.getloadavg()[0], 1)}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
