"""Which keyframes to pair for stereo: baseline-to-height ratio and image overlap.

Along a survey line consecutive keyframes are displaced along the image y axis; across lines, along
the image x axis. Both make valid stereo pairs; they are chosen separately so that a keyframe gets
its best along-line partner and, where lines overlap, its best across-line partner.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photogram_ros.core.camera import PinholeCamera


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
class PairCriteria:
    target_baseline_ratio: float = 0.22   # B/H the chooser prefers
    min_baseline_ratio: float = 0.08
    max_baseline_ratio: float = 0.8
    min_overlap: float = 0.4
    max_along: int = 1                    # partners per new keyframe along the line
    max_across: int = 1                   # partners per new keyframe across lines
    max_angle_deg: float = 20.0           # optical axes further apart than this are not paired


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
        if np.degrees(np.arccos(cosang)) > crit.max_angle_deg:
            continue
        ov = overlap_fraction(camera, new_T, T, height_m, n=16)
        if ov < crit.min_overlap:
            continue
        b_cam = new_T[:3, :3].T @ base
        c = PairCandidate(key, ratio, ov, abs(b_cam[1]) >= abs(b_cam[0]))
        cands.append(c)
    target = crit.target_baseline_ratio
    cands.sort(key=lambda c: -(c.overlap - abs(np.log(c.baseline_ratio / target))))
    along = [c for c in cands if c.along][:crit.max_along]
    across = [c for c in cands if not c.along][:crit.max_across]
    return along + across


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
