"""Which keyframes to pair for stereo, and which depths each pair searches.

Along a survey line consecutive keyframes are displaced along the image y axis; across lines, along
the image x axis. Both make valid stereo pairs; they are chosen separately so that a keyframe gets
its best along-line partner and, where lines overlap, its best across-line partner.

`plan_pairs` is the one planner of the stereo node (in flight) and of io/densify.py (the products,
from the final poses): given a new keyframe's pose, its candidate partners' poses, the ground height
and, when known, the tie points around them, it returns the partners with each pair's depth search
(min/max depth along the older keyframe's axis): the ground height +- relief_m, narrowed to the
depths the pair's tie points span (widened by depth_margin_m) when there are enough of them.
The matching from the final adjustment plans with PairCriteria.for_final(): more partners across lines
(final_pairs_across) down to a smaller common footprint (final_min_overlap) than the stereo node in flight.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from photogram_ros.core import gsd
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.errors import ConfigError
from photogram_ros.params import param

OK, BELOW_GROUND = 'ok', 'below_ground'   # PairPlan statuses


def overlap_fraction(camera: PinholeCamera, map_T_cam_a: np.ndarray, map_T_cam_b: np.ndarray, depth_m: float,
                     n: int = 32) -> float:
    """Fraction of image a whose scene, taken at `depth_m` along a's axis, is seen inside image b."""
    u = np.linspace(0, camera.width - 1, n)
    v = np.linspace(0, camera.height - 1, n)
    uv = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    rays = camera.unproject(uv)
    pts_a = rays * (depth_m / rays[:, 2:3])           # a plane at depth_m in front of camera a
    pts_map = pts_a @ map_T_cam_a[:3, :3].T + map_T_cam_a[:3, 3]
    pts_b = (pts_map - map_T_cam_b[:3, 3]) @ map_T_cam_b[:3, :3]
    uv_b, front = camera.project(pts_b)
    return float(np.mean(front & camera.in_image(uv_b)))


@dataclass
class PairLimits:
    """What makes two keyframes a usable stereo pair: checked by the planner and again by stereo_pair."""
    min_overlap: float = param(0.4, 'skip pairs whose images overlap less than this fraction', min=0.0, max=1.0)
    min_baseline_ratio: float = param(0.08, 'skip pairs with a smaller baseline-to-depth ratio', min=0.0, max=5.0)
    max_baseline_ratio: float = param(1.2, 'skip pairs with a larger baseline-to-depth ratio (partners are chosen '
                                           'nearest target_baseline_ratio: a wider pair only where no nearer one '
                                           'overlaps, as on a fixed-wing survey at 60 % forward overlap)',
                                      min=0.0, max=10.0)

    def check(self) -> None:
        if self.min_baseline_ratio >= self.max_baseline_ratio:
            raise ConfigError('min_baseline_ratio must be smaller than max_baseline_ratio')


@dataclass
class PairCriteria(PairLimits):
    """The planner's parameters: which partners a new keyframe gets, and the depths a pair searches."""
    target_baseline_ratio: float = param(0.22, 'preferred baseline-to-height ratio when choosing partners',
                                         min=0.01, max=5.0)
    max_pairs_along: int = param(1, 'partners per new keyframe along its flight line', min=0, max=10)
    max_pairs_across: int = param(1, 'partners per new keyframe on neighbouring lines', min=0, max=10)
    max_axis_angle_deg: float = param(20.0, 'keyframes whose optical axes differ more are not paired',
                                      min=0.0, max=90.0)
    relief_m: float = param(gsd.AUTO, 'depth search half-range around the ground, m (terrain relief + buildings); '
                                  'the most the search spans; -1: from the flying height (core/gsd.py: 25 m at '
                                  '40 m)',
                         min=gsd.AUTO, max=1e4)
    depth_from_sparse_cloud: bool = param(True, 'search only the depths the pair\'s tie points span (the sparse '
                                                'cloud, widened by depth_margin_m, within relief_m): the SGBM '
                                                'cost is proportional to the search')
    depth_margin_m: float = param(gsd.AUTO, 'margin around the tie points\' depths, m (what has no tie point, e.g. a '
                                       'plain roof above its corners); -1: from the GSD (core/gsd.py: 4 m for the '
                                       'simulator\'s 640x480 at 40 m)',
                               min=gsd.AUTO, max=1e3)

    final_pairs_along: int = param(1, 'partners per keyframe along its line when the products are matched again '
                                      'from the final adjustment (io/densify.py); a second one (B/H twice the '
                                      'first) raised the simulator\'s DSM RMSE from 1.24 to 1.38 GSD',
                                   min=0, max=10)
    final_pairs_across: int = param(2, 'partners per keyframe on neighbouring lines when matching again from the '
                                       'final adjustment: after the flight there is time for more pairs than in '
                                       'flight, and a DSM cell needs two that agree (brighton_beach: 27 -> 39 '
                                       'pairs, measured share of the camera hull 47.1 -> 51.6 %)', min=0, max=10)
    final_min_overlap: float = param(0.25, 'min_overlap when matching again from the final adjustment: lines of '
                                           '50-60 % side overlap give the diagonal partner a quarter of the image',
                                     min=0.0, max=1.0)
    final_lr_check: bool = param(True, 'left-right check (StereoParams.lr_check) when matching again from the final '
                                       'adjustment; off, the check between pairs (export min_pairs 2) is left alone: '
                                       'half the SGBM time and 2 points more of brighton_beach measured, but the '
                                       'simulator\'s DSM RMSE 1.24 -> 3.4 GSD (occlusions at walls agree across pairs)')

    def check(self) -> None:
        gsd.check_auto_or_at_least(self, {'relief_m': 0.5, 'depth_margin_m': 0.0})
        super().check()

    def for_final(self) -> 'PairCriteria':
        """The criteria of the matching from the final adjustment: final_pairs_along / _across partners,
        final_min_overlap."""
        return dataclasses.replace(self, max_pairs_along=self.final_pairs_along,
                                   max_pairs_across=self.final_pairs_across, min_overlap=self.final_min_overlap)


@dataclass
class PairCandidate:
    other: int            # index (key) of the older keyframe
    baseline_ratio: float
    overlap: float
    along: bool           # baseline mostly along the image y axis of the new keyframe


def choose_pairs(camera: PinholeCamera, new_T: np.ndarray, others: dict, height_m: float,
                 crit: PairCriteria | None = None) -> list[PairCandidate]:
    """Best partners for a new keyframe among `others` {key: map_T_cam}; `height_m` is the depth to ground."""
    crit = crit or PairCriteria()
    cands = []
    for key, T in others.items():
        base = T[:3, 3] - new_T[:3, 3]
        ratio = float(np.linalg.norm(base)) / max(height_m, 1e-6)
        if not crit.min_baseline_ratio <= ratio <= crit.max_baseline_ratio:
            continue
        cosang = np.clip(new_T[:3, 2] @ T[:3, 2], -1.0, 1.0)
        if np.degrees(np.arccos(cosang)) > crit.max_axis_angle_deg:
            continue
        ov = overlap_fraction(camera, new_T, T, height_m, n=16)
        if ov < crit.min_overlap:
            continue
        b_cam = new_T[:3, :3].T @ base
        c = PairCandidate(key, ratio, ov, abs(b_cam[1]) >= abs(b_cam[0]))
        cands.append(c)
    target = crit.target_baseline_ratio
    cands.sort(key=lambda c: -(c.overlap - abs(np.log(c.baseline_ratio / target))))
    along = [c for c in cands if c.along][:crit.max_pairs_along]
    across = [c for c in cands if not c.along][:crit.max_pairs_across]
    return along + across


@dataclass
class PlannedPair(PairCandidate):
    """A pair to match: `other` (the older keyframe, camera a of stereo_pair) with the new keyframe."""
    depth_range_m: tuple[float, float]    # along the older keyframe's optical axis
    from_tie_points: bool                 # the range was narrowed to the pair's tie points


@dataclass
class PairPlan:
    status: str                           # OK, or BELOW_GROUND (the new keyframe is not above the ground)
    height_m: float                       # the new keyframe's height above the ground
    pairs: list[PlannedPair] = field(default_factory=list)


def plan_pairs(camera: PinholeCamera, new_T: np.ndarray, others: dict, ground_m: float, criteria: PairCriteria,
               depth_limits_m: tuple[float, float], tie_points_map: np.ndarray | None = None) -> PairPlan:
    """Partners of a new keyframe (pose `new_T`) among `others` {key: map_T_cam} and each pair's depth search.

    The search is the new keyframe's height above `ground_m` (map z, m) +- relief_m, within
    `depth_limits_m` (the stereo matcher's valid depths); with criteria.depth_from_sparse_cloud and
    `tie_points_map` (N, 3) it is narrowed to the depths the pair's own tie points span (when that
    leaves a non-empty range). Without tie points the ground-based range is all there is.
    """
    height = float(new_T[2, 3] - ground_m)
    if height <= 0:
        return PairPlan(BELOW_GROUND, height)
    if gsd.unresolved(criteria):   # left to the GSD: this keyframe's
        criteria, _ = gsd.resolve(criteria, gsd.derive(camera.width, camera.height, camera.fx, height))
    lo0 = max(depth_limits_m[0], height - criteria.relief_m)
    hi0 = min(depth_limits_m[1], height + criteria.relief_m)
    use_ties = criteria.depth_from_sparse_cloud and tie_points_map is not None
    plan = PairPlan(OK, height)
    for c in choose_pairs(camera, new_T, others, height, criteria):
        lo, hi, narrowed = lo0, hi0, False
        seen = (depth_range_from_points(camera, others[c.other], new_T, tie_points_map, criteria.depth_margin_m)
                if use_ties else None)
        if seen is not None and min(hi, seen[1]) > max(lo, seen[0]):
            lo, hi, narrowed = max(lo, seen[0]), min(hi, seen[1]), True
        plan.pairs.append(PlannedPair(**vars(c), depth_range_m=(lo, hi), from_tie_points=narrowed))
    return plan


def depth_range_from_points(camera: PinholeCamera, map_T_cam_a: np.ndarray, map_T_cam_b: np.ndarray,
                            points_map: np.ndarray, margin_m: float, min_points: int = 30) -> tuple | None:
    """Depths along camera a's axis (m) that the pair's tie points span, widened by `margin_m`.

    A survey's stereo search covers every height the terrain and buildings could have; the tie
    points the pair shares say which ones this pair sees, and the SGBM cost is proportional to the
    search. The 1st and 99th percentiles leave stray points out; the margin covers what has no tie
    point (a plain roof above its corners). None with fewer than `min_points` shared points.
    """
    P = np.asarray(points_map, float).reshape(-1, 3)
    if len(P) < min_points:
        return None
    # The footprint of a nadir-ish camera lies within its height times the half diagonal of the image
    # over the focal length of its nadir: a cheap cut before projecting.
    C = map_T_cam_a[:3, 3]
    reach = 1.5 * abs(C[2] - np.median(P[:, 2])) * np.hypot(camera.width, camera.height) / (2 * camera.fx)
    P = P[np.hypot(P[:, 0] - C[0], P[:, 1] - C[1]) < reach]
    seen, depth = np.ones(len(P), bool), None
    for T in (map_T_cam_a, map_T_cam_b):
        pc = (P - T[:3, 3]) @ T[:3, :3]
        uv, front = camera.project(pc)
        seen &= front & camera.in_image(uv)
        if depth is None:
            depth = pc[:, 2]
    if seen.sum() < min_points:
        return None
    lo, hi = np.percentile(depth[seen], (1.0, 99.0))
    return float(lo - margin_m), float(hi + margin_m)
