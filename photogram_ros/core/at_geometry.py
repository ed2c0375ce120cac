"""The aerial triangulation's ray geometry: rays intersected, points reprojected, the antenna's lever arm.

Shared by the block (core/at_block.py), its adjustments (core/at_problem.py) and the reports (core/at_report.py).
"""

from __future__ import annotations

import numpy as np

from photogram_ros.core.camera import PinholeCamera


def reprojection_errors_px(camera: PinholeCamera, map_T_cams: np.ndarray, points_map_m: np.ndarray,
                           uv_px: np.ndarray) -> np.ndarray:
    """(n,) pixel distance of each observation: the point points_map_m[i] (map m) seen from map_T_cams[i]
    (4, 4, camera to map) against uv_px[i] (distorted pixels); NaN behind the camera."""
    pc = np.einsum('nji,nj->ni', map_T_cams[:, :3, :3], points_map_m - map_T_cams[:, :3, 3])
    z = np.where(pc[:, 2] > 1e-9, pc[:, 2], np.nan)
    return np.linalg.norm(camera.normalized_to_pixel(pc[:, :2] / z[:, None]) - uv_px, axis=1)


def lever_arm_cam_from_frd(lever_frd_m) -> np.ndarray:
    """Body-FRD lever arm -> camera frame, for a nadir camera whose image top points forward.

    Optical x = body right, optical y = body backward, optical z = body down.
    """
    f, r, d = np.asarray(lever_frd_m, float)
    return np.array([r, -f, d])


def triangulate_rays(centres: np.ndarray, dirs: np.ndarray, groups: np.ndarray, n: int) -> np.ndarray:
    """Least-squares intersection of rays grouped by point: (n, 3), NaN where undetermined."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    A = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    b = np.einsum('nij,nj->ni', A, centres)
    As = np.zeros((n, 3, 3))
    bs = np.zeros((n, 3))
    np.add.at(As, groups, A)
    np.add.at(bs, groups, b)
    out = np.full((n, 3), np.nan)
    ok = np.abs(np.linalg.det(As)) > 1e-12
    out[ok] = np.linalg.solve(As[ok], bs[ok][..., None])[..., 0]
    return out


def reprojection_residuals_px(camera: PinholeCamera, map_T_cams: np.ndarray, uv: np.ndarray,
                              X_map: np.ndarray) -> np.ndarray:
    """(N, 2) pixels: the map point `X_map` (m) projected through the N cameras `map_T_cams` (camera to
    map), minus its observations `uv` (px, as measured: distorted)."""
    pc = np.einsum('nji,nj->ni', map_T_cams[:, :3, :3], X_map[None] - map_T_cams[:, :3, 3])
    return camera.normalized_to_pixel(pc[:, :2] / pc[:, 2:3]) - uv


def intersect_point(camera: PinholeCamera, map_T_cams: np.ndarray, uv: np.ndarray):
    """Multi-ray intersection refined by Gauss-Newton on the reprojection error (cameras fixed):
    (map point, m; number of rays; RMS of its reprojection residuals, px), or None."""
    xn = camera.pixel_to_normalized(uv)
    dirs = np.einsum('nij,nj->ni', map_T_cams[:, :3, :3], np.column_stack([xn, np.ones(len(xn))]))
    X = triangulate_rays(map_T_cams[:, :3, 3], dirs, np.zeros(len(xn), int), 1)[0]
    if not np.all(np.isfinite(X)):
        return None

    def res(X):
        return reprojection_residuals_px(camera, map_T_cams, uv, X).ravel()

    for _ in range(10):
        r = res(X)
        J = np.column_stack([(res(X + d) - r) / 1e-6 for d in np.eye(3) * 1e-6])
        dx = np.linalg.lstsq(J, -r, rcond=None)[0]
        X = X + dx
        if np.linalg.norm(dx) < 1e-7:
            break
    r = res(X).reshape(-1, 2)
    return X, len(uv), float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))


def row_residuals(camera: PinholeCamera, Ts: np.ndarray, uv: np.ndarray, X: np.ndarray):
    """Reprojection distance (px) of X in each camera, and the same on the ground (m, px * depth / f)."""
    pc = np.einsum('nji,nj->ni', Ts[:, :3, :3], X[None] - Ts[:, :3, 3])
    z = pc[:, 2]
    ok = z > 1e-6
    e = np.full(len(uv), np.inf)
    if ok.any():
        e[ok] = np.linalg.norm(camera.normalized_to_pixel(pc[ok, :2] / z[ok, None]) - uv[ok], axis=1)
    return e, np.where(ok, e * np.abs(z) / camera.fx, np.inf)


def consensus(camera: PinholeCamera, Ts: np.ndarray, uv: np.ndarray, thr_px: float):
    """The largest set of rows that agree on one point (every pair tried): (X, inlier mask) or (None, none)."""
    n = len(uv)
    best, best_key = None, None
    for i in range(n):
        for j in range(i + 1, n):
            hit = intersect_point(camera, Ts[[i, j]], uv[[i, j]])
            if hit is None:
                continue
            e, _ = row_residuals(camera, Ts, uv, hit[0])
            inl = e <= thr_px
            key = (int(inl.sum()), -float(np.sum(np.minimum(e, thr_px))))
            if inl[i] and inl[j] and (best_key is None or key > best_key):
                best, best_key = inl, key
    if best is None:
        return None, np.zeros(n, bool)
    hit = intersect_point(camera, Ts[best], uv[best])
    if hit is None:
        return None, np.zeros(n, bool)
    X = hit[0]
    e, _ = row_residuals(camera, Ts, uv, X)
    inl = e <= thr_px
    if inl.sum() >= 2 and not np.array_equal(inl, best):
        hit = intersect_point(camera, Ts[inl], uv[inl])
        X = hit[0] if hit is not None else X
    return X, inl if inl.sum() >= 2 else best


def robust_intersection(camera: PinholeCamera, map_T_cams: np.ndarray, uv: np.ndarray, max_px: float):
    """A point from its observations when some may be wrong: (xyz, n used, RMS px) of the largest set of
    observations within max_px of one point (every pair tried when all of them do not agree), or None."""
    Ts, uv = np.asarray(map_T_cams, float).reshape(-1, 4, 4), np.asarray(uv, float).reshape(-1, 2)
    got = intersect_point(camera, Ts, uv) if len(uv) >= 2 else None
    if got is not None and np.all(row_residuals(camera, Ts, uv, got[0])[0] <= max_px):
        return got
    X, inl = consensus(camera, Ts, uv, max_px) if len(uv) >= 3 else (None, None)
    return None if X is None else intersect_point(camera, Ts[inl], uv[inl])
