"""photogram-ros triangulate: offline aerial triangulation of a flight bag or a folder of geotagged photos."""

from __future__ import annotations

HELP = 'aerial triangulation of a flight bag or of geotagged photos (EXIF GPS or geo.txt), GCPs/check points; report'


def add_arguments(p) -> None:
    p.add_argument('input', help='a flight bag (images + /gps/fix or raw MAVLink), or a folder of geotagged JPEGs '
                                 '(with an optional OpenDroneMap geo.txt)')
    p.add_argument('--gcp', help='OpenDroneMap gcp_list.txt (first line a CRS; names CHK* are check points)')
    p.add_argument('--targets', help='for a bag: the flight\'s control file of ArUco targets, as `replay --gcp` reads '
                                   'it (first line a CRS, then "name marker_id x y z [sigma_h_m sigma_v_m]"; CHK* '
                                   'are check points): the markers found in the keyframes are the observations')
    p.add_argument('--check', default='', help='more check-point names, comma separated')
    p.add_argument('--out', required=True, help='output folder (poses.csv, sparse.ply/.las, report.md/.json)')
    p.add_argument('--camera', help='calibration YAML (ROS camera_calibration layout); default: the bag\'s '
                                    'camera_info, or the simulator truth beside the folder, if any')
    p.add_argument('--crs', help='output CRS (default: the GCP CRS, else the UTM zone of the first photo)')
    p.add_argument('--gcp-sigma', default='0.02,0.02,0.03', help='GCP sigma E,N,U in metres')
    p.add_argument('--neighbours', type=int, default=8, help='photos matched with each photo (by position)')
    p.add_argument('--window', type=int, default=10, help='sliding-window size of the incremental adjustment')
    p.add_argument('--lever-arm', default='0,0,0', help='antenna in the camera frame x,y,z (m)')
    p.add_argument('--self-calibrate', default='', help='intrinsics refined in the final adjustment, e.g. '
                                                        '"f,k1,k2" (from f, cx, cy, k1, k2, p1, p2, k3)')
    p.add_argument('--exif-altitude', choices=('msl', 'ellipsoidal', 'relative'), default=None,
                   help='what the photos\' EXIF GPSAltitude is: msl (the EXIF standard; default), ellipsoidal '
                        '(WGS84), or relative to the take-off point (many drones; needs --takeoff-altitude-m). '
                        'Not given: msl, and the report says if the adjusted ground makes that look wrong')
    p.add_argument('--takeoff-altitude-m', type=float, default=None,
                   help='height of the take-off point (m), for --exif-altitude relative')
    p.add_argument('--takeoff-heights', choices=('msl', 'ellipsoidal'), default='msl',
                   help='reference of --takeoff-altitude-m: msl (EGM2008; default) or ellipsoidal (WGS84)')


def _read_geo_txt(path):
    """OpenDroneMap geo.txt -> {name: (lat, lon, h_ellipsoidal, h_acc, v_acc)}."""
    from photogram_ros.core.geodesy import crs_to_geodetic
    from photogram_ros.errors import DataError
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
        h_acc = float(ln[7]) if len(ln) >= 9 else 5.0
        v_acc = float(ln[8]) if len(ln) >= 9 else 10.0
        out[ln[0]] = (lat, lon, h, max(h_acc, 1e-3), max(v_acc, 1e-3))
    return out


def _read_exif(path, altitude: str = 'msl', takeoff_h_m: float | None = None, takeoff_heights: str = 'msl'):
    """EXIF GPS -> (lat, lon, h_ellipsoidal, h_acc, v_acc) or None.

    `altitude`, `takeoff_h_m`, `takeoff_heights`: what the EXIF altitude is relative to
    (`image_source.exif_altitude_to_ellipsoidal_m`).
    """
    from photogram_ros.io.image_source import exif_altitude_to_ellipsoidal_m, read_exif_gps
    fix = read_exif_gps(path)
    if fix is None:
        return None
    h_m = float(exif_altitude_to_ellipsoidal_m(fix.lat_deg, fix.lon_deg, fix.alt_msl_m, altitude, takeoff_h_m,
                                               takeoff_heights))
    return fix.lat_deg, fix.lon_deg, h_m, 5.0, 10.0


def _read_gcps(path, origin, check_names):
    """ODM gcp_list.txt -> (control points, {image: {name: uv}})."""
    import numpy as np

    from photogram_ros.core.geodesy import crs_to_geodetic
    from photogram_ros.errors import DataError
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith('#')]
    crs = ' '.join(lines[0])
    pts, obs = {}, {}
    for ln in lines[1:]:
        if len(ln) < 6:
            raise DataError(f'{path}: line {" ".join(ln)!r} needs: x y z px py image [name]')
        x, y, z, u, v = (float(s) for s in ln[:5])
        name = ln[6] if len(ln) > 6 else f'{ln[0]}_{ln[1]}'
        lat, lon, h = crs_to_geodetic(x, y, z, crs)
        pts[name] = origin.geodetic_to_enu(float(lat), float(lon), float(h))
        obs.setdefault(ln[5], {})[name] = np.array([u, v])
    return crs, pts, obs


def run(a) -> int:
    import json
    import sys
    import time
    from pathlib import Path

    import cv2
    import numpy as np
    import yaml

    from photogram_ros.core import photo_matching as pm
    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.core.incremental import GnssFix, KeyframeRecord
    from photogram_ros.errors import CalibrationError, ConfigError, DataError

    src = Path(a.input)
    exif_altitude = getattr(a, 'exif_altitude', None)
    takeoff_h_m = getattr(a, 'takeoff_altitude_m', None)
    takeoff_heights = getattr(a, 'takeoff_heights', 'msl')
    if takeoff_h_m is not None and exif_altitude != 'relative':
        raise ConfigError('--takeoff-altitude-m is only used with --exif-altitude relative (EXIF altitudes above '
                          'the take-off point): add that, or drop --takeoff-altitude-m')
    if exif_altitude == 'relative' and takeoff_h_m is None:
        raise ConfigError('--exif-altitude relative needs the take-off point\'s height: --takeoff-altitude-m H '
                          '(m above mean sea level; add --takeoff-heights ellipsoidal for a WGS84 height)')
    if (src / 'metadata.yaml').exists():
        targets = None
        if a.targets:
            from photogram_ros.io.control_file import read_control_file
            targets = read_control_file(a.targets, a.check.split(','))
        camera, origin, records, assumptions = _bag_records(src, a.camera, targets)
        a.control_set = targets
        if exif_altitude:
            assumptions.append(f'--exif-altitude {exif_altitude} ignored: a bag has no EXIF')
        return _adjust_and_write(a, records, camera, origin, assumptions, {})
    if not src.is_dir():
        raise DataError(f'{src} is not a folder of photos')
    images = sorted(p for p in src.iterdir() if p.suffix.lower() in ('.jpg', '.jpeg', '.png', '.tif', '.tiff'))
    if len(images) < 3:
        raise DataError(f'{src} holds {len(images)} images: at least 3 overlapping photos are needed')
    assumptions = []
    # Positions
    geo = {}
    info = {'n_inputs': len(images)}
    if (src / 'geo.txt').exists():
        geo = _read_geo_txt(src / 'geo.txt')
        assumptions.append('positions from geo.txt (heights ellipsoidal, per-image accuracy used as sigma)')
        if exif_altitude:
            assumptions.append(f'--exif-altitude {exif_altitude} ignored: positions come from geo.txt')
    else:
        for p in images:
            g = _read_exif(p, exif_altitude or 'msl', takeoff_h_m, takeoff_heights)
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
        if exif_altitude is None and geo:
            # Checked once the block has a ground: only then can an MSL reading be seen to be wrong.
            info['exif_geodetic'] = np.array([g[:3] for g in geo.values()])
    first = next((geo[p.name] for p in images if p.name in geo), None)
    if first is None:
        raise DataError(f'no image in {src} has a position (EXIF GPS or geo.txt): georeferencing impossible')
    origin = LocalFrame(first[0], first[1], first[2])
    # Camera
    if a.camera:
        camera = PinholeCamera.from_ros_yaml_dict(yaml.safe_load(Path(a.camera).read_text()))
        assumptions.append(f'calibration from {a.camera}, held fixed')
    elif (src.parent / 'ground_truth.json').exists():
        camera = PinholeCamera.from_ros_yaml_dict(json.loads((src.parent / 'ground_truth.json').read_text())['camera'])
        assumptions.append('calibration from the simulator truth beside the photos, held fixed')
    else:
        raise CalibrationError('no calibration: pass --camera calib.yaml (make one with photogram-ros calibrate)')
    # Features and matches
    t0 = time.monotonic()
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
    pos = np.array([origin.geodetic_to_enu(*geo[p.name][:3]) if p.name in geo else [np.nan] * 3 for p in images])
    pos = np.where(np.isfinite(pos), pos, np.nanmean(pos, axis=0))
    matches = {}
    for i, j in pm.neighbours(pos, a.neighbours):
        m = pm.match_pair(feats[i], feats[j], camera)
        if len(m):
            matches[(i, j)] = m
    tracks = pm.build_tracks([len(f.uv) for f in feats], matches)
    print(f'{len(images)} photos, {sum(len(f.uv) for f in feats)} features, {len(matches)} verified pairs, '
          f'in {time.monotonic() - t0:.1f} s', file=sys.stderr)
    records = []
    for p, f, tr in zip(images, feats, tracks):
        keep = tr >= 0
        g = geo.get(p.name)
        fix = GnssFix(g[0], g[1], g[2], np.diag([g[3] ** 2, g[3] ** 2, g[4] ** 2])) if g else None
        records.append(KeyframeRecord(0, tr[keep], f.uv[keep], fix, p.name))
    return _adjust_and_write(a, records, camera, origin, assumptions, info)


def _relative_exif_note(origin, points_map_m, photos_geodetic, control_map_m=None) -> str | None:
    """The report's warning when EXIF altitudes read as MSL put the ground where no survey is.

    `points_map_m`: adjusted tie points (N, 3) in the map (ENU, m); `photos_geodetic`: (M, 3) lat_deg, lon_deg,
    h_m (ellipsoidal) of the photos from their EXIF as MSL; `control_map_m`: surveyed GCP/check
    points (map ENU), which are the ground when given: a block strained between GCPs and wrong
    photo heights has tie points anywhere.
    """
    import numpy as np

    from photogram_ros.core import geoid
    from photogram_ros.io import image_source as isrc
    if control_map_m is not None and len(control_map_m):
        P, what = np.asarray(control_map_m, float).reshape(-1, 3), 'median GCP/check point'
    else:
        P, what = points_map_m[np.all(np.isfinite(points_map_m), axis=1)], 'median tie point'
    if not len(P):
        return None
    lat, lon, h = origin.enu_to_geodetic(P)
    ground_msl_m = float(np.median(geoid.ellipsoid_to_msl_m(lat, lon, h)))
    # Back through the same geoid: exactly the EXIF altitudes as written.
    photo_alt_m = float(np.median(geoid.ellipsoid_to_msl_m(*photos_geodetic.T)))
    if not isrc.exif_altitudes_look_relative(ground_msl_m, photo_alt_m):
        return None
    return (f'EXIF altitudes look relative to the take-off point, not MSL: the ground ({what}) is at '
            f'{ground_msl_m:.1f} m MSL and the photos\' EXIF altitude (median) {photo_alt_m:.1f} m '
            f'(rule: ground within {isrc.GROUND_NEAR_SEA_LEVEL_M:.0f} m of 0 m MSL with the photos '
            f'{isrc.MIN_FLYING_HEIGHT_M:.0f} m or more above it, ground below {isrc.GROUND_BELOW_SEA_LEVEL_M:.0f} m '
            'MSL, or photos below the ground). Heights here are then off by about the take-off height (with GCPs, '
            'the whole block is strained): rerun with --exif-altitude relative --takeoff-altitude-m H (the take-off '
            'point\'s height above MSL; add --takeoff-heights ellipsoidal for a WGS84 one), or with '
            '--exif-altitude msl if the site really lies there')


def _adjust_and_write(a, records, camera, origin, assumptions, info) -> int:
    """Incremental AT of the keyframe records, a full adjustment, then poses, sparse cloud and report."""
    import csv
    import sys
    from pathlib import Path

    import numpy as np

    from photogram_ros.core.at_report import build_report, intrinsics_sigma, write_report
    from photogram_ros.core.geodesy import utm_epsg
    from photogram_ros.core.incremental import ControlPoint, IncrementalAT, IncrementalOptions
    from photogram_ros.core.rotations import opk_from_map_R_cam
    from photogram_ros.io.export import GeoCloud, enu_to_crs, write_las, write_ply

    out = Path(a.out)
    # Control
    control, target_obs = [], {}
    crs = a.crs
    if getattr(a, 'control_set', None) is not None:   # a bag's targets file: observations already in records
        control = a.control_set.in_map(origin)
    elif a.gcp:
        gcp_crs, gcp_pts, target_obs = _read_gcps(Path(a.gcp), origin, {s.strip() for s in a.check.split(',')})
        sigma = np.array([float(v) for v in a.gcp_sigma.split(',')])
        checks = {s.strip() for s in a.check.split(',') if s.strip()}
        for name, xyz in gcp_pts.items():
            role = 'check' if name.upper().startswith('CHK') or name in checks else 'gcp'
            control.append(ControlPoint(name, np.asarray(xyz, float), sigma, role))
        crs = crs or gcp_crs
    crs = crs or f'EPSG:{utm_epsg(origin.lat_deg, origin.lon_deg)}'
    lever = tuple(float(v) for v in a.lever_arm.split(','))
    at = IncrementalAT(camera, IncrementalOptions(window_size=a.window, lever_arm_cam_m=lever), origin, control)
    for rec in records:
        if target_obs:
            rec.target_uv = target_obs.get(rec.name, {})
        at.add_keyframe(rec)
    # Photos that did not register in sequence get a second chance against the whole block.
    for kf in at.kfs:
        if kf.map_T_cam is None and at.registered and at._register(kf).registered:
            at._triangulate_new(kf)
    refine = tuple(v.strip() for v in a.self_calibrate.split(',') if v.strip())
    before = camera
    rep_adj = at.full_adjustment(refine_intrinsics=refine)
    self_cal = None
    if refine:
        after = at.camera
        self_cal = {k: {'before': float(getattr(before, k)), 'after': float(getattr(after, k))}
                    for k in ('fx', 'fy', 'cx', 'cy')}
        self_cal.update({n: {'before': before.dist[i], 'after': after.dist[i]}
                         for i, n in enumerate(('k1', 'k2', 'p1', 'p2', 'k3'))})
        sig = intrinsics_sigma(at, refine)
        for name, v in sig.items():
            for key in (('fx', 'fy') if name == 'f' else (name,)):
                if key in self_cal:
                    self_cal[key]['sigma'] = v
        if 's0_px' in sig:
            self_cal['s0_px'] = sig['s0_px']
        sf = f" +- {sig['f']:.2f}" if 'f' in sig else ''
        assumptions.append(f'self-calibration of {", ".join(refine)} in the final adjustment: '
                           f'fx {before.fx:.2f} -> {after.fx:.2f}{sf} px (sigmas a posteriori, scaled by the '
                           'variance of unit weight; parameters not refined have none)')
    lost = [kf.name for kf in at.kfs if kf.map_T_cam is None]
    if lost:
        assumptions.append(f'{len(lost)} photos could not be oriented (blurred or without overlap): {lost[:10]}')
    assumptions.append('lever arm antenna-camera ' + str(lever) + ' m in the camera frame')
    P = np.array([at.points[t] for t in at.points if t >= 0]).reshape(-1, 3)
    if info.get('exif_geodetic') is not None:
        note = _relative_exif_note(origin, P, info['exif_geodetic'], [c.map_xyz for c in control])
        if note:
            assumptions.append(note)
            print(f'warning: {note}', file=sys.stderr)
    # Outputs
    out.mkdir(parents=True, exist_ok=True)
    with open(out / 'poses.csv', 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(['image', 'x', 'y', 'z', 'crs', 'lat_deg', 'lon_deg', 'h_m', 'omega_deg', 'phi_deg', 'kappa_deg'])
        for k in at.registered:
            kf = at.kfs[k]
            C = kf.map_T_cam[:3, 3]
            e, n, h = enu_to_crs(origin, C[None], crs)
            lat, lon, hh = origin.enu_to_geodetic(C)
            o, ph, ka = np.degrees(opk_from_map_R_cam(kf.map_T_cam[:3, :3]))
            w.writerow([kf.name, f'{e[0]:.4f}', f'{n[0]:.4f}', f'{h[0]:.4f}', crs, f'{float(lat):.9f}',
                        f'{float(lon):.9f}', f'{float(hh):.4f}', f'{o:.5f}', f'{ph:.5f}', f'{ka:.5f}'])
    e, n, h = enu_to_crs(origin, P, crs)
    cloud = GeoCloud(e, n, h, np.full((len(P), 3), 200, np.uint8), np.ones(len(P), np.uint32),
                     np.ones(len(P), np.float32), crs, 'ellipsoidal')
    write_ply(cloud, out / 'sparse.ply')
    write_las(cloud, out / 'sparse.las')
    rep = build_report(at, assumptions)
    rep['crs'] = crs
    rep['adjustment_status'] = rep_adj.status
    if self_cal is not None:
        rep['self_calibration'] = self_cal
    md, js = write_report(rep, out)
    ck = rep['check']['rmse']
    print(f"oriented {len(at.registered)}/{info.get('n_inputs', len(records))} images, {len(P)} tie points, reprojection "
          f"{rep['reprojection_rms_px']:.3f} px; check points: "
          + (f"n={ck['n']} RMSE horizontal {ck['horizontal_m'] * 100:.1f} cm, vertical {ck['vertical_m'] * 100:.1f} cm"
             if ck.get('n') else 'none') + f'; wrote {out}')
    return 0


def _bag_records(src, camera_path, targets=None):
    """Keyframes of a flight bag: its images through the tracker, fixes from /gps/fix or raw MAVLink;
    with `targets` (a ControlSet), the ArUco markers found in each keyframe by name."""
    import sys

    import numpy as np
    import yaml

    from photogram_ros import msgs
    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.core.incremental import GnssFix, KeyframeRecord
    from photogram_ros.core.keyframes import GpsFix
    from photogram_ros.core.control import detect_keyframe_targets
    from photogram_ros.core.tracker import Tracker
    from photogram_ros.errors import CalibrationError, DataError
    from photogram_ros.io import mavlink as ml
    from photogram_ros.io.bag import BagReader, deserialize

    assumptions = []
    with BagReader(src) as bag:
        topics = bag.topics()
        image_topics = [t for t in ('/camera/image_raw', '/camera/image_raw/compressed') if t in topics]
        if not image_topics:
            raise DataError(f'{src} has no /camera/image_raw(/compressed) topic: nothing to triangulate')
        fixes = []
        if '/gps/fix' in topics:
            for m in bag.messages(['/gps/fix']):
                d = msgs.fix_from_navsatfix(deserialize(m.msgtype, m.data))
                if d['status'] >= 0 and np.isfinite(d['lat_deg']):
                    fixes.append(GpsFix.from_dict(d))
            assumptions.append('positions from the bag\'s /gps/fix (ellipsoidal heights, their covariance as sigma)')
        elif '/mavlink/from_fcu' in topics:
            stream = ml.MavlinkStream()
            raw = []
            for m in bag.messages(['/mavlink/from_fcu']):
                raw += [(x, m.stamp_ns * 1e-9) for x in stream.feed(bytes(deserialize(m.msgtype, m.data).data))]
            events, _ = ml.fixes_from_messages(raw)
            for ev in events:
                f = ev.fix
                if ev.best and f.has_position:
                    fixes.append(GpsFix(int(round(f.t_s * 1e9)), f.lat_deg, f.lon_deg, f.h_m,
                                        np.asarray(f.cov_enu_m2, float).reshape(3, 3)))
            assumptions.append('positions decoded from the raw MAVLink in the bag (GPS_RAW_INT, EGM2008 heights)')
        if camera_path:
            camera = PinholeCamera.from_ros_yaml_dict(yaml.safe_load(open(camera_path).read()))
            assumptions.append(f'calibration from {camera_path}, held fixed')
        elif '/camera/camera_info' in topics:
            first = next(bag.messages(['/camera/camera_info']))
            camera = msgs.camera_from_info(deserialize(first.msgtype, first.data))
            assumptions.append('calibration from the bag\'s camera_info, held fixed')
        else:
            raise CalibrationError(f'{src} has no camera_info: pass --camera calib.yaml')
        tracker = Tracker(camera)
        for f in fixes:
            tracker.add_fix(f)
        keyframes = []
        for m in bag.messages(image_topics[:1]):
            msg = deserialize(m.msgtype, m.data)
            keyframes += tracker.process(msgs.image_from_msg(msg), msgs.ns_from_time(msg.header.stamp))
        keyframes += tracker.flush()
        for e in bag.errors:
            assumptions.append(f'bag damaged: {e}; triangulated what precedes the damage')
    print(f'{src}: {len(keyframes)} keyframes, {len(fixes)} fixes', file=sys.stderr)
    records, n_seen = [], 0
    for kf in keyframes:
        fix = None if kf.fix is None else GnssFix(kf.fix.lat_deg, kf.fix.lon_deg, kf.fix.h_m,
                                                  np.asarray(kf.fix.covariance_enu_m2, float))
        obs = kf.observations
        target_uv = {}
        if targets is not None:
            target_uv, _ = targets.target_uv(detect_keyframe_targets(kf.image, camera))
            n_seen += len(target_uv)
        records.append(KeyframeRecord(kf.stamp_ns, obs['track_id'].astype(np.int64),
                                      np.column_stack([obs['u'], obs['v']]), fix, f'{kf.stamp_ns}', target_uv))
    first = next((r.fix for r in records if r.fix is not None), None)
    if first is None:
        raise DataError(f'no keyframe of {src} has a GNSS fix: georeferencing impossible')
    if targets is None:
        assumptions.append('no control points (give the flight\'s targets file with --targets for GCPs and check '
                           'points)')
    else:
        assumptions.append(f'control points from {targets.source or "the targets file"}: {len(targets.gcp_names)} GCPs, '
                           f'{len(targets.check_names)} check points, {n_seen} marker observations found by ArUco '
                           'detection in the keyframes')
    return camera, LocalFrame(first.lat_deg, first.lon_deg, first.h_m), records, assumptions
