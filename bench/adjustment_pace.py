"""The adjustment stage's cost per keyframe (stages/adjustment.py over core/incremental.py), this tree against a
baseline tree (main) in the same run.

Each keyframe goes into `AdjustmentStage` as bundle_node feeds it (its fix, then its features) and `drain()`
adjusts it at once, as the node's worker does when nothing queues up; each tree runs in a process of its own
(PYTHONPATH = that tree), the trees alternating, `--repeats` times. Per keyframe: the worker thread's CPU time
for the whole keyframe path (`cpu_ms`) and up to the call that hands out its poses (`cpu_to_pose_ms`, the
pose lag's share of the adjuster on an idle core); per run: the window solves' iterations, the keyframe the
first pose came with, the final adjustment's reprojection RMS and, on the simulated flight, the camera centres'
errors against the truth in flight (the pose each keyframe's own update published) and after the final
adjustment.

Sets: toledo (../shared/data/photos/toledo: 42 DJI photos, EXIF GPS; its KeyframeBlock from
io/photo_block.read_photo_block, cached in --cache as a pickle), sample (the simulator's sample flight, about 76
keyframes, RTK fixes, with truth).

    .venv/bin/python bench/adjustment_pace.py [--sets toledo,sample] [--base-ref main] [--repeats 2]
        [--cache /tmp/adjustment_pace] [--results bench/results]
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / 'shared' / 'data'
SETS = {'toledo': DATA / 'photos' / 'toledo' / 'images'}


# --- the worker (runs under the tree being measured) -------------------------------------------------------

def _load(name: str, cache: Path):
    """(camera, [(stamp_ns, record)], truth {stamp: map_T_cam} or None, truth origin or None)."""
    if name == 'sample':
        from photogram_ros.sim.observations import simulate_keyframes
        from photogram_ros.sim.scenario import preset
        sk = simulate_keyframes(preset('sample'), keyframe_interval_s=1.0, attitude_sigma_deg=None)
        recs = [(r.stamp_ns, r) for r in sk.records]
        return sk.camera, recs, dict(zip([s for s, _ in recs], sk.true_map_T_cam)), sk.origin, \
            [float(v) for v in sk.lever_arm_cam_m]
    path = cache / f'{name}.pkl'
    with open(path, 'rb') as f:
        block = pickle.load(f)
    # One photo a second, in file-name order (the flight's).
    return block.camera, [(i * 10**9, r) for i, r in enumerate(block.records)], None, None, [0.0, 0.0, 0.0]


def worker(name: str, cache: Path) -> dict:
    import photogram_ros
    from photogram_ros.core.gnss_fix import COV_DIAGONAL_KNOWN, STATUS_FIX, STATUS_GBAS_FIX
    from photogram_ros.params import from_dict
    from photogram_ros.stages.adjustment import (AdjustmentParams, AdjustmentStage, DiagnosticsLog,
                                                 RecordedOutputs)
    camera, recs, truth, truth_origin, lever = _load(name, cache)
    status = STATUS_GBAS_FIX if truth is not None else STATUS_FIX

    class Timed(RecordedOutputs):
        def __init__(self):
            super().__init__()
            self.pose_cpu = None

        def poses(self, poses):
            if self.pose_cpu is None:
                self.pose_cpu = time.thread_time()
            super().poses(poses)

    out = Timed()
    stage = AdjustmentStage(from_dict(AdjustmentParams, {'lever_arm_cam_m': lever}), DiagnosticsLog(), out)
    stage.set_camera(camera)
    cpu, to_pose, inflight, first_pose = [], [], {}, None
    for i, (stamp, r) in enumerate(recs):
        f = r.fix
        stage.add_fix(stamp, f.lat_deg, f.lon_deg, f.h_m, np.diag(np.diag(f.cov_enu_m2)), status, COV_DIAGONAL_KNOWN)
        stage.add_keyframe(stamp, r.track_ids, r.uv)
        out.pose_cpu = None
        c0 = time.thread_time()
        stage.drain()
        c1 = time.thread_time()
        cpu.append(c1 - c0)
        if out.pose_cpu is not None:
            to_pose.append(out.pose_cpu - c0)
            first_pose = i if first_pose is None else first_pose
        if stamp in out.pose_by_stamp:
            inflight.setdefault(stamp, out.pose_by_stamp[stamp][0].copy())
    c0 = time.thread_time()
    outcome = stage.finish()
    finish_s = time.thread_time() - c0
    solves = stage.at.adjustment.solve_log()
    row = {'set': name, 'package': str(Path(photogram_ros.__file__).parent.parent), 'keyframes': len(recs),
           'oriented': int(stage.at.block.n_oriented), 'final': outcome.status,
           'first_pose_keyframe': first_pose,
           'cpu_ms': _stats(cpu), 'cpu_to_pose_ms': _stats(to_pose), 'cpu_total_s': round(float(sum(cpu)), 2),
           'finish_cpu_s': round(finish_s, 2),
           'solve_iterations_median': float(np.median([s['iterations'] for s in solves])) if solves else None,
           'final_rms_px': stage.diag.values.get('full_adjustment_rms_px'),
           'block_gnss_fit_h_m': stage.diag.values.get('block_gnss_fit_h_m')}
    if truth is not None:
        o = stage.at.origin

        def err(T, s):
            return float(np.linalg.norm(truth_origin.ecef_to_enu(o.enu_to_ecef(T[:3, 3])) - truth[s][:3, 3]))
        e_in = [err(T, s) for s, T in inflight.items()]
        e_fin = [err(T, s) for s, (T, _) in out.pose_by_stamp.items()]
        row['inflight_error_m'] = _stats(e_in, 3, 1.0)
        row['final_error_m'] = _stats(e_fin, 3, 1.0)
    return row


def _stats(v, nd: int = 1, scale: float = 1e3) -> dict:
    if not len(v):
        return {'n': 0}
    a = np.asarray(v, float) * scale
    return {'n': len(a), 'median': round(float(np.median(a)), nd), 'p95': round(float(np.percentile(a, 95)), nd),
            'max': round(float(a.max()), nd)}


# --- the driver ---------------------------------------------------------------------------------------------

def _base_tree(ref: str, where: Path) -> tuple[Path, str]:
    """`ref` exported (git archive) into `where`/<commit>; (path, short commit)."""
    commit = subprocess.run(['git', 'rev-parse', '--short', ref], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout.strip()
    tree = where / f'base_{commit}'
    if not (tree / 'photogram_ros').is_dir():
        tree.mkdir(parents=True, exist_ok=True)
        arc = subprocess.run(['git', 'archive', ref, 'photogram_ros'], cwd=ROOT, capture_output=True, check=True)
        subprocess.run(['tar', '-x', '-C', str(tree)], input=arc.stdout, check=True)
    return tree, commit


def _cache_set(name: str, cache: Path) -> None:
    if name == 'sample' or (cache / f'{name}.pkl').is_file():
        return
    from photogram_ros.io.photo_block import read_photo_block
    block = read_photo_block(SETS[name])
    with open(cache / f'{name}.pkl', 'wb') as f:
        pickle.dump(block, f)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--sets', default='toledo,sample')
    ap.add_argument('--base-ref', default='main')
    ap.add_argument('--repeats', type=int, default=2)
    ap.add_argument('--cache', default='/tmp/adjustment_pace')
    ap.add_argument('--results', default=str(ROOT / 'bench' / 'results'))
    ap.add_argument('--worker', help=argparse.SUPPRESS)
    a = ap.parse_args()
    cache = Path(a.cache)
    if a.worker:
        print(json.dumps(worker(a.worker, cache)))
        return 0
    sys.path.insert(0, str(ROOT / 'bench'))
    from machine import ResultWriter, machine_info, tree_state
    cache.mkdir(parents=True, exist_ok=True)
    base, base_commit = _base_tree(a.base_ref, cache)
    head = tree_state()['commit'][:7]
    trees = {'base': base, 'new': ROOT}
    out = Path(a.results) / f'adjustment_pace_{head}.jsonl'
    env0 = {**os.environ, 'OMP_NUM_THREADS': '1', 'OPENBLAS_NUM_THREADS': '1'}
    with ResultWriter(out, 'adjustment_pace', modules=['photogram_ros/stages/adjustment.py',
                                                       'photogram_ros/core/at_problem.py',
                                                       'photogram_ros/core/incremental.py']) as w:
        w.write({'what': f'the adjustment stage per keyframe: base {a.base_ref} ({base_commit}, git archive) and '
                         f'this tree alternating, {a.repeats} repeats, one process each, OMP/OpenBLAS 1 thread',
                 'base_commit': base_commit, 'machine': machine_info(),
                 'command': ' '.join(['.venv/bin/python', 'bench/adjustment_pace.py', *sys.argv[1:]])})
        for name in a.sets.split(','):
            _cache_set(name, cache)
            rows = {'base': [], 'new': []}
            for rep in range(a.repeats):
                for label, tree in trees.items():
                    env = {**env0, 'PYTHONPATH': str(tree)}
                    t0 = time.time()
                    r = subprocess.run([sys.executable, str(Path(__file__).resolve()), '--worker', name,
                                        '--cache', str(cache)], env=env, capture_output=True, text=True,
                                       timeout=3600)
                    if r.returncode:
                        print(r.stderr[-3000:], file=sys.stderr)
                        raise SystemExit(f'{label} worker failed on {name}')
                    row = json.loads(r.stdout.strip().splitlines()[-1])
                    row.update(tree=label, repeat=rep, wall_s=round(time.time() - t0, 1),
                               code=base_commit if label == 'base' else head)
                    rows[label].append(row)
                    print(json.dumps(w.write(row)), flush=True)

            def med(label, key, sub='median'):
                return float(np.median([r[key][sub] if sub else r[key] for r in rows[label]]))
            summary = {'set': name, 'summary': True}
            for key, sub in (('cpu_ms', 'median'), ('cpu_ms', 'p95'), ('cpu_to_pose_ms', 'median'),
                             ('cpu_to_pose_ms', 'p95'), ('cpu_total_s', None)):
                b, n = med('base', key, sub), med('new', key, sub)
                summary[f'{key}{"_" + sub if sub else ""}'] = {'base': b, 'new': n, 'ratio': round(n / b, 3)}
            print(json.dumps(w.write(summary)), flush=True)
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
