"""CPU of one keyframe's cloud on the 20 MP sim flight, split by step: stereo_pair's phases and the map's fusion.

Reads a map folder kept by `bench/inflight_20mp.py --keep DIR` (DIR/1s/replay/map: the keyframes' full-resolution
JPEGs and final poses, the camera), decodes each keyframe at the reduction the tracker sends to stereo (libjpeg's
DCT scaling, 4 for 20 MP), plans each keyframe's pairs with the stereo node's own planner and parameters against
the keyframes before it (the ground: --ground-m, or the median height of the map's
fused cells; the map's fused cells stand in for the tie points that narrow it) and matches them; then fuses the clouds in a fresh Fusion with the map's cell. Prints one JSON line:
process CPU ms per pair and per cloud fused, the phases' wall ms (medians), points per cloud.
`--set name=value` overrides a StereoNodeParams field; `--baseline-set` runs the baseline's settings first on the
same pairs, alternating pair by pair (the ratio is new / baseline, measured in the same run).

    PYTHONPATH=$PWD .venv/bin/python bench/cloud_pair_cost.py /tmp/keep/1s/replay/map --pairs 20 \
        --set lr_check=false --out bench/results/cloud_pair_cost_<commit>.jsonl
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import fields, replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import ResultWriter  # noqa: E402
from photogram_ros.core import gsd, stereo  # noqa: E402
from photogram_ros.core.fusion import Fusion, FusionConfig  # noqa: E402
from photogram_ros.core.pairs import plan_pairs  # noqa: E402
from photogram_ros.io.map_store import MapStore  # noqa: E402
from photogram_ros.nodes.stereo_node import StereoNodeParams  # noqa: E402

REDUCED = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
           8: cv2.IMREAD_REDUCED_COLOR_8}


def _overrides(items: list[str]) -> dict:
    kinds = {f.name: f.type for f in fields(StereoNodeParams)}
    out = {}
    for item in items:
        k, _, v = item.partition('=')
        if k not in kinds:
            raise SystemExit(f'unknown stereo parameter {k}')
        out[k] = json.loads(v) if v[:1] in '-0123456789tf[' else v
    return out


def _ground_m(store: MapStore) -> float:
    zs = []
    for key in store.tile_keys()[:50]:
        cells = store.load_tile(key)
        if cells is not None:
            n = cells['n'] > 0
            zs.append(np.asarray(cells['z'][n], float))
    if not zs:
        raise SystemExit('the map holds no fused cells: pass --ground-m')
    return float(np.median(np.concatenate(zs)))


def _tie_points(store: MapStore, n: int = 20000) -> np.ndarray:
    """Stand-ins for the sparse cloud: `n` of the map's fused cells (x, y, z in map), for the pairs' depth search."""
    t = store.cell_m * int(store.meta['tile_cells'])
    out = []
    for key in store.tile_keys():
        cells = store.load_tile(key)
        if cells is None:
            continue
        idx = np.flatnonzero(cells['n'] > 0)
        out.append(np.column_stack([cells['x'][idx] + key[0] * t, cells['y'][idx] + key[1] * t, cells['z'][idx]]))
    xyz = np.concatenate(out) if out else np.zeros((0, 3))
    return xyz[np.random.default_rng(0).choice(len(xyz), min(n, len(xyz)), replace=False)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('map_dir')
    ap.add_argument('--pairs', type=int, default=16, help='keyframe pairs to match (from --start)')
    ap.add_argument('--start', type=int, default=60, help='first keyframe (flight order) to pair')
    ap.add_argument('--reduction', type=int, default=4, choices=sorted(REDUCED))
    ap.add_argument('--ground-m', type=float, default=float('nan'))
    ap.add_argument('--set', action='append', default=[], metavar='NAME=VALUE')
    ap.add_argument('--baseline-set', action='append', default=None, metavar='NAME=VALUE',
                    help='also run these settings (may be none: --baseline-set "") alternately, as the baseline')
    ap.add_argument('--cv-threads', type=int, default=1, help='OpenCV threads (the bench\'s stereo.cv_threads: 1)')
    ap.add_argument('--label', default='')
    ap.add_argument('--out', default='')
    a = ap.parse_args()
    store = MapStore(a.map_dir)
    cam = store.load_camera()
    kfs = store.keyframes()
    ground = a.ground_m if np.isfinite(a.ground_m) else _ground_m(store)
    heights = [k['map_T_cam'][2, 3] - ground for k in kfs]
    settings = gsd.derive(cam.width, cam.height, cam.fx, float(np.median(heights)))
    configs = {'new': _overrides(a.set)}
    if a.baseline_set is not None:
        configs = {'baseline': _overrides([s for s in a.baseline_set if s]), **configs}
    params = {}
    for name, over in configs.items():
        p, _ = gsd.resolve(replace(StereoNodeParams(), **over), settings)
        params[name] = p
    small = cam.scaled(1.0 / a.reduction)
    cv2.setNumThreads(a.cv_threads)
    ties = _tie_points(store)
    images: dict[int, np.ndarray] = {}

    def image(i):
        if i not in images:
            images[i] = cv2.imread(str(kfs[i]['image_path']), REDUCED[a.reduction])
        return images[i]

    jobs = []
    for i in range(a.start, len(kfs)):
        if len(jobs) >= a.pairs:
            break
        others = {j: kfs[j]['map_T_cam'] for j in range(max(0, i - 40), i)}
        p = params['new']
        plan = plan_pairs(small, kfs[i]['map_T_cam'], others, ground, p, (p.min_depth_m, p.max_depth_m), ties)
        jobs += [(pp.other, i, pp.depth_range_m) for pp in plan.pairs]
    jobs = jobs[:a.pairs]
    res: dict[str, dict[str, list]] = {n: {'cpu_ms': [], 'wall_ms': [], 'points': [], 'fuse_cpu_ms': []}
                                       for n in configs}
    phases: dict[str, dict[str, list]] = {n: {} for n in configs}
    fusion = {n: Fusion(FusionConfig(cell_m=settings.cell_m)) for n in configs}
    for j, i, depth in jobs:
        for name in configs:
            p = gsd.for_reduced_images(params[name], a.reduction)
            c0, w0 = time.process_time(), time.perf_counter()
            r = stereo.stereo_pair(small, image(j), kfs[j]['map_T_cam'], image(i), kfs[i]['map_T_cam'], p, depth)
            c1, w1 = time.process_time(), time.perf_counter()
            if not r.ok:
                continue
            fusion[name].add(r.cloud)
            c2 = time.process_time()
            res[name]['cpu_ms'].append((c1 - c0) * 1e3)
            res[name]['wall_ms'].append((w1 - w0) * 1e3)
            res[name]['fuse_cpu_ms'].append((c2 - c1) * 1e3)
            res[name]['points'].append(int(r.cloud.size))
            for k, v in r.timings_ms.items():
                phases[name].setdefault(k, []).append(v)
    writer = ResultWriter(a.out, 'cloud_pair_cost', modules=['photogram_ros/core/stereo.py',
                                                             'photogram_ros/core/fusion.py']) if a.out else None
    row = {'label': a.label, 'map_dir': a.map_dir, 'reduction': a.reduction, 'pairs_planned': len(jobs),
           'ground_m': round(ground, 2), 'gsd': settings.summary(), 'threads_cv': cv2.getNumThreads()}
    for name in configs:
        r = res[name]
        row[name] = {'set': configs[name], 'pairs_ok': len(r['cpu_ms']),
                     **{f'{k}_median': round(float(np.median(v)), 1) for k, v in r.items() if v},
                     'phases_wall_ms_median': {k: round(float(np.median(v)), 1) for k, v in phases[name].items()},
                     'cells_fused': int(sum(t.f['n'].astype(bool).sum() for t in fusion[name].tiles.values()))}
    if 'baseline' in res and res['baseline']['cpu_ms'] and res['new']['cpu_ms']:
        row['cpu_ratio_new_to_baseline'] = round(float(np.median(res['new']['cpu_ms']) /
                                                       np.median(res['baseline']['cpu_ms'])), 3)
    print(json.dumps(row))
    if writer is not None:
        writer.write(row)
    return 0


if __name__ == '__main__':
    sys.exit(main())
