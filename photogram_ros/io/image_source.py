"""Frames from a folder of photos, a video file or a video device, with times and EXIF GPS.

A folder is played in shooting order (EXIF DateTimeOriginal + SubSecTimeOriginal, in the zone of
OffsetTimeOriginal, else an assumed UTC offset) so that a user's existing survey photos can go
through the mapper like a live camera. EXIF GPS altitude is above mean sea level (EXIF 2.3), so
`GnssFix.at` converts it to the WGS84 ellipsoidal height the rest of the system uses (REP-145). Many drones
write it above the take-off point instead (or a barometric altitude tens of metres off):
`exif_altitude_to_ellipsoidal_m` converts either reading, `exif_altitudes_look_relative` spots them.
`read_exif_camera` gathers what the EXIF and a DJI XMP say about the camera (focal length, sensor,
calibrated focal) for core/exif_intrinsics.py, and `read_dji_xmp` the XMP's drone-dji fields
(gimbal and flight angles, altitudes). A file that is empty, not an image or a truncated JPEG is
skipped, named, and recorded in `skipped` (`image_file_problem`): one bad file must not end a survey,
nor change how the others are timed. `read_fix_log` reads the GNSS log that goes with a video (a
CSV as `photogram-ros fixes --format csv` writes it from a .tlog, a dataflash log or a bag). No ROS
here: the camera node is a thin adapter over these iterators.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Iterator

import numpy as np

from photogram_ros.core import gnss_fix as gf
from photogram_ros.core.gnss_fix import (EXIF_ALTITUDE_REFERENCES, EXIF_ALTITUDE_SPELLINGS,  # noqa: F401 (read here)
                                         exif_altitude_to_ellipsoidal_m)
from photogram_ros.errors import ConfigError, DataError
from photogram_ros.io.geo_txt import geo_txt_fixes

IMAGE_SUFFIXES = ('.jpg', '.jpeg', '.png', '.tif', '.tiff')
GPS_IFD = 0x8825
EXIF_IFD = 0x8769
TAG_DATETIME_ORIGINAL = 0x9003
TAG_SUBSEC_ORIGINAL = 0x9291
TAG_OFFSET_ORIGINAL = 0x9011
TAG_MAKE, TAG_MODEL = 0x010F, 0x0110
TAG_FOCAL_LENGTH = 0x920A
TAG_FOCAL_35MM = 0xA405
TAG_FOCAL_PLANE_XRES = 0xA20E
TAG_FOCAL_PLANE_UNIT = 0xA210
# FocalPlaneResolutionUnit -> mm per unit (EXIF: 2 inch, 3 cm; 4 mm and 5 um as some cameras write).
FOCAL_PLANE_UNIT_MM = {1: 25.4, 2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
XMP_SEARCH_BYTES = 1 << 19          # the XMP packet of a camera JPEG sits in its first APP segments


# Sigmas of a DJI RTK-fixed photo whose XMP states no RtkStd* (per-axis horizontal, vertical).
RTK_FIXED_DEFAULT_M = (0.02, 0.03)


def dji_rtk_accuracy(path, xmp: dict | None = None) -> tuple[int, float, float] | None:
    """A DJI RTK photo's own solution quality from its XMP (`xmp`: read_dji_xmp of the photo when already read):
    (RtkFlag, per-axis horizontal and vertical 1-sigma in metres), or None when the XMP has no RtkFlag (not an
    RTK drone) or flag 0 (no solution). The one reading of `triangulate` (io/photo_block) and camera_node
    (read_exif_gps).

    The sigmas are RtkStdLon, RtkStdLat (horizontal: sqrt((lon^2 + lat^2) / 2)) and RtkStdHgt, each at
    least the floor of the flag's quality class (core/exposure_positions.DJI_RTK_FLAG_Q ->
    core.exposure_positions.Q_FLOOR_M: a float or single solution's formal sigma is optimistic); a flag
    without sigmas takes its class's floor, and a fixed one without sigmas 2 cm / 3 cm."""
    from photogram_ros.core.exposure_positions import Q_FLOOR_M
    from photogram_ros.core.exposure_positions import DJI_RTK_FLAG_Q
    xmp = read_dji_xmp(path) if xmp is None else xmp
    flag = xmp_float(xmp, 'RtkFlag')
    if flag is None or int(flag) == 0:
        return None
    flag = int(flag)
    floor_h, floor_v = Q_FLOOR_M.get(DJI_RTK_FLAG_Q.get(flag, 5), Q_FLOOR_M[5])
    lon_m, lat_m, hgt_m = (xmp_float(xmp, k) for k in ('RtkStdLon', 'RtkStdLat', 'RtkStdHgt'))
    if lon_m is None or lat_m is None or hgt_m is None:
        return flag, max(floor_h, RTK_FIXED_DEFAULT_M[0]), max(floor_v, RTK_FIXED_DEFAULT_M[1])
    return flag, max((0.5 * (lon_m ** 2 + lat_m ** 2)) ** 0.5, floor_h, 1e-3), max(hgt_m, floor_v, 1e-3)


@dataclass
class Frame:
    stamp_ns: int
    image: np.ndarray     # BGR uint8 (H, W, 3)
    gps: gf.GnssFix | None   # a photo's geo.txt position, else its EXIF GPS, or a map folder's stored fix
    path: str             # file path, or the video source and frame index


def _exif(path):
    """A photo's EXIF; the image is not decoded, so a panorama's size is no decompression bomb here."""
    import warnings

    from PIL import Image
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', Image.DecompressionBombWarning)
        with Image.open(path) as im:
            return im.getexif()


def read_exif_gps(path) -> gf.GnssFix | None:
    """EXIF GPS of a photo as a fix (core.gnss_fix.GnssFix); None when absent or unreadable.

    Its height is GPSAltitude signed by GPSAltitudeRef (without it, a DJI XMP's drone-dji:AbsoluteAltitude) as
    written, datum 'exif': above mean sea level as EXIF 2.3 says, but many drones write it above the take-off
    point; `GnssFix.at` reads it as the user says (exif_altitude_to_ellipsoidal_m), in camera_node as in
    triangulate. It has no time of its own (stamp 0). A DJI RTK photo (`dji_rtk_accuracy`) has its XMP sigmas
    (covariance known) and its RtkFlag on the quality scale (native: the flag); any other its covariance unknown
    (the EXIF sigmas of the caller apply) and the quality of a single solution."""
    try:
        gps = _exif(path).get_ifd(GPS_IFD)
    except (OSError, SyntaxError, ValueError):
        return None
    if 2 not in gps or 4 not in gps:
        return None

    def dms(v):
        # Rationals arrive as IFDRational; a zero denominator (seen in some cameras) is NaN.
        return float(v[0]) + float(v[1]) / 60 + float(v[2]) / 3600

    try:
        lat = dms(gps[2]) * (-1 if gps.get(1) == 'S' else 1)
        lon = dms(gps[4]) * (-1 if gps.get(3) == 'W' else 1)
        ref = gps.get(5, 0)
        below = ref in (1, b'\x01')
        alt = float(gps[6]) * (-1 if below else 1) if 6 in gps else None
    except (TypeError, ValueError, IndexError, ZeroDivisionError):
        return None
    xmp = read_dji_xmp(path)
    if alt is None:
        # No GPSAltitude: a DJI photo's XMP drone-dji:AbsoluteAltitude, the same altitude above mean sea level
        # (DJI writes both alike); else 0 m, as before the EXIF had altitudes (the photo's height then unknown).
        alt = xmp_float(xmp, 'AbsoluteAltitude')
        alt = 0.0 if alt is None else alt
    if not (np.isfinite(lat) and np.isfinite(lon) and np.isfinite(alt)):
        return None
    rtk = dji_rtk_accuracy(path, xmp)
    if rtk is None:
        return gf.GnssFix(lat, lon, alt, np.zeros((3, 3)), cov_type=gf.COV_UNKNOWN, quality=gf.Q_SINGLE,
                          height_datum='exif', source='EXIF')
    from photogram_ros.core.exposure_positions import DJI_RTK_FLAG_Q
    flag, sh, sv = rtk
    return gf.GnssFix(lat, lon, alt, np.diag([sh * sh, sh * sh, sv * sv]), cov_type=gf.COV_DIAGONAL_KNOWN,
                      quality=DJI_RTK_FLAG_Q.get(flag, gf.Q_SINGLE), height_datum='exif', source='EXIF + DJI RTK XMP',
                      quality_native=flag, native_scale='DJI RtkFlag')




def exif_altitude_reading(reference: str = 'msl', takeoff_h_m: float | None = None,
                          takeoff_reference: str = 'msl') -> tuple[str, float | None, str]:
    """How to read EXIF altitudes, checked, as (reference, takeoff_h_m, takeoff_reference) for
    exif_altitude_to_ellipsoidal_m and GnssFix.at: the one rule of `triangulate --exif-altitude` and
    camera_node's exif_altitude. 'orthometric' is taken for 'msl'; a take-off height that is None or NaN is none.
    Raises ConfigError for an unknown reading, 'relative' without a take-off height, or a take-off height
    without 'relative'."""
    ref = EXIF_ALTITUDE_SPELLINGS.get(reference, reference)
    takeoff_ref = EXIF_ALTITUDE_SPELLINGS.get(takeoff_reference, takeoff_reference)
    if ref not in EXIF_ALTITUDE_REFERENCES:
        raise ConfigError(f'EXIF altitude reading {reference!r} unknown; choose orthometric (above mean sea level, '
                          'the EXIF standard), ellipsoidal or relative')
    if takeoff_ref not in ('msl', 'ellipsoidal'):
        raise ConfigError(f"take-off height reference {takeoff_reference!r} unknown; choose orthometric or "
                          "ellipsoidal")
    takeoff = None if takeoff_h_m is None or not np.isfinite(takeoff_h_m) else float(takeoff_h_m)
    if ref == 'relative' and takeoff is None:
        raise ConfigError('EXIF altitudes relative to the take-off point need its height (triangulate '
                          '--takeoff-altitude-m H, camera_node takeoff_altitude_m; above mean sea level unless '
                          'the take-off heights are ellipsoidal)')
    if ref != 'relative' and takeoff is not None:
        raise ConfigError(f'a take-off height ({takeoff:g} m) is only used with EXIF altitudes relative to the '
                          'take-off point: say relative, or drop the take-off height')
    return ref, takeoff, takeoff_ref


# The rule of `exif_altitudes_look_relative`, in metres.
GROUND_NEAR_SEA_LEVEL_M = 15.0     # the take-off point is on the ground: relief of a block around it
MIN_FLYING_HEIGHT_M = 20.0         # survey photos are taken at least this far above the ground
GROUND_BELOW_SEA_LEVEL_M = -30.0   # hardly any survey site is lower (Dead Sea shores aside)


def exif_altitudes_look_relative(ground_msl_m: float, photo_alt_m: float) -> bool:
    """Whether EXIF altitudes taken as MSL look like heights above the take-off point instead.

    `ground_msl_m`: the block's ground (median tie-point height, MSL) after an adjustment held by
    those altitudes; `photo_alt_m`: the photos' median EXIF altitude as written. Relative altitudes
    put the ground within 15 m of 0 m MSL with the photos 20 m or more above it; a barometric
    altitude far off can sink the ground below -30 m MSL; photos below the ground (GCPs holding the
    block at its true height) cannot be MSL either. A survey really near sea level is flagged too:
    the caller says how to silence it.
    """
    flying_m = photo_alt_m - ground_msl_m
    return bool((abs(ground_msl_m) <= GROUND_NEAR_SEA_LEVEL_M and flying_m >= MIN_FLYING_HEIGHT_M)
                or ground_msl_m < GROUND_BELOW_SEA_LEVEL_M or flying_m < 0)


def _parse_offset(text) -> timedelta | None:
    s = str(text).strip().strip('\x00')
    if len(s) != 6 or s[0] not in '+-' or s[3] != ':':
        return None
    try:
        d = timedelta(hours=int(s[1:3]), minutes=int(s[4:6]))
    except ValueError:
        return None
    return -d if s[0] == '-' else d


def read_exif_time_ns(path, utc_offset_s: float = 0.0) -> tuple[int | None, bool, bool]:
    """(UTC shooting time in ns or None, whether the EXIF stated its zone, whether it had sub-seconds).

    DateTimeOriginal is local time with 1 s resolution; SubSecTimeOriginal adds the fraction and
    OffsetTimeOriginal the zone. Without a zone, `utc_offset_s` (camera clock minus UTC) is assumed.
    """
    try:
        ex = _exif(path).get_ifd(EXIF_IFD)
    except (OSError, SyntaxError, ValueError):
        return None, False, False
    text = ex.get(TAG_DATETIME_ORIGINAL)
    if not text:
        return None, False, False
    try:
        local = datetime.strptime(str(text).strip().strip('\x00'), '%Y:%m:%d %H:%M:%S')
    except ValueError:
        return None, False, False
    sub = str(ex.get(TAG_SUBSEC_ORIGINAL, '')).strip().strip('\x00')
    sub_ns = int(round(float('0.' + sub) * 1e9)) if sub.isdigit() else 0
    offset = _parse_offset(ex.get(TAG_OFFSET_ORIGINAL, ''))
    zoned = offset is not None
    if offset is None:
        offset = timedelta(seconds=utc_offset_s)
    utc = local.replace(tzinfo=timezone.utc) - offset
    seconds = int(utc.timestamp())   # whole seconds: exact
    return seconds * 1_000_000_000 + sub_ns, zoned, sub.isdigit()


def _text(v) -> str:
    return str(v).replace('\x00', '').strip() if v is not None else ''


def _positive(v) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return f if np.isfinite(f) and f > 0 else None


def read_dji_xmp(path) -> dict[str, str]:
    """The drone-dji fields of a photo's XMP packet (GimbalYawDegree, RelativeAltitude, CalibratedFocalLength,
    ...) as written; {} without one."""
    import re
    try:
        with open(path, 'rb') as fh:
            head = fh.read(XMP_SEARCH_BYTES)
    except OSError:
        return {}
    i = head.find(b'<x:xmpmeta')
    if i < 0:
        return {}
    j = head.find(b'</x:xmpmeta>', i)
    packet = head[i:j if j > 0 else len(head)].decode('utf-8', errors='replace')
    out = dict(re.findall(r'drone-dji:(\w+)="([^"]*)"', packet))
    out.update(re.findall(r'<drone-dji:(\w+)>([^<]*)</drone-dji:\1>', packet))
    return out


def xmp_float(xmp: dict, key: str) -> float | None:
    try:
        v = float(xmp[key])
    except (KeyError, TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def read_exif_camera(path):
    """What a photo's EXIF and DJI XMP say about its camera (core.exif_intrinsics.ExifCameraTags), with
    the size of the image as stored; None when the file cannot be opened as an image."""
    from PIL import Image

    from photogram_ros.core.exif_intrinsics import ExifCameraTags
    try:
        with Image.open(path) as im:
            size = im.size
            exif = im.getexif()
            ex = exif.get_ifd(EXIF_IFD)
    except (OSError, SyntaxError, ValueError):
        return None
    unit_mm = FOCAL_PLANE_UNIT_MM.get(int(ex.get(TAG_FOCAL_PLANE_UNIT, 2) or 2))
    xres = _positive(ex.get(TAG_FOCAL_PLANE_XRES))
    xmp = read_dji_xmp(path)
    return ExifCameraTags(
        width_px=int(size[0]), height_px=int(size[1]), make=_text(exif.get(TAG_MAKE)),
        model=_text(exif.get(TAG_MODEL)), focal_mm=_positive(ex.get(TAG_FOCAL_LENGTH)),
        focal_35mm=_positive(ex.get(TAG_FOCAL_35MM)),
        focal_plane_px_per_mm=xres / unit_mm if xres and unit_mm else None,
        xmp_focal_px=_positive(xmp.get('CalibratedFocalLength')),
        xmp_cx_px=_positive(xmp.get('CalibratedOpticalCenterX')),
        xmp_cy_px=_positive(xmp.get('CalibratedOpticalCenterY')))


def exif_intrinsics(path):
    """core.exif_intrinsics.ExifIntrinsics of one photo; CalibrationError (naming the file) without a
    usable focal length, DataError when it is not an image."""
    from photogram_ros.core.exif_intrinsics import intrinsics_from_exif
    from photogram_ros.errors import CalibrationError
    tags = read_exif_camera(path)
    if tags is None:
        raise DataError(f'{Path(path).name} cannot be read as an image')
    try:
        return intrinsics_from_exif(tags)
    except CalibrationError as exc:
        raise CalibrationError(f'{Path(path).name}: {exc}') from exc


def image_file_problem(path) -> str | None:
    """Why a file in a photo folder cannot be used ('empty file (0 bytes)', 'not an image: ...',
    'truncated or corrupt: ...'), or None when it decodes. Reads only the header, unless a JPEG lacks
    its end-of-image marker (a truncated copy): then it is decoded in full, as OpenCV would pad it grey."""
    from PIL import Image
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        return f'cannot be read: {exc}'
    if size == 0:
        return 'empty file (0 bytes)'
    import warnings
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', Image.DecompressionBombWarning)
            with Image.open(path) as im:
                fmt = im.format
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        return f'not an image: {exc}'
    if fmt == 'JPEG':
        with open(path, 'rb') as fh:
            fh.seek(max(0, size - 4096))
            tail = fh.read().rstrip(b'\x00\xff')
        if not tail.endswith(b'\xff\xd9'):
            try:
                with Image.open(path) as im:
                    im.load()
            except (OSError, SyntaxError, ValueError) as exc:
                return f'truncated or corrupt JPEG: {exc}'
    return None


def camera_of(path) -> tuple[int, int, str]:
    """(width, height, 'Make Model' from the EXIF) of a photo, read from its header; a panorama of any size
    is read without Pillow's decompression-bomb warning (it is only measured here)."""
    import warnings

    from PIL import Image
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', Image.DecompressionBombWarning)
        with Image.open(path) as im:
            size = im.size
            try:
                exif = im.getexif()
                model = ' '.join(t for t in (_text(exif.get(TAG_MAKE)), _text(exif.get(TAG_MODEL))) if t)
            except (OSError, SyntaxError, ValueError):
                model = ''
    return int(size[0]), int(size[1]), model


def camera_words(key: tuple) -> str:
    """(3600, 2700, 'DJI FC6310') -> '3600x2700 DJI FC6310' ('camera unnamed in the EXIF' without a model)."""
    w, h, model = key
    return f'{w}x{h} ' + (model or '(camera unnamed in the EXIF)')


def majority_camera(cameras: dict) -> tuple | None:
    """The camera (width, height, model) most photos of `cameras` (path -> camera_of) were taken with; on a
    tie, the one of the first photo among the tied. None for no photo."""
    counts: dict = {}
    for key in cameras.values():
        counts[key] = counts.get(key, 0) + 1
    return max(counts, key=lambda k: counts[k]) if counts else None


def file_digest(path: Path) -> bytes:
    """A hash of the file's bytes (duplicate copies of a photo)."""
    import hashlib
    h = hashlib.blake2b(digest_size=16)
    with open(path, 'rb') as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b''):
            h.update(chunk)
    return h.digest()


def _decode(path: Path) -> np.ndarray:
    """Decode fully with Pillow: it refuses truncated JPEGs, where OpenCV returns a grey-padded image."""
    from PIL import Image
    try:
        with Image.open(path) as im:
            im.load()
            rgb = np.asarray(im.convert('RGB'))
    except (OSError, SyntaxError, ValueError) as exc:
        raise DataError(f'{path.name} cannot be decoded: {exc}') from exc
    return np.ascontiguousarray(rgb[:, :, ::-1])


def _image_or_skip(path: Path, undecoded, skipped: list):
    """What `undecoded(path)` gives (a JPEG's bytes), else the decoded image; None when it cannot be decoded,
    recorded in `skipped`."""
    image = undecoded(path) if undecoded is not None else None
    if image is not None:
        return image
    try:
        return _decode(path)
    except DataError as exc:
        skipped.append((str(path), str(exc)))
        return None


PENDING_MAX_S = 30.0   # FolderSource.refresh: a new file that does not become a whole image in this long is skipped


class FolderSource:
    """The photos of a folder in shooting order; iterate for `Frame`s.

    One camera per block: the photos of the camera most of the folder was taken with (image size and
    EXIF make and model, `camera`) are played; the others (a panorama, a thumbnail, another camera's
    photo) are named in `skipped` and `other_camera` and left out, so a stray image never sinks the
    flight. Photos without EXIF DateTimeOriginal (a PNG among JPEGs) are skipped and named while at
    least half of the folder has its time: the others keep their real timing. When most have none, the
    folder plays in file-name order, `fallback_period_s` apart."""

    def __init__(self, folder, utc_offset_s: float = 0.0, fallback_period_s: float = 1.0):
        self.folder = Path(folder)
        self.utc_offset_s = utc_offset_s
        self.next_index = 0
        self._pending: dict = {}   # refresh(): path -> (its size at the last look, first seen), while it may grow
        self.activity_at = 0.0     # refresh(): when a new file was last seen (time.monotonic)
        if not self.folder.is_dir():
            raise ConfigError(f'{folder} is not a folder of images')
        files = sorted(p for p in self.folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise DataError(f'{folder} holds no {"/".join(s[1:].upper() for s in IMAGE_SUFFIXES)} images')
        self.notes: list[str] = []
        self.skipped: list[tuple[str, str]] = []   # (path, why)
        self.other_camera: list[tuple[str, str]] = []   # (path, why): photos of another camera, left out
        usable, cameras = [], {}
        for p in files:
            why = image_file_problem(p)
            if why is not None:
                # Not usable at all: skipped here, so it does not change how the others are timed.
                self.skipped.append((str(p), f'{p.name}: {why}'))
                continue
            usable.append(p)
            cameras[p] = camera_of(p)
        if not usable:
            raise DataError(f'{folder}: none of its {len(files)} image files can be read '
                            f'({"; ".join(w for _, w in self.skipped[:3])})')
        timed = [(p, *read_exif_time_ns(p, utc_offset_s)) for p in usable]
        files = [e[0] for e in timed]
        missing = [p for p, t, _, _ in timed if t is None]
        by_time = 2 * len(missing) <= len(timed)
        if by_time:
            for p in missing:
                self.skipped.append((str(p), f'{p.name} has no EXIF DateTimeOriginal while {len(timed) - len(missing)} '
                                             'photos of the folder have one: skipped (its time is unknown)'))
            timed = [e for e in timed if e[1] is not None]
        timed = self._drop_duplicates(timed)
        # One camera per block, among the photos that can be placed in time.
        self.camera = majority_camera({e[0]: cameras[e[0]] for e in timed})
        odd = [e[0] for e in timed if cameras[e[0]] != self.camera]
        for p in odd:
            why = (f'{p.name}: {camera_words(cameras[p])}, another camera than the block\'s '
                   f'{camera_words(self.camera)} ({len(timed) - len(odd)} photos): left out')
            self.skipped.append((str(p), why))
            self.other_camera.append((str(p), why))
        if odd:
            self.notes.append(f'one camera per block: {camera_words(self.camera)} ({len(timed) - len(odd)} of '
                              f'{len(timed)} photos); left out {len(odd)} of another camera or size: '
                              + ', '.join(p.name for p in odd[:10]) + (', ...' if len(odd) > 10 else ''))
        timed = [e for e in timed if cameras[e[0]] == self.camera]
        if by_time:
            # Name as tie-breaker: burst photos can share a second when SubSec is absent.
            timed.sort(key=lambda e: (e[1], e[0].name))
            self.entries = [(p, t) for p, t, _, _ in timed]
            unzoned = sum(1 for _, _, z, _ in timed if not z)
            if unzoned:
                self.notes.append(f'{unzoned} of {len(timed)} photos have no OffsetTimeOriginal: camera clock '
                                  f'taken as UTC{utc_offset_s / 3600:+g} h')
            coarse = sum(1 for _, _, _, sub in timed if not sub)
            if coarse:
                self.notes.append(f'{coarse} of {len(timed)} photos have no SubSecTimeOriginal: their stamps '
                                  'have 1 s resolution')
        else:
            # Most photos untimed: interleaving the few timed ones would be arbitrary; name order is safer.
            self.notes.append(f'{len(missing)} of {len(files)} images have no EXIF DateTimeOriginal: '
                              f'played in file-name order, {fallback_period_s:g} s apart from the first '
                              'file time')
            t0 = next((t for _, t, _, _ in timed if t is not None), None)
            if t0 is None:
                t0 = int(min(p.stat().st_mtime_ns for p in files))
            step = int(round(fallback_period_s * 1e9))
            self.entries = [(e[0], t0 + i * step) for i, e in enumerate(timed)]

        # Positions from a geo.txt beside the photos (a PPK geotag) replace their EXIF GPS.
        self.geo: dict = {}
        if (self.folder / 'geo.txt').exists():
            self.geo = geo_txt_fixes(self.folder / 'geo.txt')
            self.notes.append(f'positions of {sum(p.name in self.geo for p, _ in self.entries)} of '
                              f'{len(self.entries)} photos from geo.txt (ellipsoidal heights, its accuracies as '
                              'sigmas), the others from their EXIF GPS')

    def __len__(self) -> int:
        return len(self.entries)

    def _drop_duplicates(self, timed: list) -> list:
        """`timed` ((path, time, ...) rows) without the byte-identical copies of a photo (the same file
        downloaded twice): each named in `skipped` with the photo it copies; the first by name is kept.
        Only photos of one size and time are compared byte for byte."""
        groups: dict = {}
        for e in sorted(timed, key=lambda e: e[0].name):
            groups.setdefault((e[0].stat().st_size, e[1]), []).append(e)
        dropped = set()
        for same in groups.values():
            seen: dict = {}
            for e in same if len(same) > 1 else ():
                digest = file_digest(e[0])
                if digest in seen:
                    dropped.add(e[0])
                    self.skipped.append((str(e[0]), f'{e[0].name}: identical to {seen[digest].name} (a duplicate '
                                                     'copy): skipped'))
                else:
                    seen[digest] = e[0]
        return [e for e in timed if e[0] not in dropped]

    def exif_intrinsics(self):
        """core.exif_intrinsics.ExifIntrinsics from the first photo's EXIF (CalibrationError without a focal
        length); for a folder without a calibration file."""
        from photogram_ros.errors import CalibrationError
        if not self.entries:
            raise CalibrationError(f'{self.folder} holds no usable photo')
        return exif_intrinsics(self.entries[0][0])

    def __iter__(self) -> Iterator[Frame]:
        return self.frames()

    def frames(self, undecoded=None, start: int = 0) -> Iterator[Frame]:
        """The photos as `Frame`s in shooting order from entry `start`, each decoded (BGR); `undecoded(path)` may
        give what to pass instead of the decoded image (a JPEG's bytes), or None to decode it. A photo that cannot
        be decoded is skipped and recorded in `skipped`. `next_index`: the entry the next frame comes from."""
        self.next_index = start
        while self.next_index < len(self.entries):   # entries refresh() appends are played too
            path, stamp_ns = self.entries[self.next_index]
            self.next_index += 1
            image = _image_or_skip(path, undecoded, self.skipped)
            if image is not None:
                yield Frame(stamp_ns, image, self.geo.get(path.name) or read_exif_gps(path), str(path))

    def refresh(self) -> int:
        """Photos that appeared in the folder since it was listed (a companion computer downloading from the
        camera during the flight), appended to `entries` in shooting order; returns how many. A file is taken
        once whole: its size the same at two refreshes and it decodes as an image (a JPEG still being copied
        lacks its end); while one is still being copied none is taken (it may be older than the others), unless
        it stays broken for PENDING_MAX_S (then it is named in `skipped`). A new photo of another camera, without an EXIF time, or taken before the last photo
        listed (time never goes back) is named in `skipped` and left out."""
        known = {p for p, _ in self.entries} | {Path(p) for p, _ in self.skipped}
        now = time.monotonic()
        ready, growing = [], []
        for p in sorted(self.folder.iterdir()):
            if p.suffix.lower() not in IMAGE_SUFFIXES or p in known:
                continue
            try:
                size = p.stat().st_size
            except OSError:
                continue
            seen = self._pending.get(p)
            if seen is None or seen[0] != size:
                self._pending[p] = (size, now if seen is None else seen[1])   # looked at again next time
                growing.append(p)
                continue
            why = 'empty file (0 bytes)' if size == 0 else image_file_problem(p)
            if why is None:
                ready.append(p)
            elif now - seen[1] > PENDING_MAX_S:   # never became whole
                del self._pending[p]
                self.skipped.append((str(p), f'{p.name}: {why} after {PENDING_MAX_S:g} s'))
            else:
                growing.append(p)
        if growing or ready:
            self.activity_at = now
        # A photo still being copied may be older than the whole ones: those taken after it wait for it (its
        # EXIF, at the file's start, usually reads already; when it does not, all wait).
        first_growing = None
        for p in growing:
            t = read_exif_time_ns(p, self.utc_offset_s)[0]
            if t is None:
                return 0
            first_growing = t if first_growing is None else min(first_growing, t)
        new = []
        for p in ready:
            t = read_exif_time_ns(p, self.utc_offset_s)[0]
            if first_growing is not None and (t is None or t >= first_growing):
                continue
            del self._pending[p]
            camera = camera_of(p)
            last_ns = self.entries[-1][1] if self.entries else None
            why = None
            if self.camera is not None and camera != self.camera:
                why = (f'{p.name}: {camera_words(camera)}, another camera than the block\'s '
                       f'{camera_words(self.camera)}: left out')
                self.other_camera.append((str(p), why))
            elif t is None:
                why = f'{p.name} has no EXIF DateTimeOriginal: skipped (its time is unknown)'
            elif (twin := next((q for q, tq in self.entries if tq == t and q.stat().st_size == p.stat().st_size
                                and file_digest(q) == file_digest(p)), None)) is not None:
                why = f'{p.name}: identical to {twin.name} (a duplicate copy): skipped'
            elif last_ns is not None and t <= last_ns:
                why = f'{p.name} was taken before the last photo played (time never goes back): skipped'
            if why is not None:
                self.skipped.append((str(p), why))
                continue
            new.append((p, t))
        new.sort(key=lambda e: (e[1], e[0].name))
        self.entries.extend(new)
        return len(new)


class VideoSource:
    """Frames of a video file (stamps from the file's timing) or a device (stamps from the wall clock)."""

    def __init__(self, source, start_ns: int | None = None):
        import cv2
        self.source = source
        self.is_device = isinstance(source, int) or str(source).startswith('/dev/')
        self.notes: list[str] = []
        self.skipped: list[tuple[str, str]] = []
        self.cap = cv2.VideoCapture(source)
        if not self.cap.isOpened():
            raise ConfigError(f'cannot open the video {"device" if self.is_device else "file"} {source!r}')
        # File times are relative to its start: anchor them at a given time or at opening.
        self.start_ns = time.time_ns() if start_ns is None else int(start_ns)
        fps = self.cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and np.isfinite(fps) and fps > 0 else 0.0

    def __iter__(self) -> Iterator[Frame]:
        import cv2
        k = 0
        misses = 0
        try:
            while True:
                ok, img = self.cap.read()
                if not ok or img is None:
                    if self.is_device and misses < 10:
                        # Devices drop a frame now and then; give up after several in a row.
                        misses += 1
                        self.skipped.append((f'{self.source}#{k}', 'device returned no frame'))
                        continue
                    return
                misses = 0
                if self.is_device:
                    stamp_ns = time.time_ns()
                else:
                    pos_ms = self.cap.get(cv2.CAP_PROP_POS_MSEC)
                    if not np.isfinite(pos_ms) or (pos_ms <= 0 and k > 0):
                        pos_ms = k * 1000.0 / self.fps if self.fps else 0.0
                    stamp_ns = self.start_ns + int(round(pos_ms * 1e6))
                if img.ndim == 2:
                    img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
                yield Frame(stamp_ns, img, None, f'{self.source}#{k}')
                k += 1
        finally:
            self.cap.release()


class StoredKeyframes:
    """The keyframes a map folder holds without a pose (taken before a crash cut the flight short, never oriented
    by the adjuster), as frames to feed again: each keyframe's saved image (the camera's full resolution) with its
    stamp and the fix the map kept for it (io/flight_inputs.keyframe_fixes; None when it kept none). A resumed
    `run` plays them before its camera's frames (camera_node `resume_keyframes_of`) so that this run's tracker and
    adjuster orient them like any keyframe. An image that cannot be decoded is named in `skipped`."""

    def __init__(self, map_dir):
        from photogram_ros.io.flight_inputs import keyframe_fixes
        from photogram_ros.io.map_store import MapStore
        self.map_dir = Path(map_dir)
        self.images = MapStore(self.map_dir).unposed_keyframe_images()   # in stamp order
        self.fixes = keyframe_fixes(self.map_dir)
        self.skipped: list[tuple[str, str]] = []
        n_fix = sum(1 for p in self.images if int(p.stem) in self.fixes)
        self.notes = [f'{len(self.images)} keyframes of {self.map_dir} saved before the restart without a pose '
                      f'({n_fix} with their fix) are played first, for this run to orient them'] if self.images else []

    def stamps_ns(self) -> list[int]:
        return [int(p.stem) for p in self.images]

    def frames(self, undecoded=None, before_ns: int | None = None) -> Iterator[Frame]:
        """The stored keyframes stamped before `before_ns` (None: all) as `Frame`s in stamp order, decoded (BGR)
        unless `undecoded(path)` gives what to pass instead (FolderSource.frames' convention)."""
        for path in self.images:
            stamp_ns = int(path.stem)
            if before_ns is not None and stamp_ns >= before_ns:
                return
            image = _image_or_skip(path, undecoded, self.skipped)
            if image is None:
                continue
            fix = self.fixes.get(stamp_ns)
            gps = None if fix is None or fix.get('status', 0) < 0 else stored_fix(fix)
            yield Frame(stamp_ns, image, gps, str(path))


def stored_fix(fix: dict) -> gf.GnssFix:
    """A keyframe's fix as the map folder kept it (io/flight_inputs.keyframe_fixes: WGS84, ellipsoidal height,
    NavSatStatus status, its 1-sigmas sigma_h_m / sigma_v_m when stored, else its covariance unknown: `GnssFix.at`
    gives it the sigmas of the caller)."""
    sh, sv = fix.get('sigma_h_m'), fix.get('sigma_v_m')
    known = sh is not None and sv is not None
    cov = np.diag([sh * sh, sh * sh, sv * sv]) if known else np.zeros((3, 3))
    return gf.GnssFix(fix['lat_deg'], fix['lon_deg'], fix['h_m'], cov, 0, int(fix.get('status', gf.STATUS_FIX)),
                      gf.COV_DIAGONAL_KNOWN if known else gf.COV_UNKNOWN, source='map folder')


def open_source(source: str, utc_offset_s: float = 0.0, fallback_period_s: float = 1.0,
                video_start_ns: int | None = None):
    """`source`: a folder of images, a video file, a device path (/dev/video0) or a device index ('0');
    `video_start_ns`: the time of a video file's first frame (default: when it is opened)."""
    s = str(source).strip()
    if not s:
        raise ConfigError('set the parameter "source" to a folder of images, a video file, or a camera device '
                          '(/dev/video0 or an index such as 0)')
    if s.isdigit():
        return VideoSource(int(s))
    p = Path(s).expanduser()
    if p.is_dir():
        return FolderSource(p, utc_offset_s, fallback_period_s)
    if s.startswith('/dev/'):
        return VideoSource(s)
    if p.is_file():
        return VideoSource(str(p), video_start_ns)
    raise ConfigError(f'source {s!r} is neither a folder, a video file nor a camera device')


FIX_LOG_COLUMNS = ('t_unix_s', 'lat_deg', 'lon_deg', 'h_m')   # needed; var_e_m2 var_n_m2 var_u_m2 status optional


def read_fix_log(path, sigma_h_m: float = 5.0) -> list:
    """GNSS fixes (core.gnss_fix.GnssFix, in time order) from a CSV with a header naming at least
    t_unix_s, lat_deg, lon_deg, h_m (WGS84 ellipsoidal): the table `photogram-ros fixes --format csv`
    writes from a .tlog, a dataflash .bin or a bag's NavSatFix, or any GNSS log put in those columns.
    Rows without a position or with status -1 (no fix) are left out; rows without variances get
    `sigma_h_m` (vertical twice it). A missing file or column is a DataError naming it."""
    import csv
    import math
    path = Path(path)
    try:
        with open(path, newline='') as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise DataError(f'GNSS log {path} cannot be read: {exc}') from exc
    if not rows or any(c not in rows[0] for c in FIX_LOG_COLUMNS):
        raise DataError(f'GNSS log {path}: a CSV with the columns {", ".join(FIX_LOG_COLUMNS)} is needed (as '
                        f'photogram-ros fixes --format csv writes); its header is {list(rows[0]) if rows else "empty"}')

    def num(row, key):
        try:
            v = float(row.get(key) or 'nan')
        except ValueError:
            return math.nan
        return v

    fixes = []
    for row in rows:
        t, lat, lon, h = (num(row, c) for c in FIX_LOG_COLUMNS)
        if not all(math.isfinite(v) for v in (t, lat, lon, h)) or num(row, 'status') == gf.STATUS_NO_FIX:
            continue
        var = [num(row, k) for k in ('var_e_m2', 'var_n_m2', 'var_u_m2')]
        known = all(math.isfinite(v) and v > 0 for v in var)
        if not known:
            var = [sigma_h_m ** 2, sigma_h_m ** 2, (2.0 * sigma_h_m) ** 2]
        status = num(row, 'status')
        fixes.append(gf.GnssFix(lat, lon, h, np.diag(var), int(round(t * 1e9)),
                                int(status) if math.isfinite(status) else gf.STATUS_FIX,
                                gf.COV_DIAGONAL_KNOWN if known else gf.COV_APPROXIMATED, source=f'fix log {path.name}'))
    if not fixes:
        raise DataError(f'GNSS log {path}: none of its {len(rows)} rows holds a fix')
    fixes.sort(key=lambda f: f.stamp_ns)
    return fixes
