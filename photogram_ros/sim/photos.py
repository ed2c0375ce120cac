"""Survey-camera deliverables: geotagged JPEGs, an OpenDroneMap geo.txt and gcp_list.txt.

Photos are taken at the front-overlap spacing a survey camera would use, from the same rendered
frames as the bag. EXIF GPS altitude is above mean sea level, as the EXIF standard says; geo.txt
carries the ellipsoidal height with per-image accuracy, as a PPK/RTK workflow would. The camera tags
are a real camera's: FocalLength (mm, for a 3 um pixel pitch), FocalPlaneX/YResolution with its unit,
FocalLengthIn35mmFilm (by the diagonal) and the image size, from which core/exif_intrinsics.py
recovers the focal length in pixels.
"""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from pathlib import Path

import cv2
import numpy as np
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from photogram_ros.core import geoid
from photogram_ros.core.geodesy import geodetic_to_crs
from photogram_ros.core.rotations import invert_T, transform_points

GPS_IFD = 0x8825
EXIF_IFD = 0x8769
PIXEL_PITCH_MM = 0.003          # the simulated sensor's pixel pitch
DIAGONAL_35MM_MM = 43.27


def _rational_dms(value_deg: float):
    v = abs(value_deg)
    d = int(v)
    m = int((v - d) * 60)
    s = (v - d - m / 60) * 3600
    # Pillow >= 10 wants IFDRational values, not (num, den) tuples.
    return (IFDRational(d, 1), IFDRational(m, 1), IFDRational(int(round(s * 10000)), 10000))


def exif_bytes(lat_deg: float, lon_deg: float, alt_msl_m: float, when: datetime, focal_mm: float,
               size_px: tuple[int, int] | None = None, pixel_pitch_mm: float = PIXEL_PITCH_MM) -> bytes:
    """EXIF of a simulated photo; with `size_px` (width, height) also the tags of its sensor geometry."""
    exif = Image.Exif()
    exif[0x010F] = 'photogram_ros'           # Make
    exif[0x0110] = 'simulator'                # Model
    exif[0x0132] = when.strftime('%Y:%m:%d %H:%M:%S')
    gps = exif.get_ifd(GPS_IFD)
    gps[0] = b'\x02\x03\x00\x00'
    gps[1] = 'N' if lat_deg >= 0 else 'S'
    gps[2] = _rational_dms(lat_deg)
    gps[3] = 'E' if lon_deg >= 0 else 'W'
    gps[4] = _rational_dms(lon_deg)
    gps[5] = 0 if alt_msl_m >= 0 else 1
    gps[6] = IFDRational(int(round(abs(alt_msl_m) * 1000)), 1000)
    ex = exif.get_ifd(EXIF_IFD)
    ex[0x9003] = when.strftime('%Y:%m:%d %H:%M:%S')   # DateTimeOriginal
    # EXIF times have 1 s resolution and no zone without these: milliseconds and UTC make the
    # photo times line up exactly with the bag's frames and GNSS fixes.
    ex[0x9291] = f'{when.microsecond // 1000:03d}'   # SubSecTimeOriginal
    z = when.strftime('%z')   # '' for a naive time: then the zone stays unstated
    if z:
        ex[0x9011] = z[:3] + ':' + z[3:]   # OffsetTimeOriginal
    ex[0x920A] = IFDRational(int(round(focal_mm * 1000)), 1000)  # FocalLength
    if size_px is not None:
        w, h = (int(v) for v in size_px)
        ex[0xA002], ex[0xA003] = w, h                               # ExifImageWidth / Height
        per_cm = IFDRational(int(round(10.0 / pixel_pitch_mm * 1000)), 1000)
        ex[0xA20E] = ex[0xA20F] = per_cm                            # FocalPlaneX/YResolution, pixels per cm
        ex[0xA210] = 3                                              # FocalPlaneResolutionUnit: cm
        diag_mm = pixel_pitch_mm * float(np.hypot(w, h))
        ex[0xA405] = int(round(focal_mm * DIAGONAL_35MM_MM / diag_mm))  # FocalLengthIn35mmFilm
    return exif.tobytes()


def write_photos(folder: Path, frames, truth, cfg) -> list[str]:
    """`frames`: [(index, image, FlightState)] of every rendered frame; writes the triggered ones."""
    folder.mkdir(parents=True, exist_ok=False)
    spacing_m = cfg.height_px * cfg.gsd_m * (1.0 - cfg.front_overlap)
    names, last = [], None
    geo_lines = ['EPSG:4326']
    fix_by_t = truth.fixes
    for k, img, st in frames:
        if last is not None and np.linalg.norm(st.pos_enu[:2] - last) < spacing_m:
            continue
        last = st.pos_enu[:2].copy()
        ft = truth.frames[k]
        # Photo position = GNSS antenna measurement nearest in time, as the camera geotags it.
        fix = min((f for f in fix_by_t if 'lat_deg' in f),
                  key=lambda f: abs(f['t_fix_unix_s'] - ft.stamp_ns * 1e-9), default=None)
        if fix is None:
            continue
        name = f'IMG_{k:04d}.JPG'
        # Integer arithmetic: a float timestamp could round 20:26:41.000 down to .999.
        when = (datetime.fromtimestamp(ft.stamp_ns // 1_000_000_000, tz=timezone.utc)
                + timedelta(microseconds=(ft.stamp_ns % 1_000_000_000) // 1000))
        rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        Image.fromarray(rgb).save(folder / name, quality=92,
                                  exif=exif_bytes(fix['lat_deg'], fix['lon_deg'], fix['alt_msl_m'], when,
                                                  cfg.focal_px * PIXEL_PITCH_MM, (img.shape[1], img.shape[0])))
        geo_lines.append(f"{name} {fix['lon_deg']:.9f} {fix['lat_deg']:.9f} {fix['h_m']:.3f} 0 0 0 "
                         f"{fix['h_acc_m']:.3f} {fix['v_acc_m']:.3f}")
        names.append((name, ft))
    (folder / 'geo.txt').write_text('\n'.join(geo_lines) + '\n')
    # gcp_list.txt: every target visible in every photo, in the UTM CRS, ellipsoidal heights.
    lines = [truth.crs]
    cam = truth.camera
    for t in truth.targets:
        lat, lon, h = truth.origin.enu_to_geodetic(t.center_enu)
        x, y, z = geodetic_to_crs(lat, lon, h, truth.crs)
        for name, ft in names:
            uv, ok = cam.project(transform_points(invert_T(ft.map_T_cam), t.center_enu[None]))
            if ok[0] and cam.in_image(uv, margin_px=20)[0]:
                lines.append(f'{float(x):.4f} {float(y):.4f} {float(z):.4f} {uv[0, 0]:.2f} {uv[0, 1]:.2f} '
                             f'{name} {t.name}')
    (folder / 'gcp_list.txt').write_text('\n'.join(lines) + '\n')
    (folder / 'README.txt').write_text(
        'Simulated survey photos. EXIF GPS altitude is MSL (geoid: ' + geoid.MODEL_NAME + '); geo.txt '
        'and gcp_list.txt heights are ellipsoidal (WGS84). Targets named CHK* are check points.\n')
    return [n for n, _ in names]
