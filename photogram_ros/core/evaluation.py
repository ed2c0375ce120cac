"""Accuracy figures: check points triangulated from adjusted cameras, trajectory and DSM against truth.

Check points are found in the keyframe images (ArUco targets, as real GCP boards often are),
intersected from the ADJUSTED poses only (intersect_targets), and compared with their surveyed
coordinates; they never enter the adjustment. All coordinates here are in one `map` ENU frame: callers convert first.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from photogram_ros.core.at_geometry import reprojection_residuals_px, robust_intersection
from photogram_ros.core.camera import PinholeCamera


@dataclass
class TargetDetection:
    marker_id: int
    center_uv: np.ndarray   # (2,) pixel where the marker's diagonals cross (its centre in perspective)
    corners_uv: np.ndarray  # (4, 2)


def detect_targets(image: np.ndarray, dictionary: int = cv2.aruco.DICT_4X4_50) -> list[TargetDetection]:
    """ArUco targets in a BGR or grey image, corners refined to sub-pixel.

    An image up to `_FULL_SEARCH_MAX_SIDE_PX` on its long side is searched whole at full resolution. A larger
    one is searched for square candidates (decoded or not) on a copy reduced by an integer factor, and each
    candidate's neighbourhood is then searched again at full resolution by the same detector with the same
    absolute size limits, so every marker comes out with the id and corners the whole-image search gives
    (the neighbourhood is wider than the detector's threshold and refinement windows). A marker is missed
    only if the reduced copy shows no square where it is; in 4000 px photos (reduced 3x) no marker the
    whole-image search finds was missed (its own limit, 3 % of the long side as perimeter, is 30 px a side).
    """
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    long_px = max(grey.shape)
    if long_px <= _FULL_SEARCH_MAX_SIDE_PX:
        corners, ids, _ = _detector(dictionary).detectMarkers(grey)
        return _detections(corners, ids)
    regions = _candidate_regions(grey, dictionary)
    if sum((u1 - u0) * (v1 - v0) for u0, v0, u1, v1 in regions) > _MAX_REGION_SHARE * grey.size:
        regions = [(0, 0, grey.shape[1], grey.shape[0])]
    out = []
    for u0, v0, u1, v1 in regions:
        crop = grey[v0:v1, u0:u1]
        corners, ids, _ = _detector(dictionary, _FULL_PARAMS.minMarkerPerimeterRate * long_px / max(crop.shape),
                                    _FULL_PARAMS.maxMarkerPerimeterRate * long_px / max(crop.shape)
                                    ).detectMarkers(crop)
        for d in _detections([c + np.array([u0, v0], np.float32) for c in corners], ids):
            if not any(o.marker_id == d.marker_id and np.linalg.norm(o.center_uv - d.center_uv) < 1.0 for o in out):
                out.append(d)   # overlapping regions find the same marker
    return out


# Images with a longer side are searched on a reduced copy (then at full resolution around each candidate).
# 1080p is searched whole: at half size, 2-3 % of the 18-26 px markers the whole search finds were missed.
_FULL_SEARCH_MAX_SIDE_PX = 2000
# The reduced copy is at most this long: 4000 px at 1/3.
_REDUCED_MAX_SIDE_PX = 1600
# Squares looked for in the reduced copy: perimeter from 2 % of its long side (the full-resolution search's
# 3 % would lose markers the whole-image search finds: quantised contours of small squares run short).
_REDUCED_MIN_PERIMETER_RATE = 0.02
# Full-resolution neighbourhood around a candidate: beyond the 23 px adaptive-threshold window's half, the
# 5 px refinement window and the reduced copy's rounding, so the marker's threshold image is the
# whole image's; and a candidate's side beyond that, so the region's own edge (a square contour where the
# threshold image is cut) is too far from the marker and its white board to be grouped with them (the
# detector drops a whole group whose largest square touches the border).
_REGION_MARGIN_PX = 20
_REGION_MARGIN_SIDES = 1.0
# Regions covering more than this share of the image: the whole image is searched instead.
_MAX_REGION_SHARE = 0.9
_FULL_PARAMS = cv2.aruco.DetectorParameters()
_DETECTORS = threading.local()


def _detector(dictionary: int, min_perimeter_rate: float | None = None,
              max_perimeter_rate: float | None = None, refine: bool = True) -> cv2.aruco.ArucoDetector:
    """The ArUco detector for these settings, made once per thread (detectMarkers writes to its parameters)."""
    key = (dictionary, min_perimeter_rate, max_perimeter_rate, refine)
    cache = _DETECTORS.__dict__.setdefault('by_key', {})
    det = cache.get(key)
    if det is None:
        prm = cv2.aruco.DetectorParameters()
        prm.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX if refine else cv2.aruco.CORNER_REFINE_NONE
        if min_perimeter_rate is not None:
            prm.minMarkerPerimeterRate = min_perimeter_rate
        if max_perimeter_rate is not None:
            prm.maxMarkerPerimeterRate = max_perimeter_rate
        det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dictionary), prm)
        if len(cache) > 64:   # per-region rates vary with the region's size
            cache.clear()
        cache[key] = det
    return det


def _candidate_regions(grey: np.ndarray, dictionary: int) -> list[tuple[int, int, int, int]]:
    """Full-resolution boxes (u0, v0, u1, v1), disjoint, around every square the reduced copy shows."""
    h, w = grey.shape
    f = -(-max(h, w) // _REDUCED_MAX_SIDE_PX)
    small = cv2.resize(grey, (w // f, h // f), interpolation=cv2.INTER_AREA)
    corners, _, rejected = _detector(dictionary, _REDUCED_MIN_PERIMETER_RATE, refine=False).detectMarkers(small)
    boxes = []
    for c in list(corners) + list(rejected):
        uv = (c.reshape(4, 2).astype(float) + 0.5) * f - 0.5
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        pad = _REGION_MARGIN_PX + 2 * f + _REGION_MARGIN_SIDES * float(np.max(hi - lo))
        boxes.append([max(int(lo[0] - pad), 0), max(int(lo[1] - pad), 0),
                      min(int(np.ceil(hi[0] + pad)) + 1, w), min(int(np.ceil(hi[1] + pad)) + 1, h)])
    return _merge_overlapping(boxes)


def _merge_overlapping(boxes: list) -> list[tuple[int, int, int, int]]:
    merged = True
    while merged:
        merged, out = False, []
        for b in boxes:
            for m in out:
                if b[0] < m[2] and m[0] < b[2] and b[1] < m[3] and m[1] < b[3]:
                    m[:] = [min(m[0], b[0]), min(m[1], b[1]), max(m[2], b[2]), max(m[3], b[3])]
                    merged = True
                    break
            else:
                out.append(list(b))
        boxes = out
    return [tuple(b) for b in boxes]


def _detections(corners, ids) -> list[TargetDetection]:
    out = []
    for c, i in zip(corners, [] if ids is None else np.asarray(ids).ravel()):
        c = np.asarray(c).reshape(4, 2).astype(float)
        out.append(TargetDetection(int(i), _diagonal_intersection(c), c))
    return out


def _diagonal_intersection(c: np.ndarray) -> np.ndarray:
    p, r = c[0], c[2] - c[0]
    q, s = c[1], c[3] - c[1]
    denom = r[0] * s[1] - r[1] * s[0]
    if abs(denom) < 1e-12:
        return c.mean(axis=0)
    t = ((q[0] - p[0]) * s[1] - (q[1] - p[1]) * s[0]) / denom
    return p + t * r


# A target intersected with a dilution of precision above this (horizontally or vertically) is not measured yet:
# seen in 2 or 3 neighbouring images of one line, its intersection's own noise is what its residual shows (the
# simulator's sample flight: vertical DOP 11 / 5.6 from 2 / 3 images, 16-39 cm off from 2), not the block's
# error. From 4 images along a line it counts (DOP 3.5-3.7); seen across lines it is under 1 (0.8-0.9 there).
MAX_INTERSECTION_DOP = 5.0


@dataclass
class PointResiduals:
    names: list
    estimated_map: np.ndarray     # (K, 3)
    surveyed_map: np.ndarray      # (K, 3)
    n_views: np.ndarray           # (K,)
    missing: list = field(default_factory=list)   # surveyed but not seen in >= 2 keyframes
    rms_px: np.ndarray | None = None              # (K,) reprojection RMS of the detections used
    # Intersected, but too weakly to count (intersection_dop above the limit): [{'name', 'views', 'dop_h',
    # 'dop_v'}] (a DOP None: the rays do not fix the point); neither in the residuals nor in `missing`.
    weak: list = field(default_factory=list)

    @property
    def residuals(self) -> np.ndarray:
        return self.estimated_map - self.surveyed_map

    def rmse(self) -> dict:
        r = self.residuals
        if not len(r):
            return {'x_m': None, 'y_m': None, 'z_m': None, 'horizontal_m': None, 'count': 0}
        rms = np.sqrt(np.mean(r ** 2, axis=0))
        return {'x_m': float(rms[0]), 'y_m': float(rms[1]), 'z_m': float(rms[2]),
                'horizontal_m': float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1)))), 'count': int(len(r))}

    def table(self) -> list[dict]:
        return [{'name': n, 'dx_m': float(d[0]), 'dy_m': float(d[1]), 'dz_m': float(d[2]), 'views': int(v)}
                for n, d, v in zip(self.names, self.residuals, self.n_views)]


def intersection_dop(camera: PinholeCamera, map_T_cams: np.ndarray, uv: np.ndarray, X_map: np.ndarray) -> tuple:
    """(horizontal, vertical) dilution of precision of the point X_map (m) intersected from its detections uv (N, 2)
    px in the cameras map_T_cams (N, 4, 4, camera to map): its standard deviation, in ground pixels (the rays'
    mean depth over the focal length), for one pixel of detection noise per axis; horizontal is the 2D one
    (sqrt of the east and north variances summed). inf when the rays do not fix the point."""
    Ts, uv, X = np.asarray(map_T_cams, float).reshape(-1, 4, 4), np.asarray(uv, float).reshape(-1, 2), np.asarray(X_map, float)
    r0 = reprojection_residuals_px(camera, Ts, uv, X).ravel()
    step = 1e-4 * max(1.0, float(np.linalg.norm(X - Ts[:, :3, 3].mean(axis=0))))
    J = np.column_stack([(reprojection_residuals_px(camera, Ts, uv, X + d).ravel() - r0) / step
                         for d in np.eye(3) * step])
    try:
        C = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return float('inf'), float('inf')
    depth = np.einsum('nj,nj->n', Ts[:, :3, 2], X[None] - Ts[:, :3, 3]).mean()
    gsd = depth / camera.fx
    if not (np.all(np.isfinite(C)) and gsd > 0) or C[2, 2] < 0 or C[0, 0] + C[1, 1] < 0:
        return float('inf'), float('inf')
    return float(np.sqrt(C[0, 0] + C[1, 1]) / gsd), float(np.sqrt(C[2, 2]) / gsd)


def intersect_targets(camera: PinholeCamera, map_T_cams: np.ndarray, observations: dict, surveyed: dict,
                      max_px: float = 10.0, max_dop: float = MAX_INTERSECTION_DOP) -> PointResiduals:
    """Each surveyed target intersected from the adjusted cameras, against its survey: the one method of the
    live accuracy (stages/adjustment.py) and the flight report.

    map_T_cams: (N, 4, 4) the posed images; observations: key -> [(image index, (u, v) px)] of the target's
    detections; surveyed: key -> (name, (3,) surveyed xyz in map). A target is intersected robustly
    (core.at_geometry.robust_intersection: the largest set of its detections within max_px of one point, the
    point refined on them); one with fewer than two detections, or none that agree, is listed as missing; one whose
    detections in use fix it with a dilution of precision above max_dop (`intersection_dop`, either axis) is
    listed as weak: its residual would measure its own intersection's noise, not the block.
    Returns PointResiduals in the order of `surveyed`, with the detections used and their RMS (px)."""
    Ts = np.asarray(map_T_cams, float).reshape(-1, 4, 4)
    names, est, sur, views, rms, missing, weak = [], [], [], [], [], [], []
    for key, (name, xyz) in surveyed.items():
        obs = observations.get(key, [])
        got = None
        if len(obs) >= 2:
            Tk, uv = Ts[[int(c) for c, _ in obs]], np.array([uv for _, uv in obs], float).reshape(-1, 2)
            got = robust_intersection(camera, Tk, uv, max_px)
        if got is None:
            missing.append(name)
            continue
        used = np.linalg.norm(reprojection_residuals_px(camera, Tk, uv, np.asarray(got[0], float)), axis=1) <= max_px
        dop_h, dop_v = intersection_dop(camera, Tk[used], uv[used], got[0]) if used.sum() >= 2 else (np.inf, np.inf)
        if not max(dop_h, dop_v) <= max_dop:
            weak.append({'name': name, 'views': int(got[1]), 'dop_h': round(dop_h, 2) if np.isfinite(dop_h) else None,
                         'dop_v': round(dop_v, 2) if np.isfinite(dop_v) else None})
            continue
        names.append(name)
        est.append(np.asarray(got[0], float))
        sur.append(np.asarray(xyz, float))
        views.append(int(got[1]))
        rms.append(float(got[2]))
    return PointResiduals(names, np.array(est).reshape(-1, 3), np.array(sur).reshape(-1, 3), np.array(views, int),
                          missing, np.array(rms, float), weak)


def trajectory_errors(est_centres_map: np.ndarray, true_centres_map: np.ndarray) -> dict:
    """Camera-centre errors (both (K, 3) in the same frame, matched by row)."""
    d = np.asarray(est_centres_map, float) - np.asarray(true_centres_map, float)
    if not len(d):
        return {'count': 0}
    return {'count': int(len(d)), 'rmse_m': float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)))),
            'rmse_horizontal_m': float(np.sqrt(np.mean(np.sum(d[:, :2] ** 2, axis=1)))),
            'rmse_vertical_m': float(np.sqrt(np.mean(d[:, 2] ** 2))),
            'max_m': float(np.max(np.linalg.norm(d, axis=1)))}


def surface_errors(dz_m: np.ndarray, gsd_m: float) -> dict:
    """Height differences (estimate - truth) summarised in metres and in GSD."""
    dz = np.asarray(dz_m, float)
    dz = dz[np.isfinite(dz)]
    if not dz.size:
        return {'count': 0}
    a = np.abs(dz)
    return {'count': int(dz.size), 'median_abs_m': float(np.median(a)), 'p90_abs_m': float(np.percentile(a, 90)),
            'rmse_m': float(np.sqrt(np.mean(dz ** 2))), 'bias_m': float(np.median(dz)),
            'median_abs_gsd': float(np.median(a) / gsd_m), 'p90_abs_gsd': float(np.percentile(a, 90) / gsd_m),
            'rmse_gsd': float(np.sqrt(np.mean(dz ** 2)) / gsd_m)}


# Circular and linear errors at 90 % (ASPRS Positional Accuracy Standards, 2014/2023; OpenDroneMap's
# report): for a circular normal error (sigma_x ~ sigma_y, zero mean) CE90 = 2.1460 sigma with
# sigma = sqrt((RMSE_x^2 + RMSE_y^2) / 2); LE90 = 1.6449 RMSE_z for a normal vertical error.
CE90_PER_SIGMA = 2.1460
LE90_PER_RMSE = 1.6449
# ASPRS: the circular formula holds while min(RMSE_x, RMSE_y) / max(...) >= 0.6.
CIRCULAR_RATIO = 0.6


def ce90_le90(residuals_m) -> dict:
    """CE90 / LE90 of check-point residuals (N, 3: dX, dY, dZ, m) from the RMSE (normal errors, see above)
    and as the empirical 90th percentile of the radial / absolute vertical errors; {'n': 0} when empty."""
    r = np.asarray(residuals_m, float).reshape(-1, 3)
    r = r[np.all(np.isfinite(r), axis=1)]
    if not len(r):
        return {'n': 0}
    rx, ry, rz = np.sqrt(np.mean(r ** 2, axis=0))
    sigma = float(np.sqrt((rx ** 2 + ry ** 2) / 2))
    ratio = float(min(rx, ry) / max(rx, ry)) if max(rx, ry) > 0 else 1.0
    return {'n': int(len(r)), 'ce90_m': CE90_PER_SIGMA * sigma, 'le90_m': LE90_PER_RMSE * float(rz),
            'ce90_empirical_m': float(np.percentile(np.hypot(r[:, 0], r[:, 1]), 90)),
            'le90_empirical_m': float(np.percentile(np.abs(r[:, 2]), 90)),
            'rmse_x_over_y': ratio, 'circular': ratio >= CIRCULAR_RATIO,
            'method': ('CE90 = 2.1460 x sigma, sigma = sqrt((RMSEx^2 + RMSEy^2) / 2) (circular normal error, ASPRS); '
                       'LE90 = 1.6449 x RMSEz; *_empirical: the 90th percentile of the errors'
                       + (f' (only {len(r)} points: coarse)' if len(r) < 20 else ''))}
