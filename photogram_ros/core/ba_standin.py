"""TEMPORARY stand-in for photogram_ros.core.bundle (being written in parallel), same contract.

scipy.optimize.least_squares with a finite-difference sparse Jacobian: slow but correct, so the
incremental pipeline can be built and tested before the real solver lands. `incremental.py`
prefers the real module when it imports; delete this file once it does.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from photogram_ros.core.camera import PinholeCamera


@dataclass
class BundleProblem:
    camera: PinholeCamera
    map_T_cams: np.ndarray
    points_map: np.ndarray
    obs_cam: np.ndarray
    obs_pt: np.ndarray
    obs_uv: np.ndarray
    fixed_cams: np.ndarray | None = None
    fixed_points: np.ndarray | None = None
    gnss_cam: np.ndarray | None = None
    gnss_pos_map: np.ndarray | None = None
    gnss_cov_map: np.ndarray | None = None
    lever_arm_cam_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    point_priors_idx: np.ndarray | None = None
    point_priors_map: np.ndarray | None = None
    point_priors_sigma_m: np.ndarray | None = None


@dataclass
class BundleOptions:
    loss: str = 'huber'
    loss_scale_px: float = 1.0
    max_iterations: int = 50
    refine_intrinsics: tuple = ()
    compute_covariance: bool = False


@dataclass
class BundleResult:
    status: str
    initial_cost: float
    final_cost: float
    iterations: int
    map_T_cams: np.ndarray
    points_map: np.ndarray
    camera: PinholeCamera
    rms: dict


def bundle_adjust(prob: BundleProblem, opts: BundleOptions = BundleOptions()) -> BundleResult:
    T0 = np.asarray(prob.map_T_cams, float)
    P0 = np.asarray(prob.points_map, float)
    C, P = len(T0), len(P0)
    fc = np.zeros(C, bool) if prob.fixed_cams is None else np.asarray(prob.fixed_cams, bool)
    fp = np.zeros(P, bool) if prob.fixed_points is None else np.asarray(prob.fixed_points, bool)
    free_c = np.flatnonzero(~fc)
    free_p = np.flatnonzero(~fp)
    cam_col = np.full(C, -1)
    cam_col[free_c] = np.arange(len(free_c)) * 6
    pt_col = np.full(P, -1)
    pt_col[free_p] = len(free_c) * 6 + np.arange(len(free_p)) * 3
    n_x = len(free_c) * 6 + len(free_p) * 3
    oc, op = np.asarray(prob.obs_cam, int), np.asarray(prob.obs_pt, int)
    uv = np.asarray(prob.obs_uv, float)
    n_obs = len(oc)
    lever = np.asarray(prob.lever_arm_cam_m, float)
    has_g = prob.gnss_cam is not None and len(prob.gnss_cam) > 0
    gc = np.asarray(prob.gnss_cam, int) if has_g else np.zeros(0, int)
    if has_g:
        Wg = np.linalg.cholesky(np.linalg.inv(np.asarray(prob.gnss_cov_map, float)))  # inv(cov) = L L^T
        gpos = np.asarray(prob.gnss_pos_map, float)
    has_p = prob.point_priors_idx is not None and len(prob.point_priors_idx) > 0
    pi = np.asarray(prob.point_priors_idx, int) if has_p else np.zeros(0, int)
    R0 = T0[:, :3, :3]
    cam = prob.camera

    def unpack(x):
        R = R0.copy()
        Cc = T0[:, :3, 3].copy()
        if len(free_c):
            cx = x[:len(free_c) * 6].reshape(-1, 6)
            R[free_c] = R0[free_c] @ Rotation.from_rotvec(cx[:, :3]).as_matrix()
            Cc[free_c] = cx[:, 3:]
        X = P0.copy()
        X[free_p] = x[len(free_c) * 6:].reshape(-1, 3)
        return R, Cc, X

    def residuals(x):
        R, Cc, X = unpack(x)
        pc = np.einsum('nji,nj->ni', R[oc], X[op] - Cc[oc])
        z = np.where(pc[:, 2] > 1e-6, pc[:, 2], 1e-6)
        res = [(cam.normalized_to_pixel(pc[:, :2] / z[:, None]) - uv).ravel()]
        if has_g:
            e = Cc[gc] + np.einsum('nij,j->ni', R[gc], lever) - gpos
            res.append(np.einsum('nji,nj->ni', Wg, e).ravel())
        if has_p:
            res.append(((X[pi] - prob.point_priors_map) / prob.point_priors_sigma_m).ravel())
        return np.concatenate(res)

    x0 = np.concatenate([np.column_stack([np.zeros((len(free_c), 3)), T0[free_c, :3, 3]]).ravel(),
                         P0[free_p].ravel()])
    n_res = 2 * n_obs + 3 * len(gc) + 3 * len(pi)
    S = lil_matrix((n_res, n_x), dtype=np.int8)
    rows = np.arange(n_obs)
    for r0 in (0, 1):
        rr = 2 * rows + r0
        m = cam_col[oc] >= 0
        for k in range(6):
            S[rr[m], cam_col[oc[m]] + k] = 1
        m = pt_col[op] >= 0
        for k in range(3):
            S[rr[m], pt_col[op[m]] + k] = 1
    base = 2 * n_obs
    for j, c in enumerate(gc):
        if cam_col[c] >= 0:
            S[base + 3 * j: base + 3 * j + 3, cam_col[c]:cam_col[c] + 6] = 1
    base += 3 * len(gc)
    for j, p in enumerate(pi):
        if pt_col[p] >= 0:
            S[base + 3 * j: base + 3 * j + 3, pt_col[p]:pt_col[p] + 3] = 1
    r_init = residuals(x0)
    loss = {'huber': 'huber', 'cauchy': 'cauchy'}.get(opts.loss, 'linear')
    if n_x == 0:
        sol_x, nfev, status = x0, 0, 'converged'
    else:
        sol = least_squares(residuals, x0, jac_sparsity=S.tocsr(), loss=loss, f_scale=opts.loss_scale_px,
                            x_scale='jac', method='trf', max_nfev=opts.max_iterations, ftol=1e-10,
                            xtol=1e-10, tr_solver='lsmr')
        sol_x, nfev = sol.x, sol.nfev
        status = 'converged' if sol.status > 0 else 'max_iterations'
    r = residuals(sol_x)
    R, Cc, X = unpack(sol_x)
    T = np.tile(np.eye(4), (C, 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = Cc
    rr = r[:2 * n_obs].reshape(-1, 2)
    rms = {'reprojection_px': float(np.sqrt(np.mean(np.sum(rr ** 2, axis=1)))) if n_obs else 0.0}
    return BundleResult(status, 0.5 * float(r_init @ r_init), 0.5 * float(r @ r), int(nfev), T, X, cam, rms)
