"""A folder of geotagged photos as keyframe records (`photogram-ros triangulate FOLDER`).

Positions come from an OpenDroneMap geo.txt beside the photos (io/geo_txt.read_geo_txt; heights ellipsoidal,
its accuracies as sigmas), else from each photo's EXIF GPS (`exif_position`; what the EXIF altitude
is relative to as the user says, MSL by default, sigma 5 m horizontal and 2 m vertical, or a DJI RTK
photo's own sigmas and fix flag from its XMP: io/image_source.dji_rtk_accuracy, the reading camera_node
publishes too; the report's assumptions and `matching.rtk_flags` count the photos per flag).

The camera: a calibration YAML (`--camera`), else the photos' EXIF (core/exif_intrinsics.py: DJI XMP
calibrated focal, FocalLength with the focal plane resolution or a known sensor width, or the 35 mm
equivalent; principal point at the centre, distortion zero), all said in the report's assumptions.
Nothing else beside the folder (a simulator's ground_truth.json, a camera.yaml) is read for it.

Features are detected on each photo decoded at reduced size (core/photo_matching.py: a 4000 px frame
4x smaller, libjpeg decoding it directly), matched between candidate pairs from the geotags (and
heading and height above ground from a DJI XMP), photos with too few verified pairs matched again
with their next candidates, and chained into tracks. A photo stored rotated by 90 degrees is turned
back. A file that is empty, not an image or a truncated JPEG is skipped and named (the report's
assumptions and a warning), the others kept. Progress goes to `log` every few seconds.

Features (one task per photo) and matching (one task per pair) run in this process, or on a Dask
cluster (io/dask_cluster.py, `triangulate --workers/--scheduler`): the workers read the photos
themselves, keep each photo's descriptors, match pairs where the features are, and send back only
feature positions and verified matches; the matches are the same wherever they ran.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from photogram_ros.core import photo_matching as pm
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.core.incremental import KeyframeRecord
from photogram_ros.errors import CalibrationError, DataError
from photogram_ros.io.dask_cluster import InProcessRunner
from photogram_ros.io.geo_txt import EXIF_SIGMA_H_M, EXIF_SIGMA_V_M, read_geo_txt
from photogram_ros.io.image_source import (IMAGE_SUFFIXES, camera_of, file_digest, dji_rtk_accuracy,
                                           exif_altitude_to_ellipsoidal_m, exif_intrinsics, image_file_problem,
                                           read_dji_xmp, read_exif_gps, xmp_float)
from photogram_ros.io.keyframe_block import KeyframeBlock, camera_from_yaml


def exif_position(path: str | Path, altitude: str = 'msl', takeoff_h_m: float | None = None,
                  takeoff_heights: str = 'msl') -> tuple[float, float, float, float, float] | None:
    """A photo's EXIF GPS -> (lat_deg, lon_deg, h_m ellipsoidal, h_acc_m, v_acc_m), or None without one: a DJI RTK
    photo's XMP sigmas (image_source.dji_rtk_accuracy), else EXIF_SIGMA_H_M / EXIF_SIGMA_V_M, as camera_node
    publishes it (ExifGps.gnss_fix).

    `altitude`, `takeoff_h_m`, `takeoff_heights`: what the EXIF altitude is relative to
    (`image_source.exif_altitude_to_ellipsoidal_m`).
    """
    fix = read_exif_gps(path)
    if fix is None:
        return None
    h_m = float(exif_altitude_to_ellipsoidal_m(fix.lat_deg, fix.lon_deg, fix.alt_msl_m, altitude, takeoff_h_m,
                                               takeoff_heights))
    return (fix.lat_deg, fix.lon_deg, h_m, *fix.sigmas_m(EXIF_SIGMA_H_M, EXIF_SIGMA_V_M))


def _positions(src: Path, images: list[Path], exif_altitude, takeoff_h_m, takeoff_heights, assumptions):
    """{image name: geo.txt/EXIF position}, the EXIF positions to check as MSL (or None), and the count of
    photos per DJI RtkFlag ({} without RTK XMP)."""
    if (src / 'geo.txt').exists():
        assumptions.append('positions from geo.txt (heights ellipsoidal, per-image accuracy used as sigma)')
        if exif_altitude:
            assumptions.append(f'--exif-altitude {exif_altitude} ignored: positions come from geo.txt')
        return read_geo_txt(src / 'geo.txt'), None, {}
    geo = {}
    flags = {}
    for p in images:
        g = exif_position(p, exif_altitude or 'msl', takeoff_h_m, takeoff_heights)
        if g:
            rtk = dji_rtk_accuracy(p)
            key = rtk[0] if rtk is not None else None
            flags[key] = flags.get(key, 0) + 1
            geo[p.name] = g
    if exif_altitude == 'relative':
        ref = 'MSL (EGM2008)' if takeoff_heights == 'msl' else 'ellipsoidal'
        how = (f'EXIF altitude taken as height above the take-off point at {takeoff_h_m:.2f} m {ref}'
               + (', converted to ellipsoidal through EGM2008 at each photo' if takeoff_heights == 'msl' else ''))
    elif exif_altitude == 'ellipsoidal':
        how = 'EXIF altitude taken as ellipsoidal (WGS84), as --exif-altitude ellipsoidal says'
    else:
        how = 'EXIF altitude taken as MSL (EGM2008) and converted to ellipsoidal'
    rtk_counts = {k: n for k, n in flags.items() if k is not None}
    if rtk_counts:
        from photogram_ros.core.exposure_positions import DJI_RTK_FLAG_NAMES
        said = ', '.join(f'{n} {DJI_RTK_FLAG_NAMES.get(k, "flag")} ({k})' for k, n in
                         sorted(rtk_counts.items(), key=lambda kn: -kn[1]))
        none = flags.get(None, 0)
        assumptions.append(f'positions from EXIF GPS; {how}; DJI RTK XMP (drone-dji:RtkFlag, RtkStdLon/Lat/Hgt) of '
                           f'{sum(rtk_counts.values())} photos: {said}; each weighted by its RTK sigmas, at least its '
                           'flag\'s quality floor (float 10 / 20 cm, single 1.5 / 3 m)'
                           + (f'; {none} photos without an RTK flag: sigma {EXIF_SIGMA_H_M:g} m horizontal, '
                              f'{EXIF_SIGMA_V_M:g} m vertical' if none else ''))
    else:
        assumptions.append(f'positions from EXIF GPS; {how}; sigma {EXIF_SIGMA_H_M:g} m horizontal, {EXIF_SIGMA_V_M:g} m '
                           'vertical (the heights of one flight agree far better than their absolute error)')
    # Checked once the block has a ground: only then can an MSL reading be seen to be wrong.
    check = np.array([g[:3] for g in geo.values()]) if exif_altitude is None and geo else None
    return geo, check, {str(k): n for k, n in rtk_counts.items()}


def _pixels(p: Path) -> tuple[int, int]:
    """A photo's (long, short) side in pixels from its header (a panorama of any size without Pillow's
    decompression-bomb warning)."""
    w, h, _ = camera_of(p)
    return max(w, h), min(w, h)


def _say(note: str, assumptions: list, log) -> None:
    assumptions.append(note)
    if log is not None:
        log(f'warning: {note}')


def _names(ps: list[Path]) -> str:
    return f'{", ".join(p.name for p in ps[:10])}{" ..." if len(ps) > 10 else ""}'


def _exif_camera(p: Path):
    """exif_intrinsics of a photo, a panorama of any size read without Pillow's decompression-bomb warning (only
    its header is read)."""
    from PIL import Image
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', Image.DecompressionBombWarning)
        return exif_intrinsics(p)


def _calibrated_camera(images: list[Path], camera_path, assumptions, log) -> tuple[PinholeCamera, dict]:
    """The calibration file's camera and the photos of another size than it (either way round), by name with
    why: a stray panorama or thumbnail is left out, not the set. CalibrationError when no photo has its size."""
    camera = camera_from_yaml(camera_path)
    size = (max(camera.width, camera.height), min(camera.width, camera.height))
    others = [p for p in images if _pixels(p) != size]
    if len(others) == len(images):
        w, h, _ = camera_of(images[0])
        raise CalibrationError(f'the photos are {w}x{h} (e.g. {images[0].name}) but the calibration {camera_path} is '
                               f'for {camera.width}x{camera.height}: give the calibration of this camera mode '
                               '(--camera), or leave --camera out to take the camera from the photos\' EXIF')
    assumptions.append(f'calibration from {camera_path}, held fixed')
    why = {}
    for p in others:
        w, h, _ = camera_of(p)
        why[p.name] = f'another image size ({w}x{h} against the calibration\'s {camera.width}x{camera.height})'
    if others:
        _say(f'{len(others)} photos of another size than the calibration\'s {camera.width}x{camera.height} not used: '
             f'{_names(others)}; one camera model per block', assumptions, log)
    return camera, why


def _camera(src: Path, images: list[Path], camera_path, assumptions, log=None
            ) -> tuple[PinholeCamera, bool, list[Path]]:
    """_camera_and_left_out without the photos left out (the camera, whether it came from the EXIF, the photos
    of that camera)."""
    return _camera_and_left_out(src, images, camera_path, assumptions, log)[:3]


def _camera_and_left_out(src: Path, images: list[Path], camera_path, assumptions, log=None
                         ) -> tuple[PinholeCamera, bool, list[Path], dict]:
    """--camera, else the EXIF of the photos; whether it came from the EXIF; the photos of that camera; and
    the photos left out, by name with why. From the EXIF, photos of two cameras (another image size, or a
    focal length more than 5 % apart) are split by camera: the largest group is used, the others are named in
    the assumptions as not used (one camera model per block). A photo without EXIF intrinsics (a stitched
    panorama, a thumbnail) is taken with the main camera when it has its image size, else named and left
    out: a stray image never refuses the set."""
    if camera_path:
        camera, why = _calibrated_camera(images, camera_path, assumptions, log)
        return camera, False, [p for p in images if p.name not in why], why
    groups = []          # [(first estimate, [paths])]: one per camera
    unknown = []         # photos without EXIF intrinsics: taken with the main camera when of its size
    for p in images:
        try:
            e = _exif_camera(p)
        except (CalibrationError, DataError):
            unknown.append(p)
            continue
        c = e.camera
        size = (max(c.width, c.height), min(c.width, c.height))
        for est0, members in groups:
            c0 = est0.camera
            if (max(c0.width, c0.height), min(c0.width, c0.height)) == size and abs(c.fx / c0.fx - 1.0) <= 0.05:
                members.append(p)
                break
        else:
            groups.append((e, [p]))
    if not groups:
        exif_intrinsics(images[0])   # raises the error that says what the EXIF lacks
    groups.sort(key=lambda g: -len(g[1]))
    est, members = groups[0]
    main_size = (max(est.camera.width, est.camera.height), min(est.camera.width, est.camera.height))
    why = {}
    sized = [p for p in unknown if _pixels(p) == main_size]
    odd = [p for p in unknown if p not in set(sized)]
    sizes = {}
    for p in odd:
        w, h, _ = camera_of(p)
        sizes[p.name] = f'{w}x{h}'
        why[p.name] = (f'another image size without EXIF focal length ({w}x{h}: a panorama, a thumbnail or another '
                       'camera)')
    if odd:
        _say(f'{len(odd)} images of another size and without an EXIF focal length not used (a panorama, a '
             f'thumbnail or another camera; the block\'s camera is {est.camera.width}x{est.camera.height} px): '
             f'{"; ".join(f"{p.name} ({sizes[p.name]})" for p in odd[:10])}{" ..." if len(odd) > 10 else ""}',
             assumptions, log)
    used = set(members) | set(sized)
    others = {}
    for p in members[1:]:
        c = exif_intrinsics(p).camera
        if abs(c.fx / est.camera.fx - 1.0) > 1e-3:
            others[p.name] = c.fx
    assumptions.append(f'no calibration given: camera from the EXIF of {members[0].name}, {est.note} (source: '
                       f'{est.source}); pass --camera calib.yaml to use a calibration instead')
    if others:
        assumptions.append(f'{len(others)} photos state another focal length (e.g. {next(iter(others))}: '
                           f'{next(iter(others.values())):.1f} px): a zoom lens; one camera is used')
    for e, ps in groups[1:]:
        c = e.camera
        for p in ps:
            why[p.name] = (f'another camera ({c.width}x{c.height} px, f {c.fx:.0f} px; one camera model per '
                           'block)')
        _say(f'{len(ps)} photos of another camera not used ({c.width}x{c.height} px, f {c.fx:.0f} px, against '
             f'{est.camera.width}x{est.camera.height} px, f {est.camera.fx:.0f} px of the {len(members)} used): '
             f'{_names(ps)}; one camera model per block: triangulate them as a folder of their own', assumptions, log)
    return est.camera, True, [p for p in images if p in used], why


def _drop_duplicates(images: list[Path], assumptions: list, log) -> tuple[list[Path], dict]:
    """`images` without the byte-identical copies of a photo (one file downloaded twice: the same features
    twice would make a pair of a photo with itself), and the copies by name with why; the shortest name is
    kept (DJI_0070.JPG before 'DJI_0070 (1).JPG'). Only files of one byte size are compared byte for byte."""
    by_size: dict = {}
    for p in sorted(images, key=lambda p: (len(p.name), p.name)):   # 'a.JPG' kept before 'a (1).JPG'
        by_size.setdefault(p.stat().st_size, []).append(p)
    why = {}
    for same in by_size.values():
        seen: dict = {}
        for p in same if len(same) > 1 else ():
            d = file_digest(p)
            if d in seen:
                why[p.name] = f'identical to {seen[d].name} (a duplicate copy)'
            else:
                seen[d] = p
    if why:
        _say(f'{len(why)} duplicate photos dropped: {"; ".join(f"{n} {w}" for n, w in list(why.items())[:10])}'
             f'{" ..." if len(why) > 10 else ""}', assumptions, log)
    return [p for p in images if p.name not in why], why


def _usable_images(src: Path, assumptions: list, log) -> tuple[list[Path], int]:
    """The folder's image files that can be used, and how many image files it holds."""
    files = sorted(p for p in src.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    images, bad = [], []
    for p in files:
        why = image_file_problem(p)
        if why is None:
            images.append(p)
        else:
            bad.append(f'{p.name} ({why})')
    if bad:
        note = f'{len(bad)} files skipped, not usable: {"; ".join(bad[:10])}' + (' ...' if len(bad) > 10 else '')
        assumptions.append(note)
        if log is not None:
            log(f'warning: {note}')
    return images, len(files)


@dataclass
class MatchStats:
    """What matching did (the report's figures and the benchmark's)."""
    photos: int = 0
    features: list = field(default_factory=list)     # per photo
    pairs_tried: int = 0
    pairs_verified: int = 0
    status_counts: dict = field(default_factory=dict)
    widened_photos: int = 0                          # photos matched with more candidates
    features_s: float = 0.0
    matching_s: float = 0.0
    track_lengths: dict = field(default_factory=dict)   # photos per track -> tracks

    def to_dict(self) -> dict:
        f = np.asarray(self.features, float)
        return {'photos': self.photos, 'features_median': float(np.median(f)) if len(f) else 0.0,
                'features_min': int(f.min()) if len(f) else 0, 'pairs_tried': self.pairs_tried,
                'pairs_verified': self.pairs_verified, 'pair_status': dict(self.status_counts),
                'widened_photos': self.widened_photos, 'features_s': round(self.features_s, 2),
                'matching_s': round(self.matching_s, 2),
                'track_lengths': {str(k): int(v) for k, v in sorted(self.track_lengths.items())}}


def _read_gray(path: Path, camera: PinholeCamera, opt: pm.MatchingOptions, assumptions: list):
    """The photo in grey at the reduced size, and full-photo pixels per reduced pixel (x, y)."""
    from PIL import Image
    with Image.open(path) as im:
        w, h = im.size
        if im.getexif().get(0x0112, 1) in (5, 6, 7, 8):   # EXIF orientation: OpenCV turns these by 90 degrees
            w, h = h, w
    r, wr, hr = pm.reduced_size(w, h, opt.max_image_px)
    flag = {1: cv2.IMREAD_GRAYSCALE, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4,
            8: cv2.IMREAD_REDUCED_GRAYSCALE_8}[r]
    img = cv2.imread(str(path), flag)
    if img is None:
        raise DataError(f'{path.name} cannot be decoded')
    factor = [float(r), float(r)]
    if (img.shape[1], img.shape[0]) != (wr, hr):
        factor = [r * img.shape[1] / wr, r * img.shape[0] / hr]
        img = cv2.resize(img, (wr, hr), interpolation=cv2.INTER_AREA)
    if (w, h) != (camera.width, camera.height):
        if (h, w) == (camera.width, camera.height):
            img = cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)
            factor = factor[::-1]
            assumptions.append(f'{path.name} was stored rotated by 90 degrees: rotated back')
        else:
            camera.check_image_size(w, h)
    return img, factor


def _footprints(images: list[Path], positions: np.ndarray, camera: PinholeCamera) -> np.ndarray | None:
    """(N, 3) ground footprints (width_m, height_m, rotation_deg of the image x axis from east) from a
    DJI XMP's gimbal yaw and height above take-off, for near-nadir photos; None when any lacks them."""
    out = []
    for p in images:
        x = read_dji_xmp(p)
        yaw, pitch, rel = (xmp_float(x, k) for k in ('GimbalYawDegree', 'GimbalPitchDegree', 'RelativeAltitude'))
        if yaw is None or rel is None or rel <= 1.0 or (pitch is not None and pitch > -70.0):
            return None
        out.append((rel * camera.width / camera.fx, rel * camera.height / camera.fy, -yaw))
    return np.array(out) if len(out) == len(positions) else None


def _looked_down(images: list[Path], assumptions: list) -> bool:
    """Whether the survey looked down: the DJI XMP gimbal pitch of most photos within 20 degrees of
    -90 where the photos state one; a mapping survey (nadir) where they do not."""
    pitch = [xmp_float(read_dji_xmp(p), 'GimbalPitchDegree') for p in images]
    pitch = np.array([v for v in pitch if v is not None], float)
    if len(pitch) < len(images) / 2:
        return True
    down = bool(np.median(pitch) <= -70.0)
    if not down:
        assumptions.append(f'the photos\' gimbal pitch (median {np.median(pitch):.0f} degrees) says an oblique '
                           'survey: the block check does not expect nadir cameras')
    return down


def _photo_features(path: Path, camera: PinholeCamera, opt: pm.MatchingOptions):
    """One photo's features (a task): (PhotoFeatures, full-photo pixels per reduced pixel (x, y),
    the notes for the report's assumptions)."""
    notes = []
    gray, fxy = _read_gray(path, camera, opt, notes)
    return pm.extract(path.name, gray, fxy, opt), fxy, notes


def _feature_positions(result) -> tuple:
    """What the block needs of a `_photo_features` result: (feature positions (K, 2), factor, notes);
    the descriptors stay where they were computed."""
    f, fxy, notes = result
    return f.uv, fxy, notes


def _match_task(a: tuple, b: tuple, camera, opt, factor, i, j) -> pm.PairMatch:
    """`pm.match_pair` of two photos given as `_photo_features` results (a task)."""
    return pm.match_pair(a[0], b[0], camera, opt, factor, i, j)


def _match_block(images, feats, camera, pos, sigma_h_m, footprints, opt, factor, log, stats: MatchStats,
                 runner=None):
    """Verified matches {(i, j): (M, 2) feature indices} of the candidate pairs, widened twice at most
    for weakly linked photos. `feats`: per photo a `_photo_features` result or a runner's handle to one."""
    runner = runner or InProcessRunner()
    order, first = pm.candidate_order(pos, opt.neighbours, sigma_h_m, footprints)
    pairs = pm.candidate_pairs(order, first)
    matches, tried = {}, set()
    verified = np.zeros(len(images), int)
    t0 = time.monotonic()
    rounds = 0
    while pairs:
        found = [0]

        def count(k, r):
            found[0] += int(r.verified)

        results = runner.run(_match_task, [(feats[i], feats[j], camera, opt, factor, i, j) for i, j in pairs],
                             'matching pairs' if not rounds else 'matching more pairs for weakly linked photos',
                             log, on_result=count, extra=lambda: f', {found[0]} verified')
        for (i, j), r in zip(pairs, results):
            tried.add((i, j))
            stats.status_counts[r.status] = stats.status_counts.get(r.status, 0) + 1
            if r.verified:
                matches[(i, j)] = r.matches
                verified[[i, j]] += 1
        rounds += 1
        if rounds > 2:
            break
        pairs = pm.more_candidates(order, tried, verified, opt.min_pairs, opt.max_extra)
        if pairs:
            stats.widened_photos += int(np.sum(verified < opt.min_pairs))
    stats.pairs_tried, stats.pairs_verified = len(tried), len(matches)
    stats.matching_s = time.monotonic() - t0
    return matches


def _central_origin(positions: list) -> LocalFrame:
    """The local frame at the geotag nearest the median latitude and longitude of the block's photos
    ((lat_deg, lon_deg, h_m, ...) each): a few photos of another site, far away, do not move it."""
    P = np.array([p[:3] for p in positions], float)
    med = np.median(P[:, :2], axis=0)
    i = int(np.argmin(np.hypot(P[:, 0] - med[0], (P[:, 1] - med[1]) * np.cos(np.radians(med[0])))))
    return LocalFrame(*P[i])


def read_photo_block(src: str | Path, camera_path: str | Path | None = None, neighbours: int = 8,
                     exif_altitude: str | None = None, takeoff_h_m: float | None = None,
                     takeoff_heights: str = 'msl', log=None, matching: pm.MatchingOptions | None = None,
                     runner=None, origin_without_positions: LocalFrame | None = None) -> KeyframeBlock:
    """The photos of the folder `src` as a KeyframeBlock, in file-name order.

    neighbours: photos matched with each photo first (replaces matching.neighbours); exif_altitude
    ('msl', 'ellipsoidal', 'relative' with takeoff_h_m in takeoff_heights, or None: msl, checked
    after the adjustment); log(text): progress lines and warnings; matching: feature and matching
    options (core.photo_matching.MatchingOptions); runner: where features and pair matching run
    (io/dask_cluster.py; default: this process, in order); origin_without_positions: the map frame's origin
    when no photo has a position (a block the GCPs place; every pair is matched), which is refused
    without it. The block's `stats` holds MatchStats.to_dict().
    """
    src = Path(src)
    if not src.is_dir():
        raise DataError(f'{src} is not a folder of photos')
    opt = pm.MatchingOptions(**{**(matching.__dict__ if matching else {}), 'neighbours': int(neighbours)})
    assumptions = []
    images, n_files = _usable_images(src, assumptions, log)
    if len(images) < 3:
        raise DataError(f'{src} holds {len(images)} usable images: at least 3 overlapping photos are needed')
    geo, exif_check, rtk_flags = _positions(src, images, exif_altitude, takeoff_h_m, takeoff_heights, assumptions)
    if not any(p.name in geo for p in images) and origin_without_positions is None:
        raise DataError(f'no image in {src} has a position (EXIF GPS or geo.txt): georeferencing impossible '
                        '(give the photos\' positions in a geo.txt, or a GCP file with 3 GCPs or more: --gcp)')
    images, excluded = _drop_duplicates(images, assumptions, log)
    camera, from_exif, images, other_camera = _camera_and_left_out(src, images, camera_path, assumptions, log)
    excluded.update(other_camera)
    if len(images) < 3:
        raise DataError(f'{src} holds {len(images)} usable images of one camera: at least 3 overlapping photos are '
                        f'needed ({len(excluded)} left out: {", ".join(list(excluded)[:5])})')
    placed = [geo[p.name] for p in images if p.name in geo]
    if not placed and origin_without_positions is None:
        raise DataError(f'no photo of the camera used in {src} has a position (EXIF GPS or geo.txt): '
                        'georeferencing impossible (give a GCP file with 3 GCPs or more: --gcp)')
    if placed:
        origin = _central_origin(placed)
    else:
        origin = origin_without_positions
        assumptions.append('no photo has a position (EXIF GPS or geo.txt): every pair of photos is matched, and '
                           'the GCPs alone place the block (3 or more needed)')
    stats = MatchStats(photos=len(images))
    t0 = time.monotonic()
    runner = runner or InProcessRunner()
    # Per photo its features (kept where computed: a worker's memory on a cluster), and here only
    # their positions.
    feats = runner.run(_photo_features, [(p, camera, opt) for p in images], 'features', log, keep=True)
    uvs = []
    for uv, fxy, notes in runner.run(_feature_positions, [(f,) for f in feats]):
        uvs.append(uv)
        assumptions.extend(notes)
    factor = max(fxy) if images else 1.0
    stats.features = [len(uv) for uv in uvs]
    stats.features_s = time.monotonic() - t0
    pos = np.array([origin.geodetic_to_enu(*geo[p.name][:3]) if p.name in geo else [np.nan] * 3 for p in images])
    sigma_h = float(np.median([g[3] for g in placed])) if placed else 0.0
    footprints = _footprints(images, pos, camera)
    if footprints is not None:
        assumptions.append('candidate pairs by footprint overlap (DJI XMP gimbal yaw and height above take-off)')
    matches = _match_block(images, feats, camera, pos, sigma_h, footprints, opt, factor, log, stats, runner)
    runner.release(feats)
    tracks = pm.build_tracks(stats.features, matches)
    lengths = pm.track_lengths(tracks)
    stats.track_lengths = {int(k): int(v) for k, v in enumerate(np.bincount(lengths)) if k >= 2 and v}
    if log is not None:
        log(f'{len(images)} photos, {sum(stats.features)} features ({stats.features_s:.1f} s), '
            f'{stats.pairs_verified}/{stats.pairs_tried} pairs verified ({stats.matching_s:.1f} s), '
            f'{int(np.sum(lengths >= 2))} tracks ({int(np.sum(lengths >= 3))} through 3+ photos)')
    lonely = [images[i].name for i in range(len(images))
              if not any(i in k for k in matches)]
    if lonely:
        assumptions.append(f'{len(lonely)} photos share no verified pair with any other: {lonely[:10]}')
    records = []
    for p, uv, tr in zip(images, uvs, tracks):
        keep = tr >= 0
        g = geo.get(p.name)
        fix = GnssFix(g[0], g[1], g[2], np.diag([g[3] ** 2, g[3] ** 2, g[4] ** 2])) if g else None
        records.append(KeyframeRecord(0, tr[keep], uv[keep], fix, p.name))
    block_stats = stats.to_dict()
    if rtk_flags:
        block_stats['rtk_flags'] = rtk_flags      # photos per DJI RtkFlag (the report's)
    return KeyframeBlock(camera, origin, records, assumptions, n_inputs=n_files, exif_geodetic=exif_check,
                         camera_from_exif=from_exif, stats=block_stats,
                         expect_nadir=_looked_down(images, assumptions), excluded=excluded)
