"""Survey-camera deliverables: geotagged JPEGs, an OpenDroneMap geo.txt, gcp_list.txt and camera.yaml.

Photos are taken at the front-overlap spacing a survey camera would use, from the same rendered
frames as the bag. EXIF GPS altitude is above mean sea level, as the EXIF standard says; geo.txt
carries the ellipsoidal height with per-image accuracy, as a PPK/RTK workflow would. The camera tags
are a real camera's: FocalLength (mm, for a 3 um pixel pitch), FocalPlaneX/YResolution with its unit,
FocalLengthIn35mmFilm (by the diagonal) and the image size, from which core/exif_intrinsics.py
recovers the focal length in pixels (principal point centred, no distortion: what a user of the photos
gets). camera.yaml is the simulated camera's calibration (principal point offset and distortion
included) in the ROS camera_info YAML that `triangulate --camera` reads, for runs that want a
calibrated camera; nothing reads it unless asked.
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
PPK_RATE_HZ = 5.0               # the PPK track's epoch rate
PPK_EPOCH_PHASE_S = 0.1         # its epochs' offset from the flight's own fix times
SIM_BOOT_BEFORE_START_S = 94.3  # the autopilot booted this long before the first fix of the flight
CAMERA_FILE = 'camera.yaml'     # the calibration beside the photos


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


def target_pixel(cam, map_T_cam: np.ndarray, point_map_m: np.ndarray, margin_px: float = 20.0):
    """(2,) distorted pixel of the map point seen by a camera at map_T_cam (4, 4, camera to map), or None when
    the camera does not see it: behind it, beyond the fold of its distortion (PinholeCamera.project), or
    outside the image (less `margin_px`)."""
    pc = transform_points(invert_T(map_T_cam), np.asarray(point_map_m, float).reshape(1, 3))
    uv, ok = cam.project(pc)
    if not ok[0] or not cam.in_image(uv, margin_px=margin_px)[0]:
        return None
    return uv[0]


def dji_rtk_xmp(flag: int, std_lon_m: float, std_lat_m: float, std_hgt_m: float) -> bytes:
    """An XMP packet as a DJI RTK drone writes its solution's quality: drone-dji:RtkFlag (50 fixed, 34 float,
    16 single) and RtkStdLon, RtkStdLat, RtkStdHgt (1-sigma, m)."""
    return ('<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>'
            '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
            '<rdf:Description rdf:about="DJI Meta Data" xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
            f'drone-dji:RtkFlag="{int(flag)}" drone-dji:RtkStdLon="{std_lon_m:.5f}" '
            f'drone-dji:RtkStdLat="{std_lat_m:.5f}" drone-dji:RtkStdHgt="{std_hgt_m:.5f}"/>'
            '</rdf:RDF></x:xmpmeta><?xpacket end="w"?>').encode('utf-8')


def insert_xmp(jpeg: Path, packet: bytes) -> None:
    """Put an XMP packet (APP1, Adobe's XMP namespace) right after the JPEG's SOI."""
    data = Path(jpeg).read_bytes()
    body = b'http://ns.adobe.com/xap/1.0/\x00' + packet
    seg = b'\xff\xe1' + (len(body) + 2).to_bytes(2, 'big') + body
    Path(jpeg).write_bytes(data[:2] + seg + data[2:])


def write_photos(folder: Path, frames, truth, cfg, exif_fixes=None, geo_txt: bool = True, xmp=None) -> list:
    """`frames`: [(index, image, FlightState)] of every rendered frame; writes the triggered ones.

    exif_fixes: the fixes (dicts as `truth.fixes`) the camera geotags its photos with (default: the
    flight's own GNSS), or a function (FrameTruth) -> such a fix; geo_txt: also write geo.txt from them;
    xmp: a function (photo name, FrameTruth) -> an XMP packet to put in the photo, or None. Also writes the
    camera's calibration (CAMERA_FILE). Returns [(photo name, FrameTruth)].
    """
    import yaml

    folder.mkdir(parents=True, exist_ok=False)
    (folder / CAMERA_FILE).write_text(yaml.safe_dump(truth.camera.to_ros_yaml_dict('sim_camera'), sort_keys=False,
                                                       default_flow_style=None))
    spacing_m = cfg.height_px * cfg.gsd_m * (1.0 - cfg.front_overlap)
    names, last = [], None
    geo_lines = ['EPSG:4326']
    fix_by_t = truth.fixes if exif_fixes is None else exif_fixes
    for k, img, st in frames:
        if last is not None and np.linalg.norm(st.pos_enu[:2] - last) < spacing_m:
            continue
        last = st.pos_enu[:2].copy()
        ft = truth.frames[k]
        # Photo position = GNSS antenna measurement nearest in time, as the camera geotags it.
        fix = fix_by_t(ft) if callable(fix_by_t) else min(
            (f for f in fix_by_t if 'lat_deg' in f), key=lambda f: abs(f['t_fix_unix_s'] - ft.stamp_ns * 1e-9),
            default=None)
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
        if xmp is not None:
            insert_xmp(folder / name, xmp(name, ft))
        geo_lines.append(f"{name} {fix['lon_deg']:.9f} {fix['lat_deg']:.9f} {fix['h_m']:.3f} 0 0 0 "
                         f"{fix['h_acc_m']:.3f} {fix['v_acc_m']:.3f}")
        names.append((name, ft))
    if geo_txt:
        (folder / 'geo.txt').write_text('\n'.join(geo_lines) + '\n')
    # gcp_list.txt: every target visible in every photo, in the UTM CRS, ellipsoidal heights.
    lines = [truth.crs]
    cam = truth.camera
    for t in truth.targets:
        lat, lon, h = truth.origin.enu_to_geodetic(t.center_enu)
        x, y, z = geodetic_to_crs(lat, lon, h, truth.crs)
        for name, ft in names:
            uv = target_pixel(cam, ft.map_T_cam, t.center_enu)
            if uv is not None:
                lines.append(f'{float(x):.4f} {float(y):.4f} {float(z):.4f} {uv[0]:.2f} {uv[1]:.2f} {name} {t.name}')
    (folder / 'gcp_list.txt').write_text('\n'.join(lines) + '\n')
    if geo_txt:
        (folder / 'README.txt').write_text(
            'Simulated survey photos. EXIF GPS altitude is MSL (geoid: ' + geoid.MODEL_NAME + '); geo.txt '
            'and gcp_list.txt heights are ellipsoidal (WGS84). Targets named CHK* are check points. The EXIF '
            'states the focal length only; ' + CAMERA_FILE + ' is the full calibration (triangulate --camera).\n')
    return names


def write_ppk(folder: Path, frames, truth, cfg, antenna_at_t) -> list:
    """What a PPK drone leaves in `folder`: photos geotagged by a consumer GNSS (EXIF, 3D fix, ~2 m), a
    5 Hz RTKLIB `flight.pos` of the antenna at survey accuracy (RTK-fixed error model, its sigmas,
    Q=1), a DJI `Timestamp.MRK` (exposure GPS times, the true antenna -> camera offset per photo in mm,
    N/E/V with V down, and the onboard single-point antenna position, flag 16), an ArduPilot `flight.bin`
    with a CAM message per photo (GPS time, body attitude) and gcp_list.txt.
    antenna_at_t(t_unix_s): the true antenna position (map ENU). Draws from its own random stream, so
    the rest of the simulation is unchanged by it."""
    from photogram_ros.core.exposure_positions import utc_unix_to_gps_s
    from photogram_ros.io.camera_events import write_mrk
    from photogram_ros.io.rtklib_pos import write_pos
    from photogram_ros.sim.dataflash import write_cam_log
    from photogram_ros.sim.gnss import MODES, GnssErrorModel, GnssScript

    rng = np.random.default_rng(cfg.seed + 24_000)
    consumer = GnssErrorModel(GnssScript('3d'), rng)
    survey = GnssErrorModel(GnssScript('rtk_fixed'), rng)
    t0_unix = min(f['t_fix_unix_s'] for f in truth.fixes)
    t1_unix = max(f['t_fix_unix_s'] for f in truth.fixes)
    # The receiver's epochs fall between exposures (0.1 s after the flight's own fixes), so every
    # photo position is interpolated.
    t_unix = np.arange(t0_unix + PPK_EPOCH_PHASE_S, t1_unix, 1.0 / PPK_RATE_HZ)
    exif_fixes, pos_llh, t_gps = [], [], []
    for t in t_unix:
        rel = float(t - t0_unix)
        a = antenna_at_t(rel + t0_unix)
        e_c = consumer.sample(rel).error_enu_m
        e_s = survey.sample(rel).error_enu_m * cfg.ppk_sigma_scale
        lat, lon, h = (float(v) for v in truth.origin.enu_to_geodetic(a + e_c))
        exif_fixes.append({'t_fix_unix_s': float(t), 'lat_deg': lat, 'lon_deg': lon, 'h_m': h,
                           'alt_msl_m': float(geoid.ellipsoid_to_msl_m(lat, lon, h)),
                           'h_acc_m': MODES['3d'].h_acc_m, 'v_acc_m': MODES['3d'].v_acc_m})
        pos_llh.append([float(v) for v in truth.origin.enu_to_geodetic(a + e_s)])
        t_gps.append(utc_unix_to_gps_s(float(t)))
    pos_llh = np.array(pos_llh)
    m = MODES['rtk_fixed']
    names = write_photos(folder, frames, truth, cfg, exif_fixes=exif_fixes, geo_txt=False)
    write_pos(folder / 'flight.pos', t_gps, pos_llh[:, 0], pos_llh[:, 1], pos_llh[:, 2],
              np.ones(len(t_gps), int), np.tile([m.h_acc_m, m.h_acc_m, m.v_acc_m], (len(t_gps), 1)))
    t_exp, off, llh, seqs = [], [], [], []
    for name, ft in names:
        t_s = ft.stamp_ns * 1e-9
        # the event mark: the exposure less the shutter's delay
        t_exp.append(utc_unix_to_gps_s(ft.stamp_ns // 1_000_000_000) + (ft.stamp_ns % 1_000_000_000) * 1e-9
                     - cfg.ppk_shutter_delay_ms * 1e-3)
        d_enu = ft.map_T_cam[:3, 3] - ft.antenna_enu
        off.append([d_enu[1], d_enu[0], -d_enu[2]])
        fx = min(exif_fixes, key=lambda f: abs(f['t_fix_unix_s'] - t_s))
        llh.append((fx['lat_deg'], fx['lon_deg'], fx['h_m']))
        seqs.append(int(name.split('_')[1].split('.')[0]))
    llh = np.array(llh)
    states = {k: st for k, _, st in frames}
    cams = []
    for (name, ft), t_g, seq, (lat, lon, h) in zip(names, t_exp, seqs, llh):
        st = states[ft.index]
        week, tow = divmod(t_g, 604800.0)
        cams.append({'boot_us': int(round((ft.stamp_ns * 1e-9 - t0_unix + SIM_BOOT_BEFORE_START_S) * 1e6)),
                     'img': seq, 'gps_week': int(week), 'gps_ms': int(round(tow * 1000)), 'lat_deg': lat,
                     'lon_deg': lon, 'alt_msl_m': float(geoid.ellipsoid_to_msl_m(lat, lon, h)),
                     'rel_alt_m': h - truth.origin.h_m, 'roll_deg': np.degrees(st.roll_rad),
                     'pitch_deg': np.degrees(st.pitch_rad), 'yaw_deg': np.degrees(st.yaw_rad)})
    write_cam_log(folder / 'flight.bin', cams)   # CAM at the event marks (t_exp), as the MRK
    write_mrk(folder / 'Timestamp.MRK', t_exp, np.array(off), llh[:, 0], llh[:, 1], llh[:, 2],
              [(MODES['3d'].h_acc_m, MODES['3d'].h_acc_m, MODES['3d'].v_acc_m)] * len(names), flag=16, seqs=seqs)
    (folder / 'README.txt').write_text(
        'Simulated PPK photo survey: EXIF GPS is a consumer 3D fix (altitude MSL, geoid ' + geoid.MODEL_NAME +
        '); flight.pos is the post-processed antenna track (RTKLIB layout, 5 Hz, GPST, ellipsoidal heights); '
        'Timestamp.MRK has the exposures (GPS time) with the antenna -> camera offsets (mm, N/E/V, V down); '
        'flight.bin is an ArduPilot dataflash log of the same exposures (CAM: GPS time, body attitude). '
        '`photogram-ros geotag --pos flight.pos --events Timestamp.MRK --photos .` writes geo.txt. '
        'gcp_list.txt heights are ellipsoidal; CHK* are check points. ' + CAMERA_FILE + ' is the camera\'s '
        'calibration (triangulate --camera); the EXIF states the focal length only.\n')
    return names


def write_rtk_photos(folder: Path, frames, truth, cfg) -> list:
    """What a DJI RTK drone (Phantom 4 RTK, M300 + P1) leaves in `folder`: photos whose EXIF GPS is the camera
    centre from its RTK solution (altitude MSL), and whose XMP carries the solution's flag and sigmas
    (drone-dji:RtkFlag, RtkStdLon/Lat/Hgt). Fixed photos: the RTK-fixed error model's noise, flag 50;
    with `cfg.rtk_float_every` n > 0 every n-th photo FLOAT, flag 34, its position `cfg.rtk_float_offset_m`
    off horizontally in a random direction, with the larger sigmas a float solution states. Also
    `rtk_truth.json`: per photo its flag and the position error written (for tests). Draws from its
    own random stream."""
    import json

    from photogram_ros.sim.gnss import MODES

    rng = np.random.default_rng(cfg.seed + 31_000)
    rng_float = np.random.default_rng(cfg.seed + 32_000)    # apart: the fixed photos' errors do not depend on it
    m = MODES['rtk_fixed']
    fixed_sd = (m.h_acc_m, m.h_acc_m, m.v_acc_m)
    float_sd = (0.5, 0.5, 0.8)
    written = {}

    def fix_for(ft):
        n = len(written)          # the photo's number in the survey, from 0
        is_float = cfg.rtk_float_every > 0 and n % cfg.rtk_float_every == cfg.rtk_float_every - 1
        err = rng.normal(0.0, 1.0, 3) * np.array(fixed_sd)
        if is_float:
            a = rng_float.uniform(0, 2 * np.pi)
            err = err + np.array([np.cos(a), np.sin(a), 0.0]) * cfg.rtk_float_offset_m
        lat, lon, h = (float(v) for v in truth.origin.enu_to_geodetic(ft.map_T_cam[:3, 3] + err))
        written[ft.index] = (34 if is_float else 50, float_sd if is_float else fixed_sd, err.tolist())
        return {'t_fix_unix_s': ft.stamp_ns * 1e-9, 'lat_deg': lat, 'lon_deg': lon, 'h_m': h,
                'alt_msl_m': float(geoid.ellipsoid_to_msl_m(lat, lon, h)), 'h_acc_m': fixed_sd[0],
                'v_acc_m': fixed_sd[2]}

    def xmp_for(name, ft):
        flag, sd, _ = written[ft.index]
        return dji_rtk_xmp(flag, sd[1], sd[0], sd[2])

    names = write_photos(folder, frames, truth, cfg, exif_fixes=fix_for, geo_txt=False, xmp=xmp_for)
    (folder / 'rtk_truth.json').write_text(json.dumps(
        {name: {'flag': written[ft.index][0], 'sd_neu_m': list(written[ft.index][1]),
                'error_enu_m': written[ft.index][2]} for name, ft in names}, indent=1))
    (folder / 'README.txt').write_text(
        'Simulated DJI RTK photo survey: EXIF GPS is the camera centre from the drone\'s RTK solution (altitude MSL, '
        'geoid ' + geoid.MODEL_NAME + '); each photo\'s XMP has drone-dji:RtkFlag (50 fixed, 34 float) and '
        'RtkStdLon/Lat/Hgt (m). rtk_truth.json: each photo\'s flag and the error written into its EXIF (ENU, m). '
        'gcp_list.txt heights are ellipsoidal; CHK* are check points.\n')
    return names


def write_geo_txt_from_exif_and_rtk_xmp(folder: Path) -> Path:
    """The geo.txt a user would make by hand for DJI RTK photos: each photo's EXIF position (altitude MSL,
    turned ellipsoidal) with its XMP RTK sigmas as the accuracies (io/photo_block.dji_rtk_accuracy)."""
    from photogram_ros.io.photo_block import dji_rtk_accuracy, exif_position
    lines = ['EPSG:4326']
    for p in sorted(Path(folder).glob('*.JPG')):
        lat, lon, h, _, _ = exif_position(p)
        _, sh, sv = dji_rtk_accuracy(p)
        lines.append(f'{p.name} {lon:.10f} {lat:.10f} {h:.4f} 0 0 0 {sh:.4f} {sv:.4f}')
    out = Path(folder) / 'geo.txt'
    out.write_text('\n'.join(lines) + '\n')
    return out
