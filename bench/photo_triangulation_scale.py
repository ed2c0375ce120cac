"""`triangulate PHOTOS` scaled out: `--workers 2` (a local Dask cluster) against `--workers 1` (in process, the
baseline, measured in the same run), split-merge against the single block, and the time growth with the photos.

Data: simulated surveys made here (or reused from --sims) with the recipe of bench/photo_triangulation.py (preset
survey, 640x480, n/20 lines of 140 m, photos at 80 % forward overlap) but rendered at 0.65 fps, one frame about
every photo (the photos are the same kind; the simulation 3x faster): about 100 and 600 photos. Per survey, mode
and worker count one JSON line: wall time of reading + matching (features per photo, matching per pair) and, unless
--matching-only, of the whole triangulation with its check-point RMSE (the photos' EXIF camera with the final
self-calibration, as for a user's photos), the CPU time of this process and of its finished child processes (the
local cluster's workers), the machine's load average before and after. A split-merge run also gives the merged
block's check-point RMSE before the global adjustment and the global adjustment's solves, iterations, time and how
far it moved the cameras. Modes: 'split' (split-merge above --split-photos photos: sub-blocks as Dask tasks) and
'single' (today's one block, --split-photos 0; run with workers 1 only, and only up to --single-max photos). Then
per survey a comparison line (speedups, parallel efficiency = speedup / workers, the check-point RMSE of
split-merge against the single block, whether the matches are the same) and a growth line: the exponent b of time ~
photos^b between the smallest and the largest survey, per mode and worker count, for the wall and the CPU time (the
latter the machine's load changes less). With --repeat the worker counts alternate and the fastest run of each is
kept. --previous reads the result lines of earlier runs of this bench on the same surveys: a run they hold is not made
again and enters the comparison and growth lines as if made here (so a long run can be made apart from the others,
on an idle machine).

    .venv/bin/python bench/photo_triangulation_scale.py [--photos 100 600] [--workers 2] [--sims DIR]
        [--modes split single] [--split-photos N] [--single-max 150] [--counts 1 2] [--matching-only]
        [--repeat 1] [--previous RESULTS.jsonl ...] [--out FILE.jsonl]

Every line goes through bench/machine.py's ResultWriter (commit, clean-tree flag, cores, load) into --out (default
/tmp/photo_triangulation_scale.jsonl), and on stdout.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import ResultWriter, machine_info  # noqa: E402
from photogram_ros.core.split_merge import SplitMergeOptions  # noqa: E402
from photogram_ros.io.aerial_triangulation import TriangulateOptions  # noqa: E402
from photogram_ros.io.triangulate_action import triangulate  # noqa: E402
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


def _cpu_s() -> float:
    """CPU time of this process and of its child processes that have ended (a local cluster's workers)."""
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def _sys_s() -> float:
    """Kernel CPU time of this process and of its ended child processes (page faults, mmap, I/O)."""
    return sum(resource.getrusage(who).ru_stime for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))


def run_once(photos: Path, workers: int, matching_only: bool, split: int | None = None) -> dict:
    """One run; split: None (the options' default), 0 (never split: the single block) or a photo count."""
    row = {'workers': workers, 'mode': 'single' if split == 0 else 'split', 'data': str(photos),
           'load_before': _load()}
    t0, c0, cc0, s0 = time.perf_counter(), time.process_time(), _cpu_s(), _sys_s()
    if matching_only:
        with open_runner(workers) as runner:
            block = read_photo_block(photos, runner=runner)
        row['matching_wall_s'] = round(time.perf_counter() - t0, 2)
        if workers == 1:      # this process did all the work: its CPU time, whatever the machine's load
            row['matching_cpu_s'] = round(time.process_time() - c0, 2)
        stats = block.stats
        row['tie_tracks'] = int(sum(v for v in stats['track_lengths'].values()))
    else:
        sm = None if split == 0 else SplitMergeOptions(**({} if split is None else {'split_photos': split}))
        with tempfile.TemporaryDirectory() as out:
            res = triangulate(photos, out, TriangulateOptions(gcp=str(photos / 'gcp_list.txt'),
                                                              lever_arm_cam_m=LEVER_ARM_CAM_M, workers=workers,
                                                              split=sm),
                              log=lambda text: print(f'# {text}', file=sys.stderr, flush=True))
        row['wall_s'] = round(time.perf_counter() - t0, 2)
        row['cpu_s'] = round(_cpu_s() - cc0, 2)
        row['sys_s'] = round(_sys_s() - s0, 2)
        rep = res.report
        stats = rep['matching']
        row['matching_wall_s'] = rep['timing_s']['reading_and_matching']
        row['adjustment_s'] = rep['timing_s']['aerial_triangulation']
        ck = rep['check']['rmse']
        row.update(oriented=res.registered, tie_points=res.tie_points, check_n=ck.get('n', 0),
                   check_h_m=ck.get('horizontal_m'), check_v_m=ck.get('vertical_m'),
                   reprojection_rms_px=rep['reprojection_rms_px'], verdict=res.verdict.get('summary'))
        sc = rep.get('self_calibration') or {}
        gn = rep.get('gnss_noise') or {}
        row.update(fx_px=(sc.get('fx') or {}).get('after'), gnss_used_hv_m=[gn.get('used_h_m'), gn.get('used_v_m')],
                   gnss_rejected=len(gn.get('rejected', [])), gnss_bias_enu_m=rep['gnss'].get('estimated_bias_enu_m'))
        smr = rep.get('split_merge')
        if smr:
            row['sub_blocks'] = [{k: b[k] for k in ('photos', 'oriented', 'status', 'wall_s', 'cpu_s')}
                                 for b in smr['sub_blocks']]
            row['overlap_camera_rms_m'] = [round(o['camera_rms_m'], 4) for o in smr['overlaps']]
            row['merge_s'] = rep['timing_s'].get('merge')
            mck = smr.get('merged_check_rmse') or {}
            row['merged_check_h_m'], row['merged_check_v_m'] = mck.get('horizontal_m'), mck.get('vertical_m')
            g = smr.get('global_adjustment')
            if g:
                mv = g['camera_moves']
                row['global_adjustment'] = {
                    'status': g['status'], 'solves': g['solves'], 'iterations': g['iterations'],
                    'solve_iterations': g['solve_iterations'], 'wall_s': g['wall_s'], 'cpu_s': g['cpu_s'],
                    'observations_left_out': g['seed']['observations_left_out'],
                    'observations': g['seed']['observations'],
                    'camera_moved_rms_m': round(mv.get('centre_rms_m', 0.0), 4),
                    'camera_moved_max_m': round(mv.get('centre_max_m', 0.0), 4),
                    'attitude_moved_rms_deg': round(mv.get('attitude_rms_deg', 0.0), 5)}
    row.update(photos=stats['photos'], features_s=stats['features_s'], pairs_s=stats['matching_s'],
               pairs_tried=stats['pairs_tried'], pairs_verified=stats['pairs_verified'],
               pair_status=stats['pair_status'], track_lengths=stats['track_lengths'], load_after=_load())
    return row


def previous_results(paths: list) -> dict:
    """{(survey size, mode, workers): result line} from earlier outputs of this bench (the lines that name a
    survey's folder, fN/photos; comparisons and growth lines are left out)."""
    best = {}
    for path in paths:
        for line in Path(path).read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(row, dict) and isinstance(row.get('run'), dict):
                row = row['run']           # one run's line (written as soon as the run ends)
            if not isinstance(row, dict) or 'data' not in row or 'mode' not in row or 'workers' not in row:
                continue
            name = Path(row['data']).parent.name
            if name.startswith('f') and name[1:].isdigit():
                best[(int(name[1:]), row['mode'], int(row['workers']))] = row
    return best


def _ratio(a, b):
    return round(a / b, 3) if a is not None and b else None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--photos', type=int, nargs='+', default=[100, 600], help='survey sizes (about; photos)')
    ap.add_argument('--workers', type=int, default=2, help='local Dask workers against the in-process path')
    ap.add_argument('--sims', help='folder for the simulated surveys (kept and reused; default: a temporary one)')
    ap.add_argument('--matching-only', action='store_true',
                    help='time reading + matching only (the part on the cluster), not the adjustment')
    ap.add_argument('--modes', nargs='+', choices=('split', 'single'), default=['split', 'single'],
                    help='split: split-merge above --split-photos; single: one block (workers 1 only)')
    ap.add_argument('--split-photos', type=int, default=None, help='split-merge block size (default: the option\'s)')
    ap.add_argument('--single-max', type=int, default=150, help='run the single block only up to this many photos')
    ap.add_argument('--counts', type=int, nargs='+', default=None,
                    help='split mode: the worker counts to run (default: 1 and --workers; no comparison line '
                         'unless both)')
    ap.add_argument('--repeat', type=int, default=1, help='runs per survey and worker count (the fastest kept)')
    ap.add_argument('--previous', nargs='+', default=[],
                    help='output of earlier runs of this bench: the runs they hold are not made again')
    ap.add_argument('--out', default=None, help='the result file (JSON lines; default '
                                                '/tmp/photo_triangulation_scale.jsonl)')
    a = ap.parse_args()
    out = ResultWriter.for_bench(a.out, 'photo_triangulation_scale', ['photogram_ros', 'config'])
    tmp = None if a.sims else tempfile.TemporaryDirectory()
    sims = Path(a.sims or tmp.name)
    sims.mkdir(parents=True, exist_ok=True)
    key = 'matching_wall_s' if a.matching_only else 'wall_s'
    modes = ['split'] if a.matching_only else a.modes
    best = previous_results(a.previous)
    for n in a.photos:
        photos = simulated_photos(n, sims)
        runs = {}
        for mode in modes:
            if mode == 'single' and n > a.single_max:
                continue
            for w in ((1,) if mode == 'single' else tuple(a.counts or (1, a.workers))):
                if (n, mode, w) not in best:
                    runs[(mode, w)] = []
        for _ in range(a.repeat):           # interleaved: a change of the machine's load hits both
            for (mode, w) in runs:
                runs[(mode, w)].append(run_once(photos, w, a.matching_only,
                                                0 if mode == 'single' else a.split_photos))
                out.write({'bench': 'photo_triangulation_scale', 'run': runs[(mode, w)][-1]})
        for (mode, w), rows in runs.items():
            row = min(rows, key=lambda r: r[key])
            row.update(bench='photo_triangulation_scale', data=str(photos), runs=[r[key] for r in rows],
                       loads=[r['load_before'] for r in rows],
                       baseline='workers 1 (in process)' if w == 1 else None)
            best[(n, mode, w)] = row
            out.write(row)
        if (n, 'split', 1) not in best or (n, 'split', a.workers) not in best:
            continue
        one, many = best[(n, 'split', 1)], best[(n, 'split', a.workers)]
        cmp = {'bench': 'photo_triangulation_scale', 'compare': f'workers {a.workers} / workers 1',
               'photos': one['photos'],
               'matching_speedup': _ratio(one['matching_wall_s'], many['matching_wall_s']),
               'same_matches': all(one[k] == many[k] for k in ('pairs_tried', 'pairs_verified', 'pair_status',
                                                                 'track_lengths'))}
        if not a.matching_only:
            sp = _ratio(one['wall_s'], many['wall_s'])
            cmp.update(speedup=sp, parallel_efficiency=round(sp / a.workers, 3) if sp else None,
                       cpu_ratio=_ratio(many['cpu_s'], one['cpu_s']),
                       check_h_ratio=_ratio(many['check_h_m'], one['check_h_m']),
                       check_v_ratio=_ratio(many['check_v_m'], one['check_v_m']),
                       loads=[one['load_before'], one['load_after'], many['load_before'], many['load_after']])
            single = best.get((n, 'single', 1))
            if single:
                cmp.update(split_over_single_check_h=_ratio(one['check_h_m'], single['check_h_m']),
                           split_over_single_check_v=_ratio(one['check_v_m'], single['check_v_m']),
                           split_speedup_over_single_workers1=_ratio(single['wall_s'], one['wall_s']),
                           split_cpu_over_single=_ratio(one['cpu_s'], single['cpu_s']))
        out.write(cmp)
    if len(a.photos) > 1:
        lo, hi = min(a.photos), max(a.photos)
        growth = {'bench': 'photo_triangulation_scale', 'growth': 'time ~ photos^b'}
        for (n, mode, w), r0 in best.items():
            r1 = best.get((hi, mode, w))
            if n != lo or r1 is None:
                continue
            growth['photos'] = [r0['photos'], r1['photos']]
            span = math.log(r1['photos'] / r0['photos'])
            for k in ('matching_wall_s', 'features_s', 'pairs_s') + (() if a.matching_only else ('adjustment_s',
                                                                                                 'wall_s', 'cpu_s')):
                growth[f'b_{k}_{mode}_workers{w}'] = round(math.log(r1[k] / r0[k]) / span, 2)
        if a.matching_only:
            r0, r1 = best[(lo, 'split', 1)], best[(hi, 'split', 1)]
            growth['b_matching_cpu_s_workers1'] = round(math.log(r1['matching_cpu_s'] / r0['matching_cpu_s'])
                                                        / math.log(r1['photos'] / r0['photos']), 2)
        out.write(growth)
    out.write({'bench': 'photo_triangulation_scale', 'machine': machine_info()})
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == '__main__':
    sys.exit(main())
