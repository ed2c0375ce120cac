"""The final matching's pair strategy against the stereo node's, on the same in-flight map folder in the same run:
pairs matched, densify seconds, seconds per pair (the ratio is the cost per pair of the new strategy) and the
share of the camera centres' hull whose fused cells two pairs confirm (what export's min_pairs 2 keeps).

"before" plans the final matching as the stereo node plans in flight (final_pairs_along / _across and
final_min_overlap set to the node's max_pairs_along / _across and min_overlap); "now" uses the final_*
criteria (core/pairs.PairCriteria.for_final). Both take the stereo_node / map_node sections of `--params`
(config/replay.yaml by default). Each variant runs `--repeat` times, alternating; the best time is kept.
Prints one JSON line per map.

    .venv/bin/python bench/products_pairs.py OUT/map [OUT/map ...] [--repeat 1]

(a replay's in-flight map folder, e.g. `photogram-ros replay ../shared/data/photos/brighton_beach/images --out OUT`)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time

import cv2
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))

from photogram_ros.commands.products import _core_params  # noqa: E402
from photogram_ros.core.fusion import FusionConfig  # noqa: E402
from photogram_ros.core.pairs import PairCriteria  # noqa: E402
from photogram_ros.core.stereo import StereoParams  # noqa: E402
from photogram_ros.io.densify import densify_map  # noqa: E402
from photogram_ros.io.export import open_map  # noqa: E402
from photogram_ros.params import load_params_file  # noqa: E402


def confirmed_share(store, cell_m: float) -> float:
    """Share of the camera centres' hull (map x, y) whose fused cells hold n_pairs >= 2."""
    C = np.array([k['map_T_cam'][:3, 3] for k in store.keyframes()])
    x0, y0 = C[:, 0].min(), C[:, 1].min()
    W, H = int((C[:, 0].max() - x0) / cell_m) + 1, int((C[:, 1].max() - y0) / cell_m) + 1
    hull = np.zeros((H, W), np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(((C[:, :2] - (x0, y0)) / cell_m).round().astype(np.int32)), 1)
    p = open_map(store)[1].points()
    c, r = ((p['x'] - x0) / cell_m).astype(int), ((p['y'] - y0) / cell_m).astype(int)
    ok = (c >= 0) & (r >= 0) & (c < W) & (r < H) & (p['n_pairs'] >= 2)
    got = np.zeros((H, W), bool)
    got[r[ok], c[ok]] = True
    return float(got[hull > 0].mean())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('maps', nargs='+', help='in-flight map folders (a replay\'s OUT/map)')
    ap.add_argument('--params', default='config/replay.yaml')
    ap.add_argument('--repeat', type=int, default=1)
    a = ap.parse_args()
    sections = load_params_file(a.params)
    stereo = _core_params(StereoParams, sections.get('stereo_node', {}), a.params)
    now = _core_params(PairCriteria, sections.get('stereo_node', {}), a.params)
    before = dataclasses.replace(now, final_pairs_along=now.max_pairs_along, final_pairs_across=now.max_pairs_across,
                                 final_min_overlap=now.min_overlap)
    fusion = _core_params(FusionConfig, sections.get('map_node', {}), a.params)
    for m in a.maps:
        got = {}
        with tempfile.TemporaryDirectory() as tmp:
            for _ in range(a.repeat):
                for name, crit in (('before', before), ('now', now)):
                    t0 = time.perf_counter()
                    d = densify_map(m, os.path.join(tmp, name), stereo, crit, fusion)
                    s = time.perf_counter() - t0
                    if name not in got or s < got[name]['s']:
                        got[name] = {'pairs': d.pairs_done, 's': round(s, 2),
                                     's_per_pair': round(s / max(d.pairs_done, 1), 3),
                                     'confirmed_in_hull': round(confirmed_share(d.store, d.store.cell_m), 3)}
        print(json.dumps({'bench': 'products_pairs', 'map': m, **got,
                          'ratio_per_pair': round(got['now']['s_per_pair'] / got['before']['s_per_pair'], 2),
                          'ratio_total': round(got['now']['s'] / got['before']['s'], 2),
                          'load': round(os.getloadavg()[0], 1)}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
