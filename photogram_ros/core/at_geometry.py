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
