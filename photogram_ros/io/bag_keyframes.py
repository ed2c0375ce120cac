"""The keyframes of a flight bag, for an offline aerial triangulation (`photogram-ros triangulate BAG`).

The bag's images go through the same tracker as in flight (core/tracker.py), with the GNSS fixes
of /gps/fix, or, without that topic, the fixes decoded from the raw MAVLink of /mavlink/from_fcu
exactly as mavlink_node would publish them. With the flight's control file the ArUco targets found
in each keyframe become its target observations by name. The result is a KeyframeBlock whose
assumptions say where positions, calibration and control came from.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from photogram_ros import msgs
from photogram_ros.core.control import ControlSet, detect_keyframe_targets
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.core.incremental import KeyframeRecord
from photogram_ros.core.tracker import Tracker
from photogram_ros.errors import CalibrationError, DataError
from photogram_ros.io.bag import MAVLINK_TOPIC, BagReader, deserialize, messages_from_bag
from photogram_ros.io.keyframe_block import KeyframeBlock, camera_from_yaml

IMAGE_TOPICS = ('/camera/image_raw', '/camera/image_raw/compressed')


def bag_fixes(bag: BagReader) -> tuple[list[GnssFix], str | None]:
    """The bag's GNSS fixes in order (from /gps/fix, else decoded from raw MAVLink), and where from."""
    topics = bag.topics()
    fixes = []
    if '/gps/fix' in topics:
        for m in bag.messages(['/gps/fix']):
            d = msgs.fix_from_navsatfix(deserialize(m.msgtype, m.data))
            if d['status'] >= 0 and np.isfinite(d['lat_deg']):
                fixes.append(GnssFix.from_dict(d))
        return fixes, 'positions from the bag\'s /gps/fix (ellipsoidal heights, their covariance as sigma)'
    if MAVLINK_TOPIC in topics:
        from photogram_ros.io.mavlink import fixes_from_messages
        events, _ = fixes_from_messages(messages_from_bag(bag))
        for ev in events:
            f = ev.fix
            if ev.best and f.has_position:
                fixes.append(GnssFix.from_fix(f))
        return fixes, 'positions decoded from the raw MAVLink in the bag (GPS_RAW_INT, EGM2008 heights)'
    return fixes, None


def read_bag_keyframes(src: str | Path, camera_path: str | Path | None = None, targets: ControlSet | None = None,
                       log=None) -> KeyframeBlock:
    """Keyframes of the flight bag `src` as a KeyframeBlock.

    camera_path: a calibration YAML (default: the bag's first camera_info); targets: the flight's
    surveyed ArUco targets, found in each keyframe by marker id; log(text): progress lines.
    """
    src = Path(src)
    assumptions = []
    with BagReader(src) as bag:
        topics = bag.topics()
        image_topics = [t for t in IMAGE_TOPICS if t in topics]
        if not image_topics:
            raise DataError(f'{src} has no /camera/image_raw(/compressed) topic: nothing to triangulate')
        fixes, where = bag_fixes(bag)
        if where:
            assumptions.append(where)
        if camera_path:
            camera = camera_from_yaml(camera_path)
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
        # What was read and what was lost, in the report and on the console (the command goes on with
        # what the bag still holds).
        damage = list(dict.fromkeys(bag.errors))
        for e in damage:
            assumptions.append(f'bag damaged: {e}; triangulated what it still holds')
        for line in bag.health():
            if log is not None:
                log(line)
    if log is not None:
        log(f'{src}: {len(keyframes)} keyframes, {len(fixes)} fixes')
    records, n_seen = [], 0
    for kf in keyframes:
        fix = kf.fix
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
        assumptions.append(f'control points from {targets.source or "the targets file"}: {len(targets.gcp_names)} '
                           f'GCPs, {len(targets.check_names)} check points, {n_seen} marker observations found by '
                           'ArUco detection in the keyframes')
    return KeyframeBlock(camera, LocalFrame(first.lat_deg, first.lon_deg, first.h_m), records, assumptions,
                         damage=damage)
