"""Multi-view triangulation: linear DLT on all views of each point, then Gauss-Newton on pixels.

Everything is vectorised over observations: the 4x4 DLT normal matrices and the 3x3 Gauss-Newton
systems of all points are accumulated with bincount and solved in one batched call.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photogram_ros.core.bundle.models import BrownModel
from photogram_ros.errors import DataError


@dataclass
class Triangulation:
    points_map: np.ndarray      # (P, 3), NaN where not triangulated
    valid: np.ndarray           # (P,) >= 2 views, in front of every camera, finite
    n_views: np.ndarray         # (P,)
    angle_deg: np.ndarray       # (P,) largest angle between two viewing rays
    reproj_rms_px: np.ndarray   # (P,) RMS reprojection error over the point's observations


def _max_ray_angle(rays, obs_pt, P):
    """Largest pairwise angle between the unit rays of each point (pairs enumerated per point)."""
    order = np.argsort(obs_pt, kind='stable')
    pt = obs_pt[order]
    n = np.bincount(pt, minlength=P)
    start = np.concatenate([[0], np.cumsum(n)])[:-1]
    reps = n[pt]
    i = np.repeat(np.arange(len(pt)), reps)
    j = start[pt][i] + (np.arange(len(i)) - np.repeat(np.cumsum(reps) - reps, reps))
    c = np.nan_to_num(np.einsum('ni,ni->n', rays[order[i]], rays[order[j]]), nan=1.0)
    ang = np.full(P, 0.0)
    np.maximum.at(ang, pt[i], np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
    return ang


def triangulate_points(camera, map_T_cams, obs_cam, obs_pt, obs_uv, n_points: int | None = None,
                       iterations: int = 5) -> Triangulation:
    """Triangulate points from distorted pixel observations in posed cameras (map_T_cam)."""
    T = np.asarray(map_T_cams, float)
    oc = np.asarray(obs_cam, np.int64).ravel()
    op = np.asarray(obs_pt, np.int64).ravel()
    uv = np.asarray(obs_uv, float).reshape(-1, 2)
    if not (len(oc) == len(op) == len(uv)):
        raise DataError('obs_cam, obs_pt and obs_uv must have the same length')
    if T.ndim != 3 or T.shape[1:] != (4, 4) or (len(oc) and (oc.min() < 0 or oc.max() >= len(T))):
        raise DataError('map_T_cams must be (C, 4, 4) and obs_cam index into it')
    P = int(n_points if n_points is not None else (op.max() + 1 if len(op) else 0))
    R = np.transpose(T[:, :3, :3], (0, 2, 1))                     # cam_R_map
    t = -np.einsum('cij,cj->ci', R, T[:, :3, 3])
    xy = camera.pixel_to_normalized(uv)
    Pm = np.concatenate([R, t[:, :, None]], axis=2)[oc]           # (N, 3, 4) normalised projection
    rows = np.stack([xy[:, 0:1] * Pm[:, 2] - Pm[:, 0], xy[:, 1:2] * Pm[:, 2] - Pm[:, 1]], axis=1)
    rows /= np.linalg.norm(rows, axis=2, keepdims=True)
    AtA = np.einsum('nka,nkb->nab', rows, rows).reshape(len(oc), 16)
    M = np.stack([np.bincount(op, AtA[:, k], minlength=P) for k in range(16)], axis=1).reshape(P, 4, 4)
    n_views = np.bincount(op, minlength=P)
    X = np.full((P, 3), np.nan)
    has = n_views >= 2
    if has.any():
        _, vec = np.linalg.eigh(M[has])
        h = vec[:, :, 0]
        with np.errstate(divide='ignore', invalid='ignore'):
            X[has] = h[:, :3] / h[:, 3:4]
    # Gauss-Newton on pixel residuals with the full distortion model.
    model = BrownModel()
    prm = np.broadcast_to(BrownModel.params_of(camera), (len(oc), 9))
    Rc = R[oc]
    for _ in range(iterations):
        Pc = np.einsum('nij,nj->ni', Rc, X[op]) + t[oc]
        r_uv, Jp, _ = model.project(Pc, prm)
        r = r_uv - uv
        J = Jp @ Rc
        H = np.einsum('nka,nkb->nab', J, J).reshape(-1, 9)
        g = np.einsum('nka,nk->na', J, r)
        Hp = np.stack([np.bincount(op, H[:, k], minlength=P) for k in range(9)], 1).reshape(P, 3, 3)
        gp = np.stack([np.bincount(op, g[:, k], minlength=P) for k in range(3)], 1)
        ok = has & np.all(np.isfinite(Hp.reshape(P, 9)), 1)
        ok[ok] = np.abs(np.linalg.det(Hp[ok])) > 1e-30
        if not ok.any():
            break
        X[ok] -= np.linalg.solve(Hp[ok], gp[ok][:, :, None])[:, :, 0]
    Pc = np.einsum('nij,nj->ni', Rc, X[op]) + t[oc]
    r = model.project(Pc, prm, jac=False)[0] - uv
    err2 = np.bincount(op, np.sum(r * r, 1), minlength=P)
    behind = np.bincount(op, (Pc[:, 2] <= 0).astype(float), minlength=P) > 0
    with np.errstate(invalid='ignore', divide='ignore'):
        rms = np.sqrt(err2 / n_views)
    centres = T[:, :3, 3][oc]
    rays = X[op] - centres
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    angle = _max_ray_angle(rays, op, P) if len(op) else np.zeros(P)
    valid = has & ~behind & np.all(np.isfinite(X), 1) & np.isfinite(rms)
    return Triangulation(points_map=X, valid=valid, n_views=n_views, angle_deg=angle, reproj_rms_px=rms)


def near_the_cameras(points_map: np.ndarray, centres_map: np.ndarray, factor: float = 10.0) -> np.ndarray:
    """Mask of the tie points within `factor` times the median distance from a point to its nearest camera.

    points_map (N, 3) and centres_map (M, 3) in one metric frame, m. A point far beyond that (rays almost
    parallel: a point kilometres away on a 40 m flight) is not ground the photos measured; the sparse cloud's
    writers leave it out. Non-finite points are never kept; with no camera every finite point is."""
    from scipy.spatial import cKDTree
    P = np.asarray(points_map, float).reshape(-1, 3)
    C = np.asarray(centres_map, float).reshape(-1, 3)
    finite = np.all(np.isfinite(P), axis=1)
    if len(C) == 0 or not finite.any():
        return finite
    d = np.full(len(P), np.inf)
    d[finite] = cKDTree(C).query(P[finite])[0]
    return finite & (d <= factor * max(float(np.median(d[finite])), 1e-6))
