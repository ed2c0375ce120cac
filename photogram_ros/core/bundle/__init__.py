"""Bundle adjustment: sparse Levenberg-Marquardt with GNSS, GCP and attitude priors.

    from photogram_ros.core.bundle import BundleProblem, BundleOptions, bundle_adjust
    res = bundle_adjust(BundleProblem(camera, map_T_cams, points_map, obs_cam, obs_pt, obs_uv, ...),
                        BundleOptions(loss='huber', loss_scale_px=1.0))

Conventions and gauge: see problem.py. Cost = 0.5 * sum rho(|r|^2) over reprojection residuals in
pixels plus 0.5 * |whitened prior residual|^2 for each prior.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from photogram_ros.core.bundle.losses import LOSSES
from photogram_ros.core.bundle.models import BALModel, BrownModel, CameraModel
from photogram_ros.core.bundle.problem import BundleOptions, BundleProblem, BundleResult
from photogram_ros.core.bundle.solver import Solver

__all__ = ['BundleProblem', 'BundleOptions', 'BundleResult', 'bundle_adjust', 'check_points',
           'CameraModel', 'BrownModel', 'BALModel', 'LOSSES']


def _map_T_cams(R, t):
    T = np.zeros((len(R), 4, 4))
    RT = np.transpose(R, (0, 2, 1))
    T[:, :3, :3] = RT
    T[:, :3, 3] = -np.einsum('cij,cj->ci', RT, t)
    T[:, 3, 3] = 1.0
    return T


def bundle_adjust(problem: BundleProblem, options: BundleOptions | None = None) -> BundleResult:
    """Adjust poses, points and (optionally) intrinsics. Numerical failure comes back as status."""
    options = options or BundleOptions()
    options.validate()
    d = problem.resolved()
    solver = Solver(d, options)
    out = solver.run()
    R, t, X, intr, b = out['R'], out['t'], out['X'], out['intr'], out['b']
    cam_cov = pt_cov = intr_cov = var = corr = bias_cov = None
    if options.compute_covariance and out['status'] != 'failed':
        cam_cov, pt_cov, intr_cov, corr, bias_cov = solver.covariance(R, t, X, intr, b, points=options.point_covariance,
                                                                     gnss_bias_free=options.gnss_bias_free)
        var = solver.variance_factor(out['cost'])
        if intr_cov is not None:
            intr_cov = intr_cov * (var if var is not None else np.nan)
        if bias_cov is not None:
            bias_cov = bias_cov * (var if var is not None else np.nan)
    camera = None
    if problem.model is None and problem.camera is not None:
        fx, fy, cx, cy, *dist = intr[0]
        camera = replace(problem.camera, fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy),
                         dist=tuple(float(v) for v in dist))
    return BundleResult(status=out['status'], reason=out['reason'], initial_cost=float(out['init']),
                        final_cost=float(out['cost']), iterations=out['iters'], successful_steps=out['ok'],
                        map_T_cams=_map_T_cams(R, t), points_map=X, camera=camera, intrinsics=intr,
                        rms=solver.residual_rms(R, t, X, intr, b), cam_centre_cov=cam_cov, point_cov=pt_cov,
                        intrinsics_cov=intr_cov, intrinsics_names=tuple(options.refine_intrinsics),
                        intrinsics_height_corr=corr, gnss_bias_cov=bias_cov,
                        gnss_bias_enu_m=np.asarray(b[:3], float) if solver.st.bias_col >= 0 else None,
                        gnss_tilt=np.asarray(b[3:5], float) if solver.st.n_bias == 5 else None,
                        variance_factor=var,
                        seconds=out['seconds'], cost_history=out['hist'], time_history=out['hist_t'])


def check_points(camera, map_T_cams, obs_cam, obs_pt, obs_uv, surveyed_map) -> dict:
    """Triangulate check points from adjusted cameras; residuals against their surveyed positions.

    obs_pt indexes surveyed_map (K, 3). Check points never enter the adjustment: call this after it.
    Returns residual_map (K, 3) (NaN where a point could not be triangulated), rmse_xy_m, rmse_z_m,
    and the triangulation diagnostics.
    """
    from photogram_ros.core.triangulation import triangulate_points
    surveyed_map = np.asarray(surveyed_map, float)
    tri = triangulate_points(camera, map_T_cams, obs_cam, obs_pt, obs_uv, n_points=len(surveyed_map))
    res = tri.points_map - surveyed_map
    ok = tri.valid
    rx = res[ok]
    return {'residual_map': res, 'valid': ok,
            'rmse_xy_m': float(np.sqrt(np.mean(np.sum(rx[:, :2] ** 2, axis=1)))) if ok.any() else float('nan'),
            'rmse_z_m': float(np.sqrt(np.mean(rx[:, 2] ** 2))) if ok.any() else float('nan'),
            'reprojection_px': tri.reproj_rms_px, 'angle_deg': tri.angle_deg}
