"""A folder of geotagged photos as keyframe records (`photogram-ros triangulate FOLDER`).

Positions come from an OpenDroneMap geo.txt beside the photos (`read_geo_txt`; heights ellipsoidal,
its accuracies as sigmas), else from each photo's EXIF GPS (`exif_position`; what the EXIF altitude
is relative to as the user says, MSL by default, sigma 5 m horizontal and 10 m vertical). Features
are matched between each photo and its nearest neighbours by position (core/photo_matching.py) and
chained into tracks; a photo stored rotated by 90 degrees is turned back. The calibration is a YAML
file or, for simulator output, the truth beside the folder.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np

from photogram_ros.core import photo_matching as pm
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame, crs_to_geodetic
from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.core.incremental import KeyframeRecord
from photogram_ros.errors import CalibrationError, DataError
from photogram_ros.io.image_source import exif_altitude_to_ellipsoidal_m, read_exif_gps
from photogram_ros.io.keyframe_block import KeyframeBlock, camera_from_yaml

IMAGE_SUFFIXES = ('.jpg', '.jpeg', '.png', '.tif', '.tiff')
# Sigmas of an EXIF geotag (a consumer GNSS), and of a geo.txt line without accuracies.
EXIF_SIGMA_H_M = 5.0
EXIF_SIGMA_V_M = 10.0


def read_geo_txt(path: str | Path) -> dict[str, tuple[float, float, float, float, float]]:
    """OpenDroneMap geo.txt -> {image name: (lat_deg, lon_deg, h_m ellipsoidal, h_acc_m, v_acc_m)}.

    First line a CRS, then ``image x y z [omega phi kappa] [h_acc v_acc]`` (geographic: x = longitude).
    """
    path = Path(path)
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith('#')]
    if not lines:
        raise DataError(f'{path} is empty')
    crs = ' '.join(lines[0])
    out = {}
    for ln in lines[1:]:
        if len(ln) < 4:
            raise DataError(f'{path}: line {" ".join(ln)!r} needs: image x y z [omega phi kappa] [h_acc v_acc]')
        x, y, z = (float(v) for v in ln[1:4])
        if crs.upper() in ('EPSG:4326', 'WGS84', 'EPSG:4979'):
            lat, lon, h = y, x, z
        else:
            lat, lon, h = (float(v) for v in crs_to_geodetic(x, y, z, crs))
        h_acc = float(ln[7]) if len(ln) >= 9 else EXIF_SIGMA_H_M
        v_acc = float(ln[8]) if len(ln) >= 9 else EXIF_SIGMA_V_M
        out[ln[0]] = (lat, lon, h, max(h_acc, 1e-3), max(v_acc, 1e-3))
    return out


def exif_position(path: str | Path, altitude: str = 'msl', takeoff_h_m: float | None = None,
                  takeoff_heights: str = 'msl') -> tuple[float, float, float, float, float] | None:
    """A photo's EXIF GPS -> (lat_deg, lon_deg, h_m ellipsoidal, h_acc_m, v_acc_m), or None without one.

    `altitude`, `takeoff_h_m`, `takeoff_heights`: what the EXIF altitude is relative to
    (`image_source.exif_altitude_to_ellipsoidal_m`).
    """
    fix = read_exif_gps(path)
    if fix is None:
        return None
    h_m = float(exif_altitude_to_ellipsoidal_m(fix.lat_deg, fix.lon_deg, fix.alt_msl_m, altitude, takeoff_h_m,
                                               takeoff_heights))
    return fix.lat_deg, fix.lon_deg, h_m, EXIF_SIGMA_H_M, EXIF_SIGMA_V_M


def _positions(src: Path, images: list[Path], exif_altitude, takeoff_h_m, takeoff_heights, assumptions):
    """{image name: geo.txt/EXIF position}, and the EXIF positions to check as MSL (or None)."""
    if (src / 'geo.txt').exists():
        assumptions.append('positions from geo.txt (heights ellipsoidal, per-image accuracy used as sigma)')
        if exif_altitude:
            assumptions.append(f'--exif-altitude {exif_altitude} ignored: positions come from geo.txt')
        return read_geo_txt(src / 'geo.txt'), None
    geo = {}
    for p in images:
        g = exif_position(p, exif_altitude or 'msl', takeoff_h_m, takeoff_heights)
        if g:
            geo[p.name] = g
    if exif_altitude == 'relative':
        ref = 'MSL (EGM2008)' if takeoff_heights == 'msl' else 'ellipsoidal'
        how = (f'EXIF altitude taken as height above the take-off point at {takeoff_h_m:.2f} m {ref}'
               + (', converted to ellipsoidal through EGM2008 at each photo' if takeoff_heights == 'msl' else ''))
    elif exif_altitude == 'ellipsoidal':
        how = 'EXIF altitude taken as ellipsoidal (WGS84), as --exif-altitude ellipsoidal says'
    else:
        how = 'EXIF altitude taken as MSL (EGM2008) and converted to ellipsoidal'
    assumptions.append(f'positions from EXIF GPS; {how}; sigma 5 m horizontal, 10 m vertical')
    # Checked once the block has a ground: only then can an MSL reading be seen to be wrong.
    check = np.array([g[:3] for g in geo.values()]) if exif_altitude is None and geo else None
    return geo, check


def _camera(src: Path, camera_path, assumptions) -> PinholeCamera:
    if camera_path:
        assumptions.append(f'calibration from {camera_path}, held fixed')
        return camera_from_yaml(camera_path)
    if (src.parent / 'ground_truth.json').exists():
        assumptions.append('calibration from the simulator truth beside the photos, held fixed')
        return PinholeCamera.from_ros_yaml_dict(json.loads((src.parent / 'ground_truth.json').read_text())['camera'])
    raise CalibrationError('no calibration: pass --camera calib.yaml (make one with photogram-ros calibrate)')


def _features(images: list[Path], camera: PinholeCamera, assumptions) -> list:
    feats = []
    for p in images:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise DataError(f'{p} cannot be read as an image')
        if (img.shape[1], img.shape[0]) != (camera.width, camera.height):
            if (img.shape[0], img.shape[1]) == (camera.width, camera.height):
                img = cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)
                assumptions.append(f'{p.name} was stored rotated by 90 degrees: rotated back')
            else:
                camera.check_image_size(img.shape[1], img.shape[0])
        feats.append(pm.extract(p.name, img))
    return feats


def read_photo_block(src: str | Path, camera_path: str | Path | None = None, neighbours: int = 8,
                     exif_altitude: str | None = None, takeoff_h_m: float | None = None,
                     takeoff_heights: str = 'msl', log=None) -> KeyframeBlock:
    """The photos of the folder `src` as a KeyframeBlock, in file-name order.

    neighbours: photos matched with each photo (nearest by position); exif_altitude ('msl',
    'ellipsoidal', 'relative' with takeoff_h_m in takeoff_heights, or None: msl, checked after the
    adjustment); log(text): progress lines.
    """
    src = Path(src)
    if not src.is_dir():
        raise DataError(f'{src} is not a folder of photos')
    images = sorted(p for p in src.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(images) < 3:
        raise DataError(f'{src} holds {len(images)} images: at least 3 overlapping photos are needed')
    assumptions = []
    geo, exif_check = _positions(src, images, exif_altitude, takeoff_h_m, takeoff_heights, assumptions)
    first = next((geo[p.name] for p in images if p.name in geo), None)
    if first is None:
        raise DataError(f'no image in {src} has a position (EXIF GPS or geo.txt): georeferencing impossible')
    origin = LocalFrame(first[0], first[1], first[2])
    camera = _camera(src, camera_path, assumptions)
    t0 = time.monotonic()
    feats = _features(images, camera, assumptions)
    pos = np.array([origin.geodetic_to_enu(*geo[p.name][:3]) if p.name in geo else [np.nan] * 3 for p in images])
    pos = np.where(np.isfinite(pos), pos, np.nanmean(pos, axis=0))
    matches = {}
    for i, j in pm.neighbours(pos, neighbours):
        m = pm.match_pair(feats[i], feats[j], camera)
        if len(m):
            matches[(i, j)] = m
    tracks = pm.build_tracks([len(f.uv) for f in feats], matches)
    if log is not None:
        log(f'{len(images)} photos, {sum(len(f.uv) for f in feats)} features, {len(matches)} verified pairs, '
            f'in {time.monotonic() - t0:.1f} s')
    records = []
    for p, f, tr in zip(images, feats, tracks):
        keep = tr >= 0
        g = geo.get(p.name)
        fix = GnssFix(g[0], g[1], g[2], np.diag([g[3] ** 2, g[3] ** 2, g[4] ** 2])) if g else None
        records.append(KeyframeRecord(0, tr[keep], f.uv[keep], fix, p.name))
    return KeyframeBlock(camera, origin, records, assumptions, n_inputs=len(images), exif_geodetic=exif_check)
