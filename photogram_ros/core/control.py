"""Ground control in flight: surveyed ArUco targets (GCPs and check points) and their detections.

A surveyed target is a board with an ArUco marker: its name, the marker id painted on it, WGS84
coordinates with an ellipsoidal height, and the survey's sigmas. Names starting with CHK are check
points (OpenDroneMap's convention; more can be named): they never enter the adjustment and are only
intersected from the adjusted cameras, so their residuals measure the map's accuracy. GCPs enter
the adjustment as point priors (core/incremental.py).

The tracker detects the markers in each keyframe (`detect_keyframe_targets`) and sends them with the
keyframe's features; `ControlSet.target_uv` turns them into `KeyframeRecord.target_uv` by marker id,
and `ControlSet.in_map` the surveyed coordinates into `ControlPoint`s of a map frame once its origin
is known. Files: photogram_ros/io/control_file.py.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.evaluation import detect_targets
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.incremental import ControlPoint
from photogram_ros.errors import DataError

# A surveyed board's centre is known to a few centimetres (RTK rover on the board); used where the
# file gives no sigma.
DEFAULT_SIGMA_H_M = 0.02
DEFAULT_SIGMA_V_M = 0.03

# One row per marker found in a keyframe: its id and the pixel where the marker's diagonals cross
# (distorted pixels, like the tracker's u, v; xn, yn undistorted normalized).
TARGET_DTYPE = np.dtype([('marker_id', '<u4'), ('u', '<f8'), ('v', '<f8'), ('xn', '<f8'), ('yn', '<f8')])

ARUCO_DICTIONARIES = ('DICT_4X4_50', 'DICT_4X4_100', 'DICT_4X4_250', 'DICT_5X5_50', 'DICT_5X5_100',
                      'DICT_6X6_50', 'DICT_6X6_250', 'DICT_7X7_50', 'DICT_ARUCO_ORIGINAL')


def is_check_name(name: str, check_names=()) -> bool:
    return name.upper().startswith('CHK') or name in set(check_names)


@dataclass
class SurveyedTarget:
    name: str
    marker_id: int
    lat_deg: float
    lon_deg: float
    h_m: float                       # above the WGS84 ellipsoid
    role: str                        # 'gcp' (constrains the adjustment) or 'check' (never used)
    sigma_h_m: float | None = None   # None: DEFAULT_SIGMA_H_M
    sigma_v_m: float | None = None


class ControlSet:
    """The surveyed targets of one flight, looked up by marker id."""

    def __init__(self, targets: list[SurveyedTarget], crs: str = '', source: str = ''):
        self.targets = list(targets)
        self.crs = crs
        self.source = source
        where = f'{source}: ' if source else ''
        self.by_marker: dict[int, SurveyedTarget] = {}
        names = set()
        for t in self.targets:
            if t.role not in ('gcp', 'check'):
                raise DataError(f'{where}target {t.name!r} has role {t.role!r}; use gcp or check')
            if t.name in names:
                raise DataError(f'{where}target name {t.name!r} appears twice: each board needs its own name')
            if t.marker_id in self.by_marker:
                raise DataError(f'{where}marker id {t.marker_id} is given to {self.by_marker[t.marker_id].name!r} '
                                f'and {t.name!r}: the boards cannot be told apart')
            names.add(t.name)
            self.by_marker[t.marker_id] = t

    def __len__(self) -> int:
        return len(self.targets)

    @property
    def gcp_names(self) -> list[str]:
        return [t.name for t in self.targets if t.role == 'gcp']

    @property
    def check_names(self) -> list[str]:
        return [t.name for t in self.targets if t.role == 'check']

    def with_checks(self, names) -> 'ControlSet':
        """The same targets with `names` (besides CHK*) made check points; an unknown name is an error."""
        names = [n for n in (s.strip() for s in names) if n]
        have = {t.name for t in self.targets}
        missing = [n for n in names if n not in have]
        if missing:
            raise DataError(f'check points {missing} are not in {self.source or "the control file"}; '
                            f'its targets are {sorted(have)}')
        return ControlSet([replace(t, role='check') if t.name in names else t for t in self.targets],
                          self.crs, self.source)

    def target_uv(self, targets: np.ndarray) -> tuple[dict, int]:
        """Detections of one keyframe (TARGET_DTYPE) -> ({target name: (u, v)}, detections of unknown
        marker ids). A marker seen twice in one image is ambiguous: both are left out (counted unknown)."""
        ids = np.asarray(targets['marker_id'], np.int64)
        uniq, counts = np.unique(ids, return_counts=True)
        twice = set(uniq[counts > 1].tolist())
        out, unknown = {}, 0
        for row, m in zip(targets, ids.tolist()):
            t = self.by_marker.get(m)
            if t is None or m in twice:
                unknown += 1
                continue
            out[t.name] = np.array([float(row['u']), float(row['v'])])
        return out, unknown

    def in_map(self, origin: LocalFrame, sigma_h_m: float | None = None,
               sigma_v_m: float | None = None) -> list[ControlPoint]:
        """Control points in the ENU frame at `origin`; sigmas given here override the file's."""
        out = []
        for t in self.targets:
            sh = sigma_h_m or t.sigma_h_m or DEFAULT_SIGMA_H_M
            sv = sigma_v_m or t.sigma_v_m or DEFAULT_SIGMA_V_M
            xyz = np.asarray(origin.geodetic_to_enu(t.lat_deg, t.lon_deg, t.h_m), float).reshape(3)
            out.append(ControlPoint(t.name, xyz, np.array([sh, sh, sv], float), t.role))
        return out


def detect_keyframe_targets(image: np.ndarray, camera: PinholeCamera,
                            dictionary: str = 'DICT_4X4_50') -> np.ndarray:
    """ArUco markers in a keyframe image, as TARGET_DTYPE rows (centre pixel, sub-pixel corners)."""
    if dictionary not in ARUCO_DICTIONARIES:
        raise DataError(f'unknown ArUco dictionary {dictionary!r}; choose from {list(ARUCO_DICTIONARIES)}')
    dets = detect_targets(image, getattr(cv2.aruco, dictionary))
    out = np.zeros(len(dets), TARGET_DTYPE)
    if dets:
        uv = np.array([d.center_uv for d in dets], float)
        xn = camera.pixel_to_normalized(uv)
        out['marker_id'] = [d.marker_id for d in dets]
        out['u'], out['v'] = uv[:, 0], uv[:, 1]
        out['xn'], out['yn'] = xn[:, 0], xn[:, 1]
    return out
