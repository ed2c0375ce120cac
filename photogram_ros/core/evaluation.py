"""Accuracy figures: check points triangulated from adjusted cameras, trajectory and DSM against truth.

Check points are found in the keyframe images (ArUco targets, as real GCP boards often are),
triangulated from the ADJUSTED poses only, and compared with their surveyed coordinates; they never
enter the adjustment. All coordinates here are in one `map` ENU frame: callers convert first.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.triangulation import triangulate_points


@dataclass
class TargetDetection:
    marker_id: int
    center_uv: np.ndarray   # (2,) pixel where the marker's diagonals cross (its centre in perspective)
    corners_uv: np.ndarray  # (4, 2)


def detect_targets(image: np.ndarray, dictionary: int = cv2.aruco.DICT_4X4_50) -> list[TargetDetection]:
    """ArUco targets in a BGR or grey image, corners refined to sub-pixel."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dictionary))
    prm = det.getDetectorParameters()
    prm.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det.setDetectorParameters(prm)
    corners, ids, _ = det.detectMarkers(grey)
    out = []
    for c, i in zip(corners, [] if ids is None else ids.ravel()):
        c = c.reshape(4, 2).astype(float)
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


@dataclass
class PointResiduals:
    names: list
    estimated_map: np.ndarray     # (K, 3)
    surveyed_map: np.ndarray      # (K, 3)
    n_views: np.ndarray           # (K,)
    missing: list = field(default_factory=list)   # surveyed but not seen in >= 2 keyframes

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


def triangulate_targets(camera: PinholeCamera, map_T_cams: np.ndarray, detections: list[list[TargetDetection]],
                        surveyed: dict, max_reproj_px: float = 3.0) -> PointResiduals:
    """Triangulate each surveyed target (marker_id -> (name, xyz_map)) seen in >= 2 posed images."""
    ids = sorted(surveyed)
    index = {m: k for k, m in enumerate(ids)}
    oc, op, uv = [], [], []
    for c, dets in enumerate(detections):
        for d in dets:
            if d.marker_id in index:
                oc.append(c)
                op.append(index[d.marker_id])
                uv.append(d.center_uv)
    names, est, sur, views, missing = [], [], [], [], []
    if oc:
        tri = triangulate_points(camera, map_T_cams, np.array(oc), np.array(op), np.array(uv), n_points=len(ids))
    for k, m in enumerate(ids):
        name, xyz = surveyed[m]
        if not oc or not tri.valid[k] or tri.reproj_rms_px[k] > max_reproj_px:
            missing.append(name)
            continue
        names.append(name)
        est.append(tri.points_map[k])
        sur.append(np.asarray(xyz, float))
        views.append(int(tri.n_views[k]))
    return PointResiduals(names, np.array(est).reshape(-1, 3), np.array(sur).reshape(-1, 3), np.array(views, int),
                          missing)


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
