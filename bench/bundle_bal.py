"""Solve a BAL problem with our bundle adjuster and, with --peers, with SciPy and Ceres (pycolmap).

    .venv/bin/python bench/bundle_bal.py ../shared/data/bal/problem-49-7776-pre.txt --peers [--out FILE]

One JSON line per solver: seconds, iterations, initial/final cost = 0.5 * sum of squared pixel
residuals over ALL observations (also those behind a camera, which COLMAP's own cost skips, so every
solver's result is re-evaluated here with one function), final RMS (px per observation), and ratios
against our solver. All start from the file's own values and use the same stopping rule: relative
cost decrease below --ftol (1e-4 as in the reference figures). Each solver runs --repeat times
(interleaved) and the run with the median wall time is reported, with its median CPU time (all
threads: Ceres runs 2). BLAS runs single-threaded (set before numpy loads) because a 441x441 Cholesky gains nothing from threads and loses a lot on a busy machine.
"""

from __future__ import annotations

import os

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import ResultWriter  # noqa: E402
from photogram_ros.core.bundle import BALModel, BundleOptions, bundle_adjust  # noqa: E402
from photogram_ros.io.bal import read_bal  # noqa: E402


def bal_cost(rotvec, t, intr, points, b):
    """0.5 * sum r^2 over all observations with the BAL model, and the RMS per observation."""
    R = Rotation.from_rotvec(rotvec).as_matrix()
    Pc = np.einsum('nij,nj->ni', R[b.obs_cam], points[b.obs_pt]) + t[b.obs_cam]
    uv = BALModel().project(Pc, intr[b.obs_cam], jac=False)[0]
    r = uv - b.obs_uv
    s = float(np.sum(r * r))
    return 0.5 * s, float(np.sqrt(s / len(r)))


def run_ours(b, ftol):
    prob = b.problem()
    t0, c0 = time.perf_counter(), time.process_time()
    res = bundle_adjust(prob, BundleOptions(loss='linear', refine_intrinsics=('f', 'k1', 'k2'),
                                            max_iterations=100, function_tolerance=ftol))
    sec, cpu = time.perf_counter() - t0, time.process_time() - c0
    T = res.map_T_cams
    R = np.transpose(T[:, :3, :3], (0, 2, 1))
    t = -np.einsum('cij,cj->ci', R, T[:, :3, 3])
    cost, rms = bal_cost(Rotation.from_matrix(R).as_rotvec(), t, res.intrinsics, res.points_map, b)
    return dict(solver='photogram_ros', seconds=sec, solve_cpu_seconds=cpu, iterations=res.iterations,
                final_cost=cost,
                final_rms_px=rms, status=res.status, cost_history=res.cost_history,
                # setup (structure, first cost) counts too: shift the run's clock by it
                time_history=[tt + sec - res.seconds for tt in res.time_history])


def run_scipy(b, ftol):
    """The SciPy cookbook set-up: trf, finite-difference sparse Jacobian, x_scale='jac'."""
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix
    C, P, N = len(b.cam_t), len(b.points), len(b.obs_cam)
    x0 = np.concatenate([np.hstack([b.cam_rotvec, b.cam_t, b.intrinsics]).ravel(), b.points.ravel()])

    def fun(x):
        cams = x[:9 * C].reshape(C, 9)
        pts = x[9 * C:].reshape(P, 3)
        R = Rotation.from_rotvec(cams[b.obs_cam, :3]).as_matrix()
        Pc = np.einsum('nij,nj->ni', R, pts[b.obs_pt]) + cams[b.obs_cam, 3:6]
        return (BALModel().project(Pc, cams[b.obs_cam, 6:9], jac=False)[0] - b.obs_uv).ravel()

    A = lil_matrix((2 * N, 9 * C + 3 * P), dtype=int)
    i = np.arange(N)
    for s in range(9):
        A[2 * i, b.obs_cam * 9 + s] = 1
        A[2 * i + 1, b.obs_cam * 9 + s] = 1
    for s in range(3):
        A[2 * i, 9 * C + b.obs_pt * 3 + s] = 1
        A[2 * i + 1, 9 * C + b.obs_pt * 3 + s] = 1
    t0 = time.perf_counter()
    r = least_squares(fun, x0, jac_sparsity=A, x_scale='jac', ftol=ftol, method='trf')
    sec = time.perf_counter() - t0
    cams = r.x[:9 * C].reshape(C, 9)
    cost, rms = bal_cost(cams[:, :3], cams[:, 3:6], cams[:, 6:9], r.x[9 * C:].reshape(P, 3), b)
    return dict(solver='scipy_least_squares_trf', seconds=sec, iterations=int(r.nfev), final_cost=cost,
                final_rms_px=rms, status=str(r.status))


def run_ceres(b, ftol):
    from bench_pycolmap_bal import solve_with_pycolmap
    return solve_with_pycolmap(b, ftol, bal_cost)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('problem')
    ap.add_argument('--peers', action='store_true', help='also run SciPy least_squares and Ceres (pycolmap)')
    ap.add_argument('--ftol', type=float, default=1e-4)
    ap.add_argument('--repeat', type=int, default=3, help='runs per solver, interleaved; medians reported')
    ap.add_argument('--no-scipy', action='store_true', help='with --peers, skip the (slow) SciPy peer')
    ap.add_argument('--out', default='/tmp/bundle_bal.jsonl', help='result file (JSON lines)')
    a = ap.parse_args(argv)
    writer = ResultWriter(a.out, 'bundle_bal', ['photogram_ros/core/bundle', 'photogram_ros/io/bal.py'])
    b = read_bal(a.problem)
    init, init_rms = bal_cost(b.cam_rotvec, b.cam_t, b.intrinsics, b.points, b)
    base = dict(problem=Path(a.problem).name, cameras=len(b.cam_t), points=len(b.points),
                observations=len(b.obs_cam), initial_cost=init, initial_rms_px=init_rms, repeats=a.repeat)
    solvers = [('ours', run_ours)]
    if a.peers:
        if not a.no_scipy:
            solvers.append(('scipy', run_scipy))
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        try:
            import bench_pycolmap_bal  # noqa: F401
            solvers.append(('ceres', run_ceres))
        except ImportError as exc:
            print(json.dumps(writer.write(dict(base, solver='ceres_pycolmap', error=f'pycolmap not installed '
                                               f'({exc}); pip install -r bench/requirements-peers.txt'))), flush=True)
    # Interleaved repeats so that a load change on the (shared) machine hits every solver alike.
    runs = {k: [] for k, _ in solvers}
    for _ in range(max(1, a.repeat)):
        for k, fn in solvers:
            c0 = time.process_time()
            row = fn(b, a.ftol)
            # A peer that times only its solve reports that; ours counts set-up too.
            row['cpu_seconds'] = row.pop('solve_cpu_seconds', time.process_time() - c0)
            runs[k].append(row)
    rows = []
    for k, _ in solvers:
        med = sorted(runs[k], key=lambda r: r['seconds'])[len(runs[k]) // 2]
        med['seconds_all'] = [r['seconds'] for r in runs[k]]
        med['cpu_seconds'] = float(np.median([r['cpu_seconds'] for r in runs[k]]))
        rows.append(med)
    ours = rows[0]
    hist = ours.pop('cost_history')
    hist_t = ours.pop('time_history')
    for row in rows:
        out = dict(base, **row)
        if row is not ours and 'seconds' in row:
            out['time_ratio_peer_over_ours'] = row['seconds'] / ours['seconds']
            out['time_ratio_ours_over_peer'] = ours['seconds'] / row['seconds']
            out['cpu_ratio_ours_over_peer'] = ours['cpu_seconds'] / row['cpu_seconds']
            out['cost_ratio_ours_over_peer'] = ours['final_cost'] / row['final_cost']
            # Iterations of ours needed to reach the peer's final cost (from our cost history).
            reach = [k for k, c in enumerate(hist) if c <= row['final_cost']]
            out['our_steps_to_reach_peer_cost'] = reach[0] if reach else None
            if reach:
                out['our_seconds_to_reach_peer_cost'] = hist_t[reach[0]]
                out['time_ratio_peer_over_ours_same_cost'] = row['seconds'] / hist_t[reach[0]]
        print(json.dumps(writer.write(out)), flush=True)


if __name__ == '__main__':
    main()
