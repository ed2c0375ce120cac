"""Sliding-window update latency as a flight grows to 500 keyframes.

A synthetic lawnmower flight (40 m height, 520 px focal, 640x480, ~300 tracked ground points per
keyframe, 0.3 px noise, RTK-like fixes) is fed keyframe by keyframe to IncrementalAT with a
10-keyframe window. Each update (PnP, triangulation, window adjustment) is timed; the baseline in
the same run is a full adjustment of the whole block at the end, i.e. what a non-windowed system
would pay per keyframe. JSON lines (bench/machine.py's ResultWriter: commit, clean-tree flag, cores, load) to
--out and stdout: latency per 100-keyframe block, median/p95, ratios.

    .venv/bin/python bench/window_latency.py [--keyframes 500] [--window 10] [--out F]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import ResultWriter  # noqa: E402
from photogram_ros.core.camera import PinholeCamera  # noqa: E402
from photogram_ros.core.geodesy import LocalFrame  # noqa: E402
from photogram_ros.core.gnss_fix import GnssFix  # noqa: E402
from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions, KeyframeRecord  # noqa: E402
from photogram_ros.core.rotations import invert_T, make_T, transform_points  # noqa: E402
from photogram_ros.sim.observations import in_fov  # noqa: E402


# What the figure measures: the incremental adjustment and its window (core/incremental and the solver under it).
MODULES = ['photogram_ros/core/incremental.py', 'photogram_ros/core/window.py', 'photogram_ros/core/bundle',
           'photogram_ros/core/resection.py', 'photogram_ros/core/triangulation.py']


def flight(n_kf: int, per_line: int = 50, spacing_m: float = 5.0, line_gap_m: float = 17.0):
    """Camera poses: lines along north, alternating direction, nadir, image top along the course."""
    poses = []
    rng = np.random.default_rng(1)
    for k in range(n_kf):
        line, j = divmod(k, per_line)
        north = j * spacing_m if line % 2 == 0 else (per_line - 1 - j) * spacing_m
        fwd = np.array([0.0, 1.0, 0.0]) if line % 2 == 0 else np.array([0.0, -1.0, 0.0])
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        R = np.column_stack([right, -fwd, [0.0, 0.0, -1.0]])
        jitter = rng.normal(0, 0.005, 3)
        Rj = R @ np.array([[1, -jitter[2], jitter[1]], [jitter[2], 1, -jitter[0]], [-jitter[1], jitter[0], 1]])
        U, _, Vt = np.linalg.svd(Rj)
        poses.append(make_T(U @ Vt, [line * line_gap_m, north, 40.0 + rng.normal(0, 0.2)]))
    return np.array(poses)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument('--keyframes', type=int, default=500)
    ap.add_argument('--window', type=int, default=10)
    ap.add_argument('--points-per-image', type=int, default=300)
    ap.add_argument('--out', default=None, help='the result file (JSON lines; default /tmp/window_latency.jsonl)')
    a = ap.parse_args()
    w = ResultWriter.for_bench(a.out, 'window_latency', MODULES)
    cam = PinholeCamera(640, 480, 520.0, 520.0, 320.2, 238.3, (-0.12, 0.05, 0.0005, -0.0003, -0.01))
    origin = LocalFrame(47.3977, 8.5456, 488.0)
    poses = flight(a.keyframes)
    rng = np.random.default_rng(2)
    lo = poses[:, :3, 3].min(0) - 30
    hi = poses[:, :3, 3].max(0) + 30
    area = (hi[0] - lo[0]) * (hi[1] - lo[1])
    footprint = 640 * 480 * (40 / 520) ** 2
    n_pts = int(a.points_per_image / 0.9 * area / footprint)
    xy = rng.uniform(lo[:2], hi[:2], (n_pts, 2))
    pts = np.column_stack([xy, 2.0 * np.sin(xy[:, 0] / 15) * np.cos(xy[:, 1] / 11) + rng.normal(0, 0.5, n_pts)])
    at = IncrementalAT(cam, IncrementalOptions(window_size=a.window), origin=origin)
    lat, cpu = [], []
    nobs = []
    for k, T in enumerate(poses):
        pc = transform_points(invert_T(T), pts)
        uv, front = cam.project(pc)
        vis = np.flatnonzero(front & cam.in_image(uv, 5) & in_fov(cam, pc) & (rng.random(n_pts) < 0.9))
        g = T[:3, 3] + rng.normal(0, [0.014, 0.014, 0.03])
        fix = GnssFix(*origin.enu_to_geodetic(g), np.diag([0.014 ** 2, 0.014 ** 2, 0.03 ** 2]))
        rec = KeyframeRecord(k * 10 ** 9, vis, uv[vis] + rng.normal(0, 0.3, (len(vis), 2)), fix)
        t0, c0 = time.perf_counter(), time.process_time()
        rep = at.add_keyframe(rec)
        lat.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        nobs.append(len(vis))
        if not rep.registered and k > 2:
            print(json.dumps({'warning': f'keyframe {k} not registered: {rep.status}'}))
    lat_ms, cpu_ms = np.array(lat) * 1e3, np.array(cpu) * 1e3
    georef = next((i for i, h in enumerate(at.history) if at.georeferenced and h.gnss_rms_m == h.gnss_rms_m), 0)
    steady = lat_ms[max(georef, 20):]
    blocks = []
    for b0 in range(0, a.keyframes, 100):
        blk, blk_cpu = lat_ms[max(b0, 20):b0 + 100], cpu_ms[max(b0, 20):b0 + 100]
        if len(blk):
            # CPU time of the process (all threads) per update: the work done, whatever the load.
            blocks.append({'keyframes': f'{b0}-{min(b0 + 100, a.keyframes)}', 'median_ms': round(float(np.median(blk)), 1),
                           'p95_ms': round(float(np.percentile(blk, 95)), 1),
                           'cpu_median_ms': round(float(np.median(blk_cpu)), 1)})
            w.write({'kind': 'block', **blocks[-1]})
    t0 = time.perf_counter()
    full = at.full_adjustment(rounds=1)
    full_s = time.perf_counter() - t0
    cam_err = None
    C = np.array([at.kfs[k].map_T_cam[:3, 3] for k in at.registered])
    cam_err = float(np.sqrt(np.mean(np.sum((C - poses[at.registered, :3, 3]) ** 2, axis=1))))
    out = {'kind': 'summary', 'keyframes': a.keyframes, 'window': a.window,
           'points_per_image_mean': round(float(np.mean(nobs)), 1), 'registered': len(at.registered),
           'points': len(at.points),
           'median_ms': round(float(np.median(steady)), 1), 'p95_ms': round(float(np.percentile(steady, 95)), 1),
           'target_median_ms': 50.0,
           'flatness_last_over_first_block': round(blocks[-1]['median_ms'] / blocks[0]['median_ms'], 2),
           'cpu_flatness_last_over_first_block': round(blocks[-1]['cpu_median_ms'] / blocks[0]['cpu_median_ms'], 2),
           'baseline_full_adjustment_s': round(full_s, 2), 'full_status': full.status,
           'ratio_full_over_window_median': round(full_s * 1e3 / float(np.median(steady)), 1),
           'camera_rmse_after_full_m': round(cam_err, 4)}
    w.write(out)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
