"""A keyframe oriented from two views, scaled by GNSS (core/at_register.py uses it).

A keyframe that shares only a few tracks with the block, and those only with one oriented keyframe at a time
(half the forward overlap: no triple overlap, so no known point to resect from; or a keyframe taken before the
block's first pair), gets its rotation and the direction of its baseline from the essential matrix of the tracks
it shares with that keyframe (core/two_view.py) and the baseline's length from the two camera centres' GNSS
positions. A confident wrong pose is worse than none, so the pose is taken only when every gate holds:

- at least `min_relative_inliers_gnss` relative-pose inliers (USAC), their points on a plane the camera faces;
- their median ray angle at least `two_view_min_angle_deg` (a short baseline leaves the direction to noise);
- the baseline between the two fixes at least the block's GNSS tolerance (`Registration.gnss_tolerance_m`: 3 x its
  GNSS residual RMS), and the direction the images give within `two_view_max_direction_deg` plus what that
  tolerance allows over the baseline (atan(tolerance / baseline)) of the direction between the fixes;
- the keyframe's antenna, so placed, within the tolerance (+ 2 % of the baseline) of its fix.

Every oriented keyframe sharing enough tracks is tried, the one sharing most first; the first that passes gives
the pose. The block must be georeferenced (the fixes' baseline in the map frame) with a GNSS residual to judge by.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photogram_ros.core.part_options import check
from photogram_ros.core.rotations import make_T
from photogram_ros.core.two_view import relative_pose, scene_facing
from photogram_ros.params import param


@dataclass
class TwoViewPose:
    """A gated two-view orientation of a keyframe: `map_T_cam`, the relative-pose inlier rows of the keyframe's
    observations (`rows`), and what it came from (`partner` kid, counts and angles: `status` says them)."""
    map_T_cam: np.ndarray
    rows: np.ndarray
    partner: int
    inliers: int
    ray_angle_deg: float
    baseline_m: float
    direction_off_deg: float
    status: str


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-12)
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def antenna_offset_map(datum, kf, map_R_cam: np.ndarray) -> np.ndarray:
    """kf's antenna minus its camera centre, map m, for a camera rotated by map_R_cam."""
    return kf.antenna_offset if kf.antenna_offset is not None else map_R_cam @ datum.lever


@dataclass(frozen=True)
class TwoViewOptions:
    """The gates of a keyframe oriented from two views (`two_view_pose`)."""
    pnp_threshold_px: float = param(3.0, 'RANSAC threshold of a new keyframe\'s resection (and of the first '
                                         'relative pose), px', min=0.1, max=100.0)
    min_relative_inliers_gnss: int = param(12, 'relative-pose inliers that fallback needs, with a georeferenced '
                                               'block, when the pose it gives puts the keyframe\'s antenna within '
                                               '3 x the block\'s GNSS residual RMS of its fix (a keyframe that '
                                               'shares only a few two-view tracks: half the forward overlap; '
                                               'core/at_two_view.py)',
                                           min=8, max=100000)
    two_view_min_angle_deg: float = param(2.0, 'a keyframe oriented from two views (fewer than '
                                               'min_relative_inliers shared tracks, scaled by GNSS) needs this median '
                                               'ray angle, deg', min=0.0, max=60.0)
    two_view_max_direction_deg: float = param(5.0, '... and the baseline direction its images give within this (plus '
                                                   'atan(GNSS tolerance / baseline)) of the direction between the '
                                                   'two fixes, deg', min=0.1, max=90.0)
    assume_nadir: bool = param(True, 'a straight first line georeferences provisionally, the roll about it '
                                     'from a near-nadir camera (final at the first turn); and a relative pose '
                                     'must see its tie points\' plane facing the camera (`min_facing`)')
    min_facing: float = param(0.5, 'with assume_nadir: a relative pose (the first two keyframes, the relative '
                                   'fallback) whose tie points\' best plane has a normal further than this |cos| '
                                   'from the optical axis is not used: it sees the ground edge-on, the planar twin '
                                   'of an aerial pair (0.5: 60 degrees, room for oblique cameras and relief)',
                              min=0.0, max=1.0)

    def __post_init__(self):
        check(self)


def two_view_pose(block, datum, opt: TwoViewOptions, kf, partners, tol_m: float) -> TwoViewPose | str:
    """kf's pose from its tracks shared with one of `partners` (oriented keyframe ids), scaled by GNSS and gated (see
    the module's doc); `tol_m` the GNSS tolerance of its fix. Returns the pose, or why none passed (the reason of the
    best-supported partner)."""
    rows_kf = np.flatnonzero(block.usable(kf))
    ids_kf = kf.track_ids[rows_kf]
    cands = []
    for r in partners:
        rk = block.kfs[r]
        if rk.frozen or rk.map_T_cam is None or rk.fix_enu is None or r in datum.rejected:
            continue
        rows_r = np.flatnonzero(block.usable(rk))
        _, i1, i2 = np.intersect1d(rk.track_ids[rows_r], ids_kf, return_indices=True)
        if len(i1) >= opt.min_relative_inliers_gnss:
            cands.append((len(i1), r, rows_r[i1], rows_kf[i2]))
    if not cands:
        return f'two views: no oriented keyframe shares {opt.min_relative_inliers_gnss} tracks'
    reason = None
    thr = opt.pnp_threshold_px / block.camera.fx
    for n, r, i1, i2 in sorted(cands, key=lambda c: -c[0]):
        got = _gated(block, datum, opt, kf, block.kfs[r], i1, i2, thr, tol_m)
        if isinstance(got, TwoViewPose):
            return got
        reason = reason or f'two views with {block.kfs[r].name} ({n} shared tracks): {got}'
    return reason


def _gated(block, datum, opt, kf, rk, i1, i2, thr: float, tol_m: float) -> TwoViewPose | str:
    res = relative_pose(block.xn(rk, i1), block.xn(kf, i2), thr, opt.min_relative_inliers_gnss, method='usac')
    if not res.ok:
        return res.status
    n_in = int(res.inliers.sum())
    if opt.assume_nadir and scene_facing(res.points_cam1[res.inliers]) < opt.min_facing:
        return 'sees its tie points edge-on (the planar twin)'
    if res.median_angle_deg < opt.two_view_min_angle_deg:
        return f'ray angle {res.median_angle_deg:.1f} deg < {opt.two_view_min_angle_deg:g}'
    R, t = res.cam2_T_cam1[:3, :3], res.cam2_T_cam1[:3, 3]
    T_r = rk.map_T_cam
    map_R = T_r[:3, :3] @ R.T
    d_map = T_r[:3, :3] @ (-R.T @ t)       # unit baseline rk -> kf, map frame
    b_gnss = (kf.fix_enu - antenna_offset_map(datum, kf, map_R)) - (rk.fix_enu - antenna_offset_map(datum, rk, T_r[:3, :3]))
    base_m = float(np.linalg.norm(b_gnss))
    if base_m < tol_m:
        return f'baseline {base_m:.1f} m between the fixes is under their tolerance {tol_m:.1f} m'
    off_deg = _angle_deg(d_map, b_gnss)
    allowed = opt.two_view_max_direction_deg + float(np.degrees(np.arctan(tol_m / base_m)))
    if off_deg > allowed:
        return f'baseline direction {off_deg:.1f} deg from the fixes\' (> {allowed:.1f})'
    T = make_T(map_R, T_r[:3, 3] + base_m * d_map)
    # The antenna so placed against the fix less the GNSS bias (the tilt's mm/m over one baseline left out).
    off_m = float(np.linalg.norm(T[:3, 3] + antenna_offset_map(datum, kf, map_R) - (kf.fix_enu - datum.bias_enu)))
    if off_m > tol_m + 0.02 * base_m:
        return f'its fix {off_m:.1f} m from the pose (> {tol_m + 0.02 * base_m:.1f} m)'
    status = (f'registered_two_view ({n_in} inliers with {rk.name}, ray angle {res.median_angle_deg:.1f} deg, '
              f'baseline {base_m:.1f} m from GNSS, {off_deg:.1f} deg from its direction)')
    return TwoViewPose(T, i2[res.inliers], rk.kid, n_in, float(res.median_angle_deg), base_m, off_deg, status)
