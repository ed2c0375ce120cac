"""Camera resection by the Direct Linear Transform and K[R|t] recovery by RQ decomposition.

The classic method (Abdel-Aziz & Karara 1971; Hartley & Zisserman ch. 7): from >= 6 known 3D points
and their (undistorted) pixels, solve the 3x4 projection matrix linearly with Hartley normalisation,
then split its left 3x3 block into an upper-triangular K and a rotation R by RQ. Distortion is not
modelled: undistort the pixels first, or refine the result in a bundle adjustment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from photogram_ros.errors import DataError


@dataclass
class Resection:
    P: np.ndarray          # (3, 4) projection matrix, scaled so that K[2, 2] = 1
    K: np.ndarray          # (3, 3) upper triangular, positive diagonal
    cam_R_map: np.ndarray  # (3, 3)
    cam_t_map: np.ndarray  # (3,)
    map_T_cam: np.ndarray  # (4, 4)
    rms_px: float          # reprojection RMS of the input points


def _normaliser(pts):
    c = pts.mean(axis=0)
    s = np.sqrt(pts.shape[1]) / max(np.mean(np.linalg.norm(pts - c, axis=1)), 1e-300)
    T = np.eye(pts.shape[1] + 1)
    T[:-1, :-1] *= s
    T[:-1, -1] = -s * c
    return T


def decompose_projection(P: np.ndarray):
    """P = K [R | t] -> (K, R, t) with K upper triangular, positive diagonal, det R = +1."""
    P = np.asarray(P, float)
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    K, R = scipy.linalg.rq(P[:, :3])
    S = np.diag(np.sign(np.diag(K)))
    K, R = K @ S, S @ R                       # S = S^-1 moves the signs into R
    t = np.linalg.solve(K, P[:, 3])
    scale = K[2, 2]
    return K / scale, R, t


def resect_dlt(points_map, uv) -> Resection:
    X = np.asarray(points_map, float).reshape(-1, 3)
    x = np.asarray(uv, float).reshape(-1, 2)
    if len(X) != len(x):
        raise DataError(f'{len(X)} points but {len(x)} pixels')
    if len(X) < 6:
        raise DataError(f'DLT resection needs at least 6 points, got {len(X)}')
    if np.linalg.matrix_rank(X - X.mean(0), tol=1e-9 * max(1.0, np.abs(X).max())) < 3:
        raise DataError('the control points are coplanar: DLT resection needs points off one plane')
    T3, T2 = _normaliser(X), _normaliser(x)
    Xn = (np.c_[X, np.ones(len(X))] @ T3.T)
    xn = (np.c_[x, np.ones(len(x))] @ T2.T)
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4] = Xn
    A[0::2, 8:12] = -xn[:, 0:1] * Xn
    A[1::2, 4:8] = Xn
    A[1::2, 8:12] = -xn[:, 1:2] * Xn
    Pn = np.linalg.svd(A)[2][-1].reshape(3, 4)
    P = np.linalg.solve(T2, Pn @ T3)
    K, R, t = decompose_projection(P)
    P = K @ np.c_[R, t]
    proj = np.c_[X, np.ones(len(X))] @ P.T
    rms = float(np.sqrt(np.mean(np.sum((proj[:, :2] / proj[:, 2:3] - x) ** 2, axis=1))))
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ t
    return Resection(P=P, K=K, cam_R_map=R, cam_t_map=t, map_T_cam=T, rms_px=rms)
