"""Map fusion throughput on one core, in points per second, against plain numpy binning.

The baseline bins the same points into the same cells with np.bincount (count + mean z): the
least any 2.5D gridding must do. Fusion also keeps position and colour means, z variance, runs the
speckle and pair-consistency gates and writes into tiles. JSON lines (bench/machine.py's ResultWriter: commit,
clean-tree flag, cores, load) to --out and stdout; target >= 2 M points/s.

    .venv/bin/python bench/fusion_throughput.py [--points-per-cloud 400000] [--clouds 12] [--out F]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))

from bench.machine import ResultWriter  # noqa: E402
from photogram_ros.core.fusion import Fusion, FusionConfig  # noqa: E402
from photogram_ros.core.stereo import CLOUD_DTYPE  # noqa: E402


def make_clouds(n_clouds: int, n_points: int, seed: int = 0) -> list[np.ndarray]:
    """Pair-sized clouds (48 m x 36 m footprints, 60 % forward overlap) on a hilly surface."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_clouds):
        c = np.zeros(n_points, dtype=CLOUD_DTYPE)
        c['x'] = rng.uniform(-24, 24, n_points)
        c['y'] = 14.4 * k + rng.uniform(-18, 18, n_points)
        c['z'] = 5 + 2 * np.sin(c['x'] / 7) + np.cos(c['y'] / 9) + rng.normal(0, 0.04, n_points)
        c['rgb'] = rng.integers(0, 2**24, n_points, dtype=np.uint32)
        c['confidence'] = rng.random(n_points)
        out.append(c)
    return out


def baseline(clouds, cell_m: float) -> float:
    t0 = time.perf_counter()
    for c in clouds:
        ix = np.floor(c['x'] / cell_m).astype(np.int64)
        iy = np.floor(c['y'] / cell_m).astype(np.int64)
        ix -= ix.min()
        iy -= iy.min()
        key = iy * (int(ix.max()) + 1) + ix
        cnt = np.bincount(key)
        _ = np.bincount(key, c['z']) / np.maximum(cnt, 1)
    return time.perf_counter() - t0


def fusion(clouds, cell_m: float, store_dir: str | None) -> float:
    store = None
    if store_dir:
        from photogram_ros.io.map_store import MapStore
        store = MapStore(store_dir, cell_m, 256)
    f = Fusion(FusionConfig(cell_m=cell_m, max_tiles_in_memory=24), store)
    f.add(clouds[0][:1000])      # warm-up (imports, first tile)
    t0 = time.perf_counter()
    for c in clouds:
        f.add(c)
    if store is not None:
        f.flush()
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--points-per-cloud', type=int, default=400_000)
    ap.add_argument('--clouds', type=int, default=12)
    ap.add_argument('--cell-m', type=float, default=0.08)
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--out', default=None, help='the result file (JSON lines; default /tmp/fusion_throughput.jsonl)')
    a = ap.parse_args()
    w = ResultWriter.for_bench(a.out, 'fusion_throughput', ['photogram_ros/core/fusion.py', 'photogram_ros/io/map_store.py'])
    clouds = make_clouds(a.clouds, a.points_per_cloud)
    n = a.clouds * a.points_per_cloud
    best = {'baseline': np.inf, 'fusion': np.inf, 'fusion+store': np.inf}
    for _ in range(a.repeats):     # best of N: the machine is shared, the minimum is the least disturbed
        best['baseline'] = min(best['baseline'], baseline(clouds, a.cell_m))
        best['fusion'] = min(best['fusion'], fusion(clouds, a.cell_m, None))
        with tempfile.TemporaryDirectory() as d:
            best['fusion+store'] = min(best['fusion+store'], fusion(clouds, a.cell_m, d))
    for name, s in best.items():
        w.write({'method': name, 'points': n, 'seconds': round(s, 4),
                          'points_per_s': round(n / s), 'ratio_to_baseline': round(best['baseline'] / s, 4),
                          'target_points_per_s': 2_000_000, 'meets_target': bool(n / s >= 2e6), 'repeats': a.repeats})
    return 0


if __name__ == '__main__':
    sys.exit(main())
