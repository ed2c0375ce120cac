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

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from photogram_ros.core.at_geometry import consensus, row_residuals
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.evaluation import detect_targets
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.incremental import ControlPoint
from photogram_ros.errors import DataError
from photogram_ros.params import param

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


def control_origin(points: list) -> LocalFrame | None:
    """A local frame at the median latitude, longitude and height of the GCPs among `points` ((lat_deg, lon_deg,
    h_m, role) each; of every point when none is a GCP): the map's origin for a block without positions of its
    own; None without points."""
    pts = [p[:3] for p in points if p[3] == 'gcp'] or [p[:3] for p in points]
    if not pts:
        return None
    return LocalFrame(*(float(v) for v in np.median(np.array(pts, float), axis=0)))


class ControlSet:
    """The surveyed targets of one flight, looked up by marker id."""

    def __init__(self, targets: list[SurveyedTarget], crs: str = '', source: str = '',
                 file_heights: dict | None = None):
        self.targets = list(targets)
        self.crs = crs
        self.source = source
        # name -> height as written in the file (placeholders such as 0 or 400 m show there, not after
        # a geoid conversion)
        self.file_heights = dict(file_heights or {})
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
                          self.crs, self.source, self.file_heights)

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

    def marker_ties(self, targets: np.ndarray, prefix: str = 'MTP_aruco') -> dict:
        """Detections of one keyframe (TARGET_DTYPE) of markers the control does not list, as manual tie
        points: {f'{prefix}{marker id}': (u, v)} (a marker seen twice in the image is left out). In flight
        they join the block's tie points measured to a pixel (IncrementalAT.add_ties)."""
        ids = np.asarray(targets['marker_id'], np.int64)
        uniq, counts = np.unique(ids, return_counts=True)
        twice = set(uniq[counts > 1].tolist())
        return {f'{prefix}{m}': np.array([float(row['u']), float(row['v'])]) for row, m in zip(targets, ids.tolist())
                if m not in self.by_marker and m not in twice}

    def central_origin(self) -> LocalFrame | None:
        """The map's origin for a flight without GNSS: control_origin() of the targets."""
        return control_origin([(t.lat_deg, t.lon_deg, t.h_m, t.role) for t in self.targets])

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
    return _target_rows([(d.marker_id, d.center_uv) for d in dets], camera)


def _target_rows(found: list, camera: PinholeCamera) -> np.ndarray:
    """[(marker id, (2,) centre pixel)] -> TARGET_DTYPE rows."""
    out = np.zeros(len(found), TARGET_DTYPE)
    if found:
        uv = np.array([c for _, c in found], float).reshape(-1, 2)
        xn = camera.pixel_to_normalized(uv)
        out['marker_id'] = [m for m, _ in found]
        out['u'], out['v'] = uv[:, 0], uv[:, 1]
        out['xn'], out['yn'] = xn[:, 0], xn[:, 1]
    return out


def detect_keyframe_targets_encoded(data, camera: PinholeCamera, dictionary: str = 'DICT_4X4_50') -> np.ndarray:
    """detect_keyframe_targets of a keyframe still compressed (its JPEG bytes, as the camera sent them): decoded
    in grey only (libjpeg's luma, no colour conversion: about a third of the colour decode's time at 20 MP), then
    searched as detect_targets searches (above 2000 px: squares found on a reduced copy, markers read at full
    resolution in the regions around them). DataError if undecodable or not the camera's size."""
    return detect_keyframe_targets(_full_grey(data, camera), camera, dictionary)


def _full_grey(data, camera: PinholeCamera) -> np.ndarray:
    """A keyframe's JPEG bytes decoded in grey at full size; DataError if undecodable or not the camera's size."""
    buf = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1)
    grey = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION) if buf.size else None
    if grey is None:
        raise DataError(f'keyframe image ({buf.size} bytes) cannot be decoded for the target search')
    if (grey.shape[1], grey.shape[0]) != (camera.width, camera.height):
        raise DataError(f'keyframe image is {grey.shape[1]}x{grey.shape[0]}, the camera {camera.width}x'
                        f'{camera.height}')
    return grey


# --- targets searched only where they can be ------------------------------------------------------
#
# A keyframe's GNSS position and the surveyed targets' coordinates say where a target can appear in its image:
# a target d metres (horizontally) from the camera, H metres below it, is imaged about d * f / H pixels from the
# principal point of a nadir camera, at an azimuth the unknown heading leaves open. The GNSS error, the tilt of
# the camera from nadir (gimbal, roll in a turn) and the lens's distortion widen that radius into a ring; a
# target whose ring misses the image is not looked for. The rings' bounding box is searched for squares on the
# reduced image (the keyframe's image for keyframes/image, decoded once at its reduction), and the full
# resolution is decoded only when a square lies in a ring, then searched only around each such square.

@dataclass
class TargetRegionOptions:
    """How far from its GNSS-predicted place a target is looked for."""
    gnss_margin_m: float = param(5.0, 'target search: horizontal GNSS error allowed beyond 3 sigma of the fix, m',
                                 min=0.0, max=10000.0)
    tilt_margin_deg: float = param(15.0, 'target search: camera tilt from nadir allowed (gimbal, roll and pitch), '
                                         'deg', min=0.0, max=60.0)
    radius_margin: float = param(0.05, 'target search: relative slack on the predicted image radius (the lens distortion, '
                                       'the relief of the terrain)', min=0.0, max=1.0)


@dataclass
class TargetRegions:
    """Where the targets of a ControlSet can be in one keyframe's image.

    status: 'rings' (rings_px holds (marker_id, r_min_px, r_max_px) about the principal point for each
    target that can be in the image; empty: none can, nothing to search), or 'unknown' (no usable height of
    the camera above the targets: the whole image is to be searched), with `why`."""
    status: str
    rings_px: list = field(default_factory=list)
    why: str = ''

    def box(self, camera: PinholeCamera) -> tuple[int, int, int, int] | None:
        """The image box (u0, v0, u1, v1) the rings cover, or None when they cover nothing."""
        if self.status != 'rings':
            return (0, 0, camera.width, camera.height)
        if not self.rings_px:
            return None
        r = max(r1 for _, _, r1 in self.rings_px)
        u0, v0 = max(0, int(camera.cx - r)), max(0, int(camera.cy - r))
        u1, v1 = min(camera.width, int(np.ceil(camera.cx + r)) + 1), min(camera.height, int(np.ceil(camera.cy + r)) + 1)
        return (u0, v0, u1, v1) if u1 > u0 and v1 > v0 else None

    def contains(self, camera: PinholeCamera, uv: np.ndarray, slack_px: float = 0.0) -> np.ndarray:
        """(N,) whether pixels `uv` (N, 2) lie in a ring (widened by slack_px); all True when unknown."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        if self.status != 'rings':
            return np.ones(len(uv), bool)
        r = np.hypot(uv[:, 0] - camera.cx, uv[:, 1] - camera.cy)
        out = np.zeros(len(uv), bool)
        for _, r0, r1 in self.rings_px:
            out |= (r >= r0 - slack_px) & (r <= r1 + slack_px)
        return out


def target_regions(camera: PinholeCamera, control: ControlSet, lat_deg: float, lon_deg: float, h_m: float,
                   sigma_h_m: float = 0.0, opt: TargetRegionOptions | None = None) -> TargetRegions:
    """The rings of the image in which the targets of `control` can appear, for a camera at the GNSS position
    (lat_deg, lon_deg, h_m: ellipsoidal, like the control's heights) with a horizontal sigma `sigma_h_m`."""
    opt = opt or TargetRegionOptions()
    if not control.targets:
        return TargetRegions('rings', [], 'no surveyed targets')
    frame = LocalFrame(float(lat_deg), float(lon_deg), float(h_m))
    enu = np.asarray(frame.geodetic_to_enu(np.array([t.lat_deg for t in control.targets], float),
                                           np.array([t.lon_deg for t in control.targets], float),
                                           np.array([t.h_m for t in control.targets], float)), float).reshape(-1, 3)
    height_m = -enu[:, 2]
    if not np.all(np.isfinite(enu)) or np.any(height_m < 1.0):
        return TargetRegions('unknown', [], f'the camera is {float(np.min(height_m)):.1f} m above a target by its '
                             'GNSS height and the control\'s: the heights do not tell where the targets are')
    f_px = 0.5 * (camera.fx + camera.fy)
    half_diag_px = max(np.hypot(u - camera.cx, v - camera.cy) for u in (0, camera.width) for v in (0, camera.height))
    rings = []
    for t, (e, n, _), hgt in zip(control.targets, enu, height_m):
        d = float(np.hypot(e, n))
        m = opt.gnss_margin_m + 3.0 * sigma_h_m + hgt * np.tan(np.radians(opt.tilt_margin_deg))
        r0 = max(0.0, d - m) * f_px / hgt * (1.0 - opt.radius_margin)
        r1 = (d + m) * f_px / hgt * (1.0 + opt.radius_margin)
        if r0 <= half_diag_px:
            rings.append((t.marker_id, float(r0), float(r1)))
    return TargetRegions('rings', rings, '' if rings else 'no surveyed target near the footprint')


def detect_targets_in_regions(encoded, reduced_grey: np.ndarray, camera: PinholeCamera, regions: TargetRegions,
                              dictionary: str = 'DICT_4X4_50') -> tuple[np.ndarray, dict]:
    """detect_keyframe_targets of a compressed keyframe searched only in `regions`: squares looked for on
    `reduced_grey` (the keyframe decoded at an integer reduction, e.g. libjpeg's DCT scaling) within the
    regions' box; the JPEG `encoded` decoded at full resolution (grey) only when a square lies in a ring, and
    searched there only in a window around each such square (the same margins as detect_targets' windows).
    Returns (TARGET_DTYPE rows, {'squares', 'windows', 'window_px', 'full_decode'} counts: squares in the rings,
    full-resolution windows searched and their pixels, full decodes). DataError if undecodable."""
    if dictionary not in ARUCO_DICTIONARIES:
        raise DataError(f'unknown ArUco dictionary {dictionary!r}; choose from {list(ARUCO_DICTIONARIES)}')
    stats = {'squares': 0, 'windows': 0, 'window_px': 0, 'full_decode': 0}
    box = regions.box(camera)
    if box is None:
        return np.zeros(0, TARGET_DTYPE), stats
    f = camera.width / reduced_grey.shape[1]
    if abs(f - round(f)) > 0.02 or round(f) < 1:
        raise DataError(f'reduced image {reduced_grey.shape[1]} px wide is no integer reduction of the camera\'s '
                        f'{camera.width} px')
    f = int(round(f))
    u0, v0, u1, v1 = (int(box[0] // f), int(box[1] // f), int(-(-box[2] // f)), int(-(-box[3] // f)))
    small = reduced_grey[v0:v1, u0:u1]
    if min(small.shape) < 8:
        return np.zeros(0, TARGET_DTYPE), stats
    prm = cv2.aruco.DetectorParameters()
    prm.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    # Squares from 2 % of the reduced image's long side as perimeter (detect_targets' reduced search), whatever
    # the box's size; up to the whole reduced image's.
    long_small = max(small.shape)
    prm.minMarkerPerimeterRate = _REDUCED_MIN_PERIMETER_RATE * max(reduced_grey.shape) / long_small
    prm.maxMarkerPerimeterRate = 4.0 * max(reduced_grey.shape) / long_small
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), prm)
    corners, _, rejected = det.detectMarkers(small)
    windows = []
    for c in list(corners) + list(rejected):
        uv = (c.reshape(4, 2).astype(float) + np.array([u0, v0]) + 0.5) * f - 0.5
        centre = uv.mean(axis=0)
        side = float(np.max(np.ptp(uv, axis=0)))
        if not regions.contains(camera, centre[None], slack_px=side)[0]:
            continue
        pad = _WINDOW_MARGIN_PX + 2 * f + _WINDOW_MARGIN_SIDES * side
        lo = np.floor(uv.min(axis=0) - pad).astype(int)
        hi = np.ceil(uv.max(axis=0) + pad).astype(int)
        windows.append((max(0, int(lo[0])), max(0, int(lo[1])), min(camera.width, int(hi[0]) + 1),
                        min(camera.height, int(hi[1]) + 1)))
    stats['squares'] = len(windows)
    if not windows:
        return np.zeros(0, TARGET_DTYPE), stats
    grey = _full_grey(encoded, camera)
    stats['full_decode'] = 1
    windows = _merged(windows)
    stats['windows'] = len(windows)
    stats['window_px'] = int(sum((a1 - a0) * (b1 - b0) for a0, b0, a1, b1 in windows))
    found = []
    aruco = getattr(cv2.aruco, dictionary)
    for a0, b0, a1, b1 in windows:
        for d in detect_targets(grey[b0:b1, a0:a1], aruco):
            c = d.center_uv + np.array([a0, b0], float)
            if not any(m == d.marker_id and np.linalg.norm(c - o) < 1.0 for m, o in found):
                found.append((d.marker_id, c))
    return _target_rows(found, camera), stats


# detect_targets' reduced search and windows (core/evaluation.py): squares from 2 % of the reduced image's long
# side as perimeter; a window reaches 20 px, two reduced pixels and one square's side beyond the square.
_REDUCED_MIN_PERIMETER_RATE = 0.02
_WINDOW_MARGIN_PX = 20
_WINDOW_MARGIN_SIDES = 1.0


def _merged(boxes: list) -> list:
    """Overlapping boxes (u0, v0, u1, v1) merged until disjoint."""
    boxes = [list(b) for b in boxes]
    merged = True
    while merged:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    boxes[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return [tuple(b) for b in boxes]


# --- control rows checked against the GNSS-only block ---------------------------------------
#
# A control file from the field has faults a surveyor does not see: rows naming a photo of another
# flight, every row of one photo naming the wrong photo, pixels outside the image, heights left as
# placeholders (0 m, 400 m). `vet_control` looks at every row and every point against the block
# adjusted on its GNSS alone (before any GCP pulls on it) and gives each row a fate and each GCP a
# use: full, horizontal only (its height contradicted by the GNSS far beyond both sigmas), or unused.

ROW_FATES = ('used', 'photo_not_in_set', 'photo_not_oriented', 'pixel_outside_image', 'duplicate', 'outlier',
             'point_unused')
POINT_USES = ('full', 'horizontal', 'unused', 'check')
# A vertical sigma that carries no weight: a GCP used horizontally only (its height is a free unknown).
HORIZONTAL_ONLY_SIGMA_V_M = 1.0e4


@dataclass
class ControlVettingOptions:
    """How control rows and points are checked against the GNSS-only block."""
    max_row_residual_px: float = param(10.0, 'a control row farther than this from where its point intersects '
                                             'from the other rows (GNSS-only block) is an outlier, px',
                                       min=0.5, max=10000.0)
    wrong_photo_m: float = param(5.0, 'an outlier row this far from its point on the ground (m, or 5 sigma of the '
                                      'GNSS) likely names the wrong photo (or point), not a mis-click',
                                 min=0.1, max=10000.0)
    height_sigmas: float = param(5.0, 'a surveyed coordinate disagreeing with its GNSS-only intersection by more '
                                      'than this many combined sigmas (survey, GNSS, intersection) is contradicted',
                                 min=1.0, max=1000.0)
    min_contradiction_m: float = param(1.0, '... and by at least this much, m', min=0.0, max=10000.0)
    contradicted_heights: str = param('horizontal', 'a GCP whose height the GNSS contradicts: used horizontally '
                                                    'only (default) or as given ("use")',
                                      choices=('horizontal', 'use'))


@dataclass
class ControlRow:
    """One observation of a control file: point `name` clicked (or detected) in photo `image`."""
    line: int                    # line in the file (0: a marker detection)
    image: str
    name: str
    uv: np.ndarray               # (2,) distorted pixel


@dataclass
class RowFate:
    row: ControlRow
    fate: str                    # one of ROW_FATES
    reason: str = ''
    residual_px: float | None = None    # against the point's GNSS-only intersection from the other rows
    residual_m: float | None = None     # the same on the ground (px times depth / f)
    likely_wrong_photo: bool = False

    def to_dict(self) -> dict:
        return {'line': self.row.line, 'image': self.row.image, 'name': self.row.name,
                'uv_px': [float(v) for v in self.row.uv], 'fate': self.fate, 'reason': self.reason,
                'residual_px': self.residual_px, 'residual_m': self.residual_m,
                'likely_wrong_photo': self.likely_wrong_photo}


@dataclass
class PointCheck:
    """A control point against its intersection from the GNSS-only block."""
    name: str
    role: str
    use: str                             # one of POINT_USES
    reason: str = ''
    rows: int = 0                        # rows in the file
    usable_rows: int = 0                 # consistent rows, in oriented photos
    gnss_only_map_m: list | None = None  # intersection from the GNSS-only block (map ENU)
    d_h_m: float | None = None           # horizontal distance, intersection - survey
    d_v_m: float | None = None           # intersection - survey, up
    sigma_h_m: float | None = None       # combined: survey, GNSS, intersection
    sigma_v_m: float | None = None
    horizontal: str = 'not_checked'      # 'agrees' | 'contradicted' | 'not_checked'
    vertical: str = 'not_checked'
    placeholder: str = ''                # why the height looks like a placeholder ('' if not)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class ControlVetting:
    rows: list                           # [RowFate], in the file's order
    points: dict                         # name -> PointCheck
    wrong_photos: dict                   # image -> why it is likely the wrong photo
    height_suspect: str = ''             # '' | 'control_heights' | 'photo_altitudes' | 'either'
    notes: list = field(default_factory=list)   # the faults, one sentence each

    def accepted_uv(self) -> dict:
        """{image: {point name: (u, v)}} of the rows used."""
        out: dict = {}
        for f in self.rows:
            if f.fate == 'used':
                out.setdefault(f.row.image, {})[f.row.name] = np.asarray(f.row.uv, float)
        return out

    def control_points(self, control: list[ControlPoint]) -> list[ControlPoint]:
        """The control as the adjustment should take it: GCPs used horizontally only get a vertical sigma
        that carries no weight, unused GCPs become check points (their rows are not passed anyway)."""
        out = []
        for c in control:
            p = self.points.get(c.name)
            if c.role != 'gcp' or p is None or p.use == 'full':
                out.append(c)
            elif p.use == 'horizontal':
                out.append(replace(c, sigma_m=np.array([c.sigma_m[0], c.sigma_m[1], HORIZONTAL_ONLY_SIGMA_V_M])))
            else:
                out.append(replace(c, role='check'))
        return out

    def counts(self) -> dict:
        return {f: sum(r.fate == f for r in self.rows) for f in ROW_FATES}

    def merge(self, later: 'ControlVetting', file_heights: dict | None = None,
              opt: ControlVettingOptions | None = None) -> list[str]:
        """Take in the rows and points of a later vetting (in flight, targets are checked as they become
        due) and give the verdicts over every point so far again; returns the notes that are new."""
        before = set(self.notes)
        self.rows += later.rows
        self.points.update(later.points)
        self.wrong_photos.update(later.wrong_photos)
        _height_verdict(self, file_heights or {}, opt or ControlVettingOptions())
        # What an unchecked vetting said is not made again from the points: keep it.
        kept = [n for n in self.notes + list(later.notes)
                if n.startswith('the control could not be checked') or 'not checked against the block' in n]
        self.notes = []
        _notes(self)
        self.notes += [n for n in kept if n not in self.notes]
        return [n for n in self.notes if n not in before]

    def to_dict(self) -> dict:
        return {'rows': [r.to_dict() for r in self.rows], 'row_fates': self.counts(),
                'points': {n: p.to_dict() for n, p in self.points.items()}, 'wrong_photos': dict(self.wrong_photos),
                'height_suspect': self.height_suspect, 'faults': list(self.notes)}


def _ray_on_plane(camera: PinholeCamera, T: np.ndarray, uv: np.ndarray, z0: float) -> np.ndarray | None:
    d = T[:3, :3] @ np.append(camera.pixel_to_normalized(np.asarray(uv, float)[None])[0], 1.0)
    if abs(d[2]) < 1e-9:
        return None
    s = (z0 - T[2, 3]) / d[2]
    return T[:3, 3] + s * d if s > 0 else None


def _placeholders(file_heights: dict, names: list[str]) -> dict:
    """name -> why its height looks like a placeholder: exactly 0, or the same to the millimetre as another
    point's of the file (no two surveyed boards share a height to the millimetre)."""
    out = {}
    for n in names:
        z = file_heights.get(n)
        if z is None:
            continue
        same = [m for m in file_heights if m != n and abs(file_heights[m] - z) < 5e-4]
        if abs(z) < 5e-4:
            out[n] = 'height exactly 0 m in the file'
        elif same:
            out[n] = f'height {z:.3f} m in the file, the same to the millimetre as {", ".join(same)}'
    return out


def vet_control(camera: PinholeCamera, poses: dict, images: set, rows: list[ControlRow],
                control: list[ControlPoint], block_sigma_enu_m, tie_points_map_m=None, file_heights=None,
                opt: ControlVettingOptions | None = None, detected: bool = False) -> ControlVetting:
    """Every control row's fate and every point's use, against the block adjusted on its GNSS alone.

    camera, poses ({image: map_T_cam} of the oriented photos): the GNSS-only block; images: every photo
    of the set (oriented or not); control: the surveyed points (map ENU, sigmas, roles); block_sigma_enu_m:
    (3,) the block's absolute uncertainty from its GNSS (E, N, U sigma, m); tie_points_map_m: (N, 3) its tie
    points (the ground under a point seen once); file_heights: {name: z as written} (placeholder heights);
    detected: the rows are marker detections (in flight), not clicks: a far row is a misread marker or a
    second board with the same id, not a wrong photo.
    """
    opt = opt or ControlVettingOptions()
    by_name = {c.name: c for c in control}
    sig_b = np.asarray(block_sigma_enu_m, float).reshape(3)
    suspect = 'likely a misread marker or a second board with its id' if detected else 'likely the wrong photo'
    fates = _file_fates(camera, poses, images, rows, by_name)
    tie = None if tie_points_map_m is None else np.asarray(tie_points_map_m, float).reshape(-1, 3)
    points = {}
    for name in dict.fromkeys([r.name for r in rows if r.name in by_name]):
        c = by_name[name]
        mine = [f for f in fates if f.row.name == name]
        cand = [f for f in mine if not f.fate]
        p = PointCheck(name, c.role, 'check' if c.role == 'check' else 'full', rows=len(mine))
        points[name] = p
        Ts = np.array([poses[f.row.image] for f in cand]).reshape(-1, 4, 4)
        uv = np.array([f.row.uv for f in cand], float).reshape(-1, 2)
        X, inl = consensus(camera, Ts, uv, opt.max_row_residual_px) if len(cand) >= 2 else (None, np.zeros(0, bool))
        if X is not None:
            e, em = row_residuals(camera, Ts, uv, X)
            for f, ei, emi, ok in zip(cand, e, em, inl):
                f.residual_px, f.residual_m = float(ei), float(emi)
                if not ok:
                    f.fate = 'outlier'
                    f.likely_wrong_photo = bool(emi > max(opt.wrong_photo_m, 5 * float(np.hypot(*sig_b[:2]))))
                    f.reason = (f'{ei:.0f} px ({emi:.1f} m on the ground) from where {name} intersects from its other '
                                f'rows in the GNSS-only block' + (f': {suspect}' if f.likely_wrong_photo else ''))
        else:
            # No two rows agree: each row's ray on the ground against the survey, horizontally.
            z0 = float(c.map_xyz[2])
            if tie is not None and len(tie):
                near = tie[np.hypot(*(tie[:, :2] - c.map_xyz[:2]).T) < 20.0]
                z0 = float(np.median(near[:, 2])) if len(near) else z0
            tol = max(opt.wrong_photo_m, 5 * float(np.hypot(*sig_b[:2])))
            for f, T in zip(cand, Ts):
                G = _ray_on_plane(camera, T, f.row.uv, z0)
                d = float(np.hypot(*(G[:2] - c.map_xyz[:2]))) if G is not None else float('inf')
                f.residual_m = d if np.isfinite(d) else None
                if d > tol:
                    f.fate, f.likely_wrong_photo = 'outlier', True
                    f.reason = (f'its ray meets the ground {d:.1f} m from {name}\'s surveyed position (GNSS-only '
                                f'block): {suspect}')
        usable = [f for f in cand if not f.fate]
        p.usable_rows = len(usable)
        if X is None or len(usable) < 2:
            p.use = 'unused'
            p.reason = (f'fewer than two usable rows ({len(usable)} of {len(mine)}): a point in one photo cannot be '
                        'intersected')
        else:
            _compare_with_survey(p, c, X, Ts[inl], sig_b, camera, opt)
            if p.horizontal == 'contradicted' and c.role == 'gcp':
                p.use = 'unused'
                p.reason = (f'its surveyed position is {p.d_h_m:.2f} m from where the GNSS-only block intersects it '
                            f'(sigma {p.sigma_h_m:.2f} m): wrong coordinates or wrong name?')
        for f in usable:
            f.fate = 'used' if p.use != 'unused' else 'point_unused'
            if f.fate == 'point_unused':
                f.reason = f'{name} is not used: {p.reason}'
    vet = ControlVetting(fates, points, {} if detected else _wrong_photos(fates))
    _height_verdict(vet, file_heights or {}, opt)
    _notes(vet)
    return vet


def _file_fates(camera: PinholeCamera, poses: dict, images: set, rows: list[ControlRow], by_name: dict) -> list:
    """[RowFate] of the rows: the fates the file and the photo set decide alone ('' for the rows left to
    check against the block)."""
    fates = [RowFate(r, '') for r in rows]
    seen = set()
    for f in fates:
        r = f.row
        if r.image not in images:
            f.fate, f.reason = 'photo_not_in_set', f'{r.image} is not one of the photos given'
        elif r.image not in poses:
            f.fate, f.reason = 'photo_not_oriented', f'{r.image} could not be oriented'
        elif r.name not in by_name:
            f.fate, f.reason = 'point_unused', f'{r.name} has no surveyed coordinates'
        elif not (0 <= r.uv[0] < camera.width and 0 <= r.uv[1] < camera.height):
            f.fate, f.reason = ('pixel_outside_image', f'pixel ({r.uv[0]:.1f}, {r.uv[1]:.1f}) is outside the '
                                f'{camera.width}x{camera.height} image')
        elif (r.image, r.name) in seen:
            f.fate, f.reason = 'duplicate', f'{r.name} is given twice in {r.image}: the first row is used'
        seen.add((r.image, r.name))
    return fates


def unchecked_vetting(camera: PinholeCamera, poses: dict, images: set, rows: list[ControlRow],
                      control: list[ControlPoint], why: str, file_heights: dict | None = None) -> ControlVetting:
    """The control taken as given when no GNSS-only block can judge it (`why`: e.g. a flight that never
    turned, whose roll about its line only the GCPs fix). Only what the file and the photo set show are
    acted on: rows naming photos not in the set (or not oriented, or pixels off the image) are not used, a
    point with fewer than two usable rows neither, and a placeholder height (exactly 0, or the same to the
    millimetre as another point's) makes its GCP horizontal only. Arguments as vet_control's."""
    by_name = {c.name: c for c in control}
    fates = _file_fates(camera, poses, images, rows, by_name)
    names = list(dict.fromkeys(r.name for r in rows if r.name in by_name))
    ph = _placeholders(file_heights or {}, [n for n in names if by_name[n].role == 'gcp'])
    points = {}
    for n in names:
        c, mine = by_name[n], [f for f in fates if f.row.name == n]
        usable = [f for f in mine if not f.fate]
        p = PointCheck(n, c.role, 'check' if c.role == 'check' else 'full', f'not checked: {why}',
                       rows=len(mine), usable_rows=len(usable))
        if len(usable) < 2:
            p.use = 'unused'
            p.reason = (f'fewer than two usable rows ({len(usable)} of {len(mine)}): a point in one photo cannot be '
                        'intersected')
        elif n in ph:
            p.placeholder, p.use = ph[n], 'horizontal'
            p.reason = f'{ph[n]}: a placeholder?; used horizontally only (not checked against the block: {why})'
        for f in usable:
            f.fate = 'used' if p.use != 'unused' else 'point_unused'
            f.reason = '' if p.use != 'unused' else f'{n} is not used: {p.reason}'
        points[n] = p
    vet = ControlVetting(fates, points, {})
    _notes(vet)
    vet.notes.insert(0, f'the control could not be checked against the GNSS: {why}; its GCPs are used as given')
    vet.notes += [f'GCP {p.name}: {p.reason}' for p in points.values() if p.use == 'horizontal']
    return vet


def _compare_with_survey(p: PointCheck, c: ControlPoint, X: np.ndarray, Ts: np.ndarray, sig_b: np.ndarray,
                         camera: PinholeCamera, opt: ControlVettingOptions) -> None:
    d = X - c.map_xyz
    # The intersection's own uncertainty: 1 px across, and along the rays by the depth over the baseline.
    depth = float(np.median(np.linalg.norm(Ts[:, :3, 3] - X, axis=1)))
    C = Ts[:, :3, 3]
    base = float(np.max(np.linalg.norm(C[:, None] - C[None], axis=2))) if len(C) > 1 else 0.0
    lateral = depth / camera.fx
    along = lateral * depth / max(base, 1e-3)
    sh = float(np.sqrt(c.sigma_m[0] ** 2 + np.hypot(*sig_b[:2]) ** 2 + lateral ** 2))
    sv = float(np.sqrt(c.sigma_m[2] ** 2 + sig_b[2] ** 2 + along ** 2))
    p.gnss_only_map_m = [float(v) for v in X]
    p.d_h_m, p.d_v_m, p.sigma_h_m, p.sigma_v_m = float(np.hypot(d[0], d[1])), float(d[2]), sh, sv
    p.horizontal = 'contradicted' if p.d_h_m > max(opt.height_sigmas * sh, opt.min_contradiction_m) else 'agrees'
    p.vertical = 'contradicted' if abs(p.d_v_m) > max(opt.height_sigmas * sv, opt.min_contradiction_m) else 'agrees'


def _wrong_photos(fates: list[RowFate]) -> dict:
    """Photos whose rows are far from their points on the ground: every checked row of the photo, or two
    or more of them (the rows of another photo given this one's name)."""
    out = {}
    for img in dict.fromkeys(f.row.image for f in fates):
        mine = [f for f in fates if f.row.image == img and f.fate in ('used', 'outlier', 'point_unused')
                and f.residual_m is not None]
        wrong = [f for f in mine if f.likely_wrong_photo]
        if wrong and (len(wrong) == len(mine) or len(wrong) >= 2):
            dm = [f.residual_m for f in wrong]
            which = ('its only checked row is' if len(mine) == 1 else
                     f'all {len(wrong)} of its checked rows are' if len(wrong) == len(mine) else
                     f'{len(wrong)} of its {len(mine)} checked rows are')
            out[img] = (f'{which} {min(dm):.0f}-{max(dm):.0f} m from where their points are '
                        f'({", ".join(f.row.name for f in wrong)}, lines {", ".join(str(f.row.line) for f in wrong)}): '
                        'the rows likely name the wrong photo')
    return out


def _height_verdict(vet: ControlVetting, file_heights: dict, opt: ControlVettingOptions) -> None:
    """GCP heights the GNSS-only block contradicts: who is the suspect, and the GCP's use."""
    gcps = [p for p in vet.points.values() if p.role == 'gcp' and p.use != 'unused']
    names = [p.name for p in vet.points.values() if p.role == 'gcp']
    ph = _placeholders(file_heights, names)
    for p in vet.points.values():
        p.placeholder = ph.get(p.name, '')
    bad = [p for p in gcps if p.vertical == 'contradicted']
    good = [p for p in gcps if p.vertical == 'agrees']
    if not bad:
        return
    dv = np.array([p.d_v_m for p in bad])
    sv = float(np.median([p.sigma_v_m for p in bad]))
    consistent = len(bad) >= 2 and float(np.ptp(dv)) <= opt.height_sigmas * sv
    if good or any(p.placeholder for p in bad) or (len(bad) >= 2 and not consistent):
        vet.height_suspect = 'control_heights'
    elif consistent:
        vet.height_suspect = 'photo_altitudes'
    else:
        vet.height_suspect = 'either'
    for p in bad:
        why = _height_text(p) + (f'; {p.placeholder}: a placeholder?' if p.placeholder else '')
        if opt.contradicted_heights == 'horizontal':
            p.use = 'horizontal'
            p.reason = why + '; used horizontally only'
        else:
            p.reason = why + '; used as given (--gcp-height-check use): the block is bent to fit it'


def _height_text(p: PointCheck) -> str:
    return (f'its surveyed height is {abs(p.d_v_m):.2f} m {"below" if p.d_v_m > 0 else "above"} where the GNSS-only '
            f'block intersects it (sigma {p.sigma_v_m:.2f} m)')


def _notes(vet: ControlVetting) -> None:
    n = vet.counts()
    L = vet.notes
    missing = sorted({f.row.image for f in vet.rows if f.fate == 'photo_not_in_set'})
    if missing:
        L.append(f'{n["photo_not_in_set"]} control rows name {len(missing)} photos that are not in the set '
                 f'({", ".join(missing[:6])}{", ..." if len(missing) > 6 else ""}): another flight\'s?')
    if n['photo_not_oriented']:
        L.append(f'{n["photo_not_oriented"]} control rows are in photos that could not be oriented')
    if n['pixel_outside_image']:
        L.append(f'{n["pixel_outside_image"]} control rows give a pixel outside the image')
    if n['duplicate']:
        L.append(f'{n["duplicate"]} control rows repeat a point in the same photo (the first is used)')
    for img, why in vet.wrong_photos.items():
        L.append(f'{img}: {why}')
    lone = [f for f in vet.rows if f.fate == 'outlier' and f.row.image not in vet.wrong_photos]
    for f in lone:
        where = f' (line {f.row.line})' if f.row.line else ''
        L.append(f'{f.row.name} in {f.row.image}{where} rejected: {f.reason}')
    for p in vet.points.values():
        if p.use == 'unused' and p.role == 'gcp':
            L.append(f'GCP {p.name} not used: {p.reason}')
        elif p.role == 'check' and p.use == 'unused':
            L.append(f'check point {p.name} not measured: {p.reason}')
        elif p.vertical == 'contradicted' and p.role == 'gcp':
            L.append(f'GCP {p.name}: {p.reason}')
        elif p.vertical == 'contradicted':
            L.append(f'check point {p.name}: {_height_text(p)}' + (f'; {p.placeholder}: a placeholder?'
                                                                    if p.placeholder else ''))
    if vet.height_suspect == 'control_heights':
        L.append('the suspect is the control file\'s heights, not the photos\' altitudes: the GNSS-only block '
                 'contradicts them by more than the survey and the GNSS allow')
    elif vet.height_suspect == 'photo_altitudes':
        off = np.median([p.d_v_m for p in vet.points.values() if p.vertical == 'contradicted' and p.role == 'gcp'])
        L.append(f'every GCP\'s surveyed height disagrees with the photos\' altitudes by the same {-off:+.1f} m: the '
                 'photos\' altitudes are the likely suspect (EXIF relative to the take-off point, or MSL read as '
                 'ellipsoidal); the GCPs were used horizontally only')
    elif vet.height_suspect == 'either':
        L.append('one GCP\'s height contradicts the photos\' altitudes: either its height or the altitudes are wrong '
                 '(more GCPs would tell)')
