"""`triangulate PHOTOS` scaled out: `--workers 2` (a local Dask cluster) against `--workers 1` (today's
in-process path, the baseline, measured in the same run), and the time growth with the photo count.

Data: simulated surveys made here (or reused from --sims) with the recipe of bench/photo_triangulation.py
(preset survey, 640x480, n/20 lines of 140 m, photos at 80 % forward overlap) but rendered at 0.65 fps,
one frame about every photo (the photos are the same kind; the simulation 3x faster): about 100 and 600
photos. Per survey and worker count one JSON line: wall time of reading + matching (features per photo,
matching per pair: what runs on the cluster) and, unless --matching-only, of the whole triangulation
with its check-point RMSE (the photos' EXIF camera with the final self-calibration, as for a user's
photos); the machine's load average before and after. Then per survey a comparison
line (speedups, RMSE ratio, whether the matches are the same) and a growth line: the exponent b of
time ~ photos^b between the smallest and the largest survey, per worker count (and, with
--matching-only, of the in-process path's CPU time, which the machine's load does not change). With
--repeat the worker counts alternate and the fastest run of each is kept.

    .venv/bin/python bench/photo_triangulation_scale.py [--photos 100 600] [--workers 2] [--sims DIR]
        [--matching-only] [--repeat 1]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import machine_info  # noqa: E402
from photogram_ros.io.aerial_triangulation import TriangulateOptions, triangulate  # noqa: E402
from photogram_ros.io.dask_cluster import open_runner  # noqa: E402
from photogram_ros.io.photo_block import read_photo_block  # noqa: E402

FPS = 0.65
LEVER_ARM_CAM_M = (0.0, -0.05, -0.2)   # the simulator's (0.05, 0, -0.20) m FRD in the nadir camera frame


def simulated_photos(n: int, where: Path) -> Path:
    """A simulated survey of about `n` photos in where/fN (made once, reused)."""
    from photogram_ros.sim.scenario import preset, simulate
    out = where / f'f{n}'
    if not (out / 'photos' / 'gcp_list.txt').exists():
        t0 = time.perf_counter()
        simulate(preset('survey', photos=True, fps=FPS, n_lines=max(2, round(n / 20)), line_length_m=140.0), out)
        print(f'# simulated {out}: {time.perf_counter() - t0:.0f} s', file=sys.stderr, flush=True)
    return out / 'photos'


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def run_once(photos: Path, workers: int, matching_only: bool) -> dict:
    row = {'workers': workers, 'load_before': _load()}
    t0, c0 = time.perf_counter(), time.process_time()
    if matching_only:
        with open_runner(workers) as runner:
            block = read_photo_block(photos, runner=runner)
        row['matching_wall_s'] = round(time.perf_counter() - t0, 2)
        if workers == 1:      # this process did all the work: its CPU time, whatever the machine's load
            row['matching_cpu_s'] = round(time.process_time() - c0, 2)
        stats = block.stats
        row['tie_tracks'] = int(sum(v for v in stats['track_lengths'].values()))
    else:
        with tempfile.TemporaryDirectory() as out:
            res = triangulate(photos, out, TriangulateOptions(gcp=str(photos / 'gcp_list.txt'),
                                                              lever_arm_cam_m=LEVER_ARM_CAM_M, workers=workers))
        row['wall_s'] = round(time.perf_counter() - t0, 2)
        rep = res.report
        stats = rep['matching']
        row['matching_wall_s'] = rep['timing_s']['reading_and_matching']
        row['adjustment_s'] = rep['timing_s']['aerial_triangulation']
        ck = rep['check']['rmse']
        row.update(oriented=res.registered, tie_points=res.tie_points, check_n=ck.get('n', 0),
                   check_h_m=ck.get('horizontal_m'), check_v_m=ck.get('vertical_m'),
                   reprojection_rms_px=rep['reprojection_rms_px'])
    row.update(photos=stats['photos'], features_s=stats['features_s'], pairs_s=stats['matching_s'],
               pairs_tried=stats['pairs_tried'], pairs_verified=stats['pairs_verified'],
               pair_status=stats['pair_status'], track_lengths=stats['track_lengths'], load_after=_load())
    return row


def _ratio(a, b):
    return round(a / b, 3) if a is not None and b else None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--photos', type=int, nargs='+', default=[100, 600], help='survey sizes (about; photos)')
    ap.add_argument('--workers', type=int, default=2, help='local Dask workers against the in-process path')
    ap.add_argument('--sims', help='folder for the simulated surveys (kept and reused; default: a temporary one)')
    ap.add_argument('--matching-only', action='store_true',
                    help='time reading + matching only (the part on the cluster), not the adjustment')
    ap.add_argument('--repeat', type=int, default=1, help='runs per survey and worker count (the fastest kept)')
    a = ap.parse_args()
    tmp = None if a.sims else tempfile.TemporaryDirectory()
    sims = Path(a.sims or tmp.name)
    sims.mkdir(parents=True, exist_ok=True)
    key = 'matching_wall_s' if a.matching_only else 'wall_s'
    best = {}
    for n in a.photos:
        photos = simulated_photos(n, sims)
        runs = {1: [], a.workers: []}
        for _ in range(a.repeat):           # interleaved: a change of the machine's load hits both
            for w in runs:
                runs[w].append(run_once(photos, w, a.matching_only))
        for w, rows in runs.items():
            row = min(rows, key=lambda r: r[key])
            row.update(bench='photo_triangulation_scale', data=str(photos), runs=[r[key] for r in rows],
                       loads=[r['load_before'] for r in rows], baseline='workers 1 (in process)' if w == 1 else None)
            best[(n, w)] = row
            print(json.dumps(row), flush=True)
        one, many = best[(n, 1)], best[(n, a.workers)]
        cmp = {'bench': 'photo_triangulation_scale', 'compare': f'workers {a.workers} / workers 1',
               'photos': one['photos'],
               'matching_speedup': _ratio(one['matching_wall_s'], many['matching_wall_s']),
               'same_matches': all(one[k] == many[k] for k in ('pairs_tried', 'pairs_verified', 'pair_status',
                                                                 'track_lengths'))}
        if not a.matching_only:
            cmp.update(speedup=_ratio(one['wall_s'], many['wall_s']),
                       check_h_ratio=_ratio(many['check_h_m'], one['check_h_m']),
                       check_v_ratio=_ratio(many['check_v_m'], one['check_v_m']))
        print(json.dumps(cmp), flush=True)
    if len(a.photos) > 1:
        lo, hi = min(a.photos), max(a.photos)
        growth = {'bench': 'photo_triangulation_scale', 'growth': 'time ~ photos^b',
                  'photos': [best[(lo, 1)]['photos'], best[(hi, 1)]['photos']]}
        for w in (1, a.workers):
            r0, r1 = best[(lo, w)], best[(hi, w)]
            span = math.log(r1['photos'] / r0['photos'])
            for k in ('matching_wall_s', 'features_s', 'pairs_s') + (() if a.matching_only else ('adjustment_s',
                                                                                                 'wall_s')):
                growth[f'b_{k}_workers{w}'] = round(math.log(r1[k] / r0[k]) / span, 2)
        if a.matching_only:
            r0, r1 = best[(lo, 1)], best[(hi, 1)]
            growth['b_matching_cpu_s_workers1'] = round(math.log(r1['matching_cpu_s'] / r0['matching_cpu_s'])
                                                        / math.log(r1['photos'] / r0['photos']), 2)
        print(json.dumps(growth), flush=True)
    print(json.dumps({'bench': 'photo_triangulation_scale', 'machine': machine_info()}), flush=True)
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == '__main__':
    sys.exit(main())
