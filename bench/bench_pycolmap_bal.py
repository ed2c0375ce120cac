"""Ceres peer for bench/bundle_bal.py: the BAL problem as a pycolmap Reconstruction.

BAL cameras look down -z with y up; COLMAP's look down +z with y down. Flipping y and z of the camera
frame (diag(1, -1, -1) on R and t) turns BAL's p = -P/P.z into COLMAP's x = P/P.z with y negated, so
COLMAP's RADIAL model (f, cx, cy, k1, k2) with cx = cy = 0 and v = -y_BAL is the same camera.
"""

from __future__ import annotations

import time

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

FLIP = np.diag([1.0, -1.0, -1.0])


def solve_with_pycolmap(b, ftol, bal_cost):
    C, P = len(b.cam_t), len(b.points)
    rec = pycolmap.Reconstruction()
    R = FLIP @ Rotation.from_rotvec(b.cam_rotvec).as_matrix()
    t = b.cam_t @ FLIP
    span = float(np.abs(b.obs_uv).max()) + 10.0
    order = np.argsort(b.obs_cam, kind='stable')
    for c in range(C):
        f, k1, k2 = b.intrinsics[c]
        cam = pycolmap.Camera(model='RADIAL', width=int(2 * span), height=int(2 * span),
                              params=[f, 0.0, 0.0, k1, k2], camera_id=c + 1)
        rec.add_camera_with_trivial_rig(cam)
        sel = order[b.obs_cam[order] == c]
        kp = np.stack([b.obs_uv[sel, 0], -b.obs_uv[sel, 1]], axis=1)
        img = pycolmap.Image(name=f'{c}', keypoints=kp, camera_id=c + 1, image_id=c + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R[c]), t[c])
        rec.add_image_with_trivial_frame(img, pose)
    pid = [rec.add_point3D(b.points[p], pycolmap.Track()) for p in range(P)]
    for c in range(C):
        sel = order[b.obs_cam[order] == c]
        for k, obs in enumerate(sel):
            rec.add_observation(pid[b.obs_pt[obs]], pycolmap.TrackElement(c + 1, k))
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    opts.refine_principal_point = False
    so = opts.ceres.solver_options
    so.function_tolerance = ftol
    so.gradient_tolerance = 0.0
    so.parameter_tolerance = 0.0
    so.max_num_iterations = 100
    so.num_threads = 2
    so.linear_solver_type = type(so.linear_solver_type).SPARSE_SCHUR
    opts.ceres.auto_select_solver_type = False
    cfg = pycolmap.BundleAdjustmentConfig()
    for c in range(C):
        cfg.add_image(c + 1)
    # UNSPECIFIED: COLMAP adds no gauge constraint, every pose moves as in the other solvers.
    cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.UNSPECIFIED)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(opts, cfg, rec)
    t0, c0 = time.perf_counter(), time.process_time()
    summary = adjuster.solve()
    sec, cpu = time.perf_counter() - t0, time.process_time() - c0
    rv, tt, intr = np.zeros((C, 3)), np.zeros((C, 3)), np.zeros((C, 3))
    for c in range(C):
        T = rec.image(c + 1).cam_from_world()
        Rc = FLIP @ T.rotation.matrix()
        rv[c] = Rotation.from_matrix(Rc).as_rotvec()
        tt[c] = FLIP @ T.translation
        p = rec.camera(c + 1).params
        intr[c] = [p[0], p[3], p[4]]
    pts = np.array([rec.point3D(pid[p]).xyz for p in range(P)])
    cost, rms = bal_cost(rv, tt, intr, pts, b)
    cs = getattr(summary, 'ceres_summary', None)
    try:
        iters = int(cs.num_successful_steps + cs.num_unsuccessful_steps)
    except AttributeError:
        iters = None
    return dict(solver='ceres_pycolmap_sparse_schur', seconds=sec, solve_cpu_seconds=cpu, iterations=iters,
                final_cost=cost,
                final_rms_px=rms, status=str(getattr(summary, 'termination_type', '')))
