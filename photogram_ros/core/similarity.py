"""Similarity transforms (scale, rotation, translation) between point sets: Umeyama and RANSAC.

Used to georeference a reconstruction made in an arbitrary frame: camera centres -> GNSS positions.
`dst ~= scale * R @ src + t`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from photogram_ros.errors import DataError


@dataclass
class Similarity:
    scale: float = 1.0
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points, float) @ self.R.T + self.t

    def apply_pose(self, a_T_cam: np.ndarray) -> np.ndarray:
        """A camera pose in the source frame -> the same camera in the target frame (no scale in R)."""
        out = np.eye(4)
        out[:3, :3] = self.R @ a_T_cam[:3, :3]
        out[:3, 3] = self.apply(a_T_cam[:3, 3])
        return out


@dataclass
class SimilarityResult:
    status: str                       # 'ok', 'too_few_points', 'degenerate'
    sim: Similarity = field(default_factory=Similarity)
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    rms_m: float = float('nan')

    @property
    def ok(self) -> bool:
        return self.status == 'ok'


def umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> Similarity:
    """Least-squares similarity (Umeyama 1991), optionally weighted; needs >= 3 non-collinear points."""
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise DataError(f'umeyama needs two (N, 3) arrays of the same shape, got {src.shape}, {dst.shape}')
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    S = src - mu_s
    D = dst - mu_d
    cov = (D * w[:, None]).T @ S
    U, sv, Vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        sign[2, 2] = -1.0
    R = U @ sign @ Vt
    var_s = float(np.sum(w * np.sum(S * S, axis=1)))
    scale = float(np.trace(np.diag(sv) @ sign) / var_s) if var_s > 0 else 1.0
    return Similarity(scale, R, mu_d - scale * R @ mu_s)


def spread(points: np.ndarray) -> np.ndarray:
    """Singular values (std, m) of a centred point set: the second one near zero means collinear."""
    p = np.asarray(points, float)
    return np.linalg.svd(p - p.mean(axis=0), compute_uv=False) / np.sqrt(max(len(p), 1))


def similarity_ransac(src, dst, threshold_m: float, rng: np.random.Generator | None = None,
                      iterations: int = 200, min_spread_ratio: float = 0.02) -> SimilarityResult:
    """Robust similarity: minimal 3-point samples, then Umeyama on the largest consensus set.

    Collinear inputs (a straight flight line) leave the roll about the line free: reported as
    'degenerate' so the caller can wait for a turn rather than trust an arbitrary rotation.
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    n = len(src)
    if n < 3:
        return SimilarityResult('too_few_points', inliers=np.zeros(n, bool))
    sv = spread(src)
    if sv[0] <= 0 or sv[1] < min_spread_ratio * sv[0]:
        return SimilarityResult('degenerate', inliers=np.zeros(n, bool))
    rng = rng or np.random.default_rng(0)
    best = np.ones(n, bool)
    best_count = -1
    if n > 3:
        for _ in range(iterations):
            idx = rng.choice(n, 3, replace=False)
            if spread(src[idx])[1] < min_spread_ratio * sv[0]:
                continue
            s = umeyama(src[idx], dst[idx])
            err = np.linalg.norm(s.apply(src) - dst, axis=1)
            inl = err < threshold_m
            if inl.sum() > best_count:
                best, best_count = inl, int(inl.sum())
    if best.sum() < 3:
        return SimilarityResult('too_few_points', inliers=best)
    for _ in range(3):   # refit on the consensus, then re-select with the refined transform
        s = umeyama(src[best], dst[best])
        err = np.linalg.norm(s.apply(src) - dst, axis=1)
        new = err < threshold_m
        if new.sum() < 3 or np.array_equal(new, best):
            break
        best = new
    rms = float(np.sqrt(np.mean(err[best] ** 2)))
    return SimilarityResult('ok', s, best, rms)


# A camera's roll about the line from its attitude prior counts when within this of the most agreed one, rad.
ROLL_PRIOR_AGREE_RAD = np.radians(3.0)


def roll_from_priors(line_dir: np.ndarray, R0: np.ndarray, src_R_cam: np.ndarray, dst_R_cam: np.ndarray):
    """The rotation about `line_dir` (target frame) that, after R0, best turns the cameras' orientations in the
    source frame `src_R_cam` (n, 3, 3) onto their priors in the target frame `dst_R_cam` (n, 3, 3), robustly:
    each camera's own angle, the one closest to most others (a few bad priors do not move it), averaged with
    those within ROLL_PRIOR_AGREE_RAD of it. None when fewer than half the cameras agree with it."""
    d = np.asarray(line_dir, float)
    A = np.einsum('ij,njk->nik', R0, np.asarray(src_R_cam, float))
    B = np.asarray(dst_R_cam, float)
    # Per camera, theta maximising trace(B^T Rot(d, theta) A) (Rodrigues, summed over the three axes).
    ad, bd = A.transpose(0, 2, 1) @ d, B.transpose(0, 2, 1) @ d
    cos_part = np.einsum('nij,nij->n', A, B) - np.sum(ad * bd, axis=1)
    sin_part = np.einsum('nij,nij->n', np.cross(d[None, :, None], A, axis=1), B)
    theta = np.arctan2(sin_part, cos_part)
    gap = np.abs(np.angle(np.exp(1j * (theta[:, None] - theta[None, :]))))
    best = int(np.argmin(np.sum(np.minimum(gap, ROLL_PRIOR_AGREE_RAD * 10), axis=1)))
    near = gap[best] <= ROLL_PRIOR_AGREE_RAD
    if 2 * near.sum() < len(theta):
        return None
    t = theta[best] + float(np.mean(np.angle(np.exp(1j * (theta[near] - theta[best])))))
    K = np.array([[0, -d[2], d[1]], [d[2], 0, -d[0]], [-d[1], d[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def similarity_on_line(src: np.ndarray, dst: np.ndarray, view_dirs_src: np.ndarray,
                       down_dst=(0.0, 0.0, -1.0), attitude_priors=None) -> Similarity:
    """Similarity for (nearly) collinear points: scale, translation and line direction from the
    points, the roll about the line from the cameras' attitude priors when given and enough agree
    (`roll_from_priors`), else from the assumption that the cameras look down on average.

    `view_dirs_src`: optical axes of the cameras in the source frame. `attitude_priors`: (src_R_cam
    (n, 3, 3), dst_R_cam (n, 3, 3)), the orientations of the cameras that have a prior in the source
    frame and in the target frame (the autopilot's attitude and the mount). A provisional answer for a
    straight first flight line; the first turn makes the full similarity observable.
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    ms, md = src.mean(0), dst.mean(0)
    _, ss, Vs = np.linalg.svd(src - ms, full_matrices=False)
    _, sd, Vd = np.linalg.svd(dst - md, full_matrices=False)
    ds, dd = Vs[0], Vd[0]
    if np.corrcoef((src - ms) @ ds, (dst - md) @ dd)[0, 1] < 0:
        dd = -dd
    scale = float(sd[0] / ss[0])
    # Minimal rotation taking ds onto dd.
    v = np.cross(ds, dd)
    c = float(ds @ dd)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    if c > -0.999:
        R0 = np.eye(3) + vx + vx @ vx / (1.0 + c)
    else:   # opposite directions: half a turn about any axis perpendicular to ds
        w = np.cross(ds, [1.0, 0.0, 0.0] if abs(ds[0]) < 0.9 else [0.0, 1.0, 0.0])
        w /= np.linalg.norm(w)
        R0 = 2.0 * np.outer(w, w) - np.eye(3)
        if c < 1.0 - 1e-12 and np.linalg.norm(R0 @ ds - dd) > 1e-6:
            # Not exactly opposite: finish with the small rotation from R0 ds onto dd.
            d1 = R0 @ ds
            v1 = np.cross(d1, dd)
            vx1 = np.array([[0, -v1[2], v1[1]], [v1[2], 0, -v1[0]], [-v1[1], v1[0], 0]])
            R0 = (np.eye(3) + vx1 + vx1 @ vx1 / (1.0 + float(d1 @ dd))) @ R0
    Rr = None if attitude_priors is None or not len(attitude_priors[0]) else roll_from_priors(dd, R0, *attitude_priors)
    if Rr is not None:
        R = Rr @ R0
        return Similarity(scale, R, md - scale * R @ ms)
    a = R0 @ np.mean(view_dirs_src, axis=0)
    g = np.asarray(down_dst, float)
    # Roll theta about dd maximising g . Rot(dd, theta) a (Rodrigues, closed form).
    p = a - dd * (dd @ a)
    q = np.cross(dd, a)
    theta = np.arctan2(g @ q, g @ p)
    K = np.array([[0, -dd[2], dd[1]], [dd[2], 0, -dd[0]], [-dd[1], dd[0], 0]])
    Rr = np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K
    R = Rr @ R0
    return Similarity(scale, R, md - scale * R @ ms)
