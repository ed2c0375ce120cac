"""PX4 uXRCE-DDS input recorded: the sample flight's GNSS fixes and attitudes as PX4 publishes them
(/fmu/out/vehicle_gps_position px4_msgs/SensorGps, /fmu/out/vehicle_attitude px4_msgs/VehicleAttitude, no raw
MAVLink), written with rosbags from the package's px4_msgs definitions (px4_msgs has no PyPI wheel), read back as
the fixes and attitudes mavlink_node gives from the same flight, and replayed: the flight maps from them as from
its MAVLink stream (docs/e2e gates of tests/test_e2e_replay.py)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT

BOOT_US = 60_000_000        # the autopilot booted this long before the bag's start


def _px4_flight(sample_bag):
    """The fixes (best receiver) and attitudes mavlink_node publishes for the sample flight, each with the bag time
    of the MAVLink chunk that completed it: [(bag_ns, Fix | Attitude)]."""
    from photogram_ros.io.bag import BagReader, messages_from_bag
    from photogram_ros.io.mavlink_ingest import Attitude, FixEvent, Ingest
    ing = Ingest()
    out = []
    with BagReader(sample_bag) as r:
        last_ns = r.start_ns
        for m, arrival_s in messages_from_bag(r):
            last_ns = int(round(arrival_s * 1e9)) if arrival_s is not None else last_ns
            for ev in ing.handle(m, arrival_s):
                if isinstance(ev, FixEvent) and ev.best and ev.fix.has_position:
                    out.append((last_ns, ev.fix))
                elif isinstance(ev, Attitude):
                    out.append((last_ns, ev))
    return out


def _px4_bag(sample_bag, out) -> dict:
    """The sample flight's camera topics and its fixes and attitudes as PX4 records (boot clock BOOT_US before the
    bag's start; UTC times from the fixes). Returns counts per PX4 topic."""
    from photogram_ros.core.px4 import ENU_R_NED, FRD_R_FLU
    from photogram_ros.core.rotations import R_from_quat, quat_from_R
    from photogram_ros.io.bag import BagReader, BagWriter
    from photogram_ros.io.bag_px4 import (SENSOR_GPS, TOPIC_ATTITUDE, TOPIC_GPS, VEHICLE_ATTITUDE, px4_msgdef,
                                          px4_typestore, serialize_px4)
    from photogram_ros.io.mavlink_ingest import Attitude
    types = px4_typestore().types
    counts = {TOPIC_GPS: 0, TOPIC_ATTITUDE: 0}
    with BagReader(sample_bag) as r, BagWriter(out, storage='mcap') as w:
        boot0_us = r.start_ns // 1000 - BOOT_US
        topics = r.topics()
        for name in ('/camera/camera_info', '/camera/image_raw/compressed'):
            w.add_topic(name, topics[name].msgtype)
        w.add_topic(TOPIC_GPS, SENSOR_GPS, msgdef=px4_msgdef(SENSOR_GPS))
        w.add_topic(TOPIC_ATTITUDE, VEHICLE_ATTITUDE, msgdef=px4_msgdef(VEHICLE_ATTITUDE))
        for m in r.messages(topics=['/camera/camera_info', '/camera/image_raw/compressed']):
            w.write_raw(m.topic, m.stamp_ns, m.data)
        for bag_ns, ev in _px4_flight(sample_bag):
            t_us = int(round(ev.t_s * 1e6))
            if isinstance(ev, Attitude):
                ned_R_frd = ENU_R_NED.T @ R_from_quat(ev.q_enu_flu_xyzw) @ FRD_R_FLU
                x, y, z, qw = quat_from_R(ned_R_frd)
                msg = types[VEHICLE_ATTITUDE](timestamp=t_us - boot0_us, timestamp_sample=t_us - boot0_us,
                                              q=np.array([qw, x, y, z], np.float32),
                                              delta_q_reset=np.zeros(4, np.float32), quat_reset_counter=0)
                w.write_raw(TOPIC_ATTITUDE, bag_ns, serialize_px4(msg))
                counts[TOPIC_ATTITUDE] += 1
                continue
            fix = ev
            fields = {f: 0 for f, _ in px4_typestore().fielddefs[SENSOR_GPS][1]}
            fields.update(timestamp=t_us - boot0_us, timestamp_sample=t_us - boot0_us, time_utc_usec=t_us,
                          latitude_deg=fix.lat_deg, longitude_deg=fix.lon_deg, altitude_ellipsoid_m=fix.h_m,
                          altitude_msl_m=fix.h_m, fix_type=fix.fix_type, eph=float(np.sqrt(fix.var_enu_m2[0])),
                          epv=float(np.sqrt(fix.var_enu_m2[2])), satellites_used=fix.sats,
                          vel_ned_valid=False, rtcm_crc_failed=False, heading=float('nan'),
                          heading_offset=float('nan'))
            w.write_raw(TOPIC_GPS, bag_ns, serialize_px4(types[SENSOR_GPS](**fields)))
            counts[TOPIC_GPS] += 1
    return counts


def test_px4_records_read_back_as_the_flights_fixes_and_attitudes(sample_bag, tmp_path):
    """Without px4_msgs: the recorded SensorGps and VehicleAttitude read back (rosbags, the shipped definitions,
    core/px4.py) as the fixes and attitudes mavlink_node gives from the flight's MAVLink stream."""
    from photogram_ros.core.rotations import R_from_quat
    from photogram_ros.io.bag import BagReader
    from photogram_ros.io.bag_px4 import Px4Records, px4_topics
    from photogram_ros.io.mavlink_ingest import Attitude
    bag = tmp_path / 'px4_bag'
    counts = _px4_bag(sample_bag, bag)
    assert counts['/fmu/out/vehicle_gps_position'] > 300 and counts['/fmu/out/vehicle_attitude'] > 300
    want = _px4_flight(sample_bag)
    got = []
    with BagReader(bag) as r:
        px4 = px4_topics(r.topics())
        assert set(px4) == {'/fmu/out/vehicle_gps_position', '/fmu/out/vehicle_attitude'}
        records = Px4Records()
        for m in r.messages(list(px4)):
            got.append(records.read(m.msgtype, m.stamp_ns, m.data))
    fixes = [g for g in got if g[0] == 'fix']
    attitudes = [g for g in got if g[0] == 'attitude']
    want_fixes = [ev for _, ev in want if not isinstance(ev, Attitude)]
    want_att = [ev for _, ev in want if isinstance(ev, Attitude)]
    skipped = [g for g in got if g[0] == 'skipped']
    # PX4's attitude is on its boot clock: those before the first fix with a UTC time cannot be placed (2 here).
    assert len(fixes) == len(want_fixes) and len(attitudes) + len(skipped) == len(want_att)
    assert len(skipped) <= 5 and {g[2] for g in skipped} == {'attitude before the first fix with a UTC time'}
    want_att = want_att[len(skipped):]
    for (_, stamp, f), w in zip(fixes, want_fixes):
        assert stamp == int(round(w.t_s * 1e6)) * 1000
        assert abs(f['lat_deg'] - w.lat_deg) < 1e-9 and abs(f['lon_deg'] - w.lon_deg) < 1e-9
        assert abs(f['h_m'] - w.h_m) < 1e-6 and f['fix_type'] == w.fix_type and f['status'] == w.status
        assert f['var_enu_m2'][2] == pytest.approx(w.var_enu_m2[2], rel=1e-5)
    worst = 0.0
    for (_, stamp, q), w in zip(attitudes, want_att):
        assert abs(stamp - w.t_s * 1e9) < 1000          # microseconds, as PX4 keeps time
        dR = R_from_quat(q).T @ R_from_quat(w.q_enu_flu_xyzw)
        worst = max(worst, float(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    assert worst < 1e-6                                  # rad: float32 quaternions


@pytest.mark.slow
@pytest.mark.ros
def test_sample_flight_maps_from_recorded_px4_topics(sample_bag, tmp_path):
    """The replay plays the PX4 records as px4_adapter publishes them (/gps/fix, /gps/fix_type, /mavlink/attitude)
    and maps the flight as from its MAVLink stream: every keyframe oriented, the check points and the cameras
    within test_e2e_replay's gates (1.5x the figures it guards)."""
    from test_e2e_replay import gate

    from photogram_ros.sim.truth import GroundTruth
    bag = tmp_path / 'px4_bag'
    _px4_bag(sample_bag, bag)
    out = tmp_path / 'out'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(bag), '--out', str(out), '--quiet',
                        '--truth', str(sample_bag)], cwd=ROOT, capture_output=True, text=True, timeout=1800)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert 'body lever arm' not in r.stdout        # the attitude came: the body lever arm is applied
    rep = json.loads((out / 'report.json').read_text())
    counts = rep['run']['counts']
    cp = rep['check_points']['rmse']
    print(f"PX4 replay: {rep['keyframes_oriented']}/{rep['keyframes_taken']} keyframes oriented; check points "
          f"{cp['horizontal_m'] * 100:.1f} cm H, {cp['z_m'] * 100:.1f} cm V over {cp['count']}; cameras against "
          f"truth {rep['trajectory_vs_truth']}; bundle {counts.get('bundle')}")
    gsd_m = GroundTruth.load(sample_bag).gsd_m
    assert rep['mapping']['mapped'] and rep['keyframes_oriented'] == rep['keyframes_taken'] >= 50
    assert cp['count'] >= 6
    assert cp['horizontal_m'] <= gate('check_h') * gsd_m and cp['z_m'] <= gate('check_v') * gsd_m
    assert rep['trajectory_vs_truth']['rmse_m'] <= gate('cameras_m')
    # The attitudes recorded before the first fix with a UTC time cannot be placed on the UNIX clock: said, not lost
    # silently (2 of 778 here).
    skipped = json.loads((out / 'run.json').read_text())['px4_records_not_published']
    assert set(skipped) == {'attitude before the first fix with a UTC time'} and 0 < sum(skipped.values()) <= 5


OLD_SENSOR_GPS = '''uint64 timestamp
int32 lat
int32 lon
int32 alt
int32 alt_ellipsoid
uint8 fix_type
float32 eph
float32 epv
uint64 time_utc_usec
'''   # the position fields of SensorGps before PX4 v1.15 (1e-7 degrees, millimetres), as such a bag records them


def test_a_recording_of_an_older_px4_reads_through_its_own_definition(tmp_path):
    """rosbag2 records each type's definition: a SensorGps of a release before v1.15 (lat/lon in 1e-7 degrees)
    reads through the bag's own, not the shipped v1.15 fields."""
    from photogram_ros.io.bag import BagReader, BagWriter
    from photogram_ros.io.bag_px4 import SENSOR_GPS, TOPIC_GPS, Px4Records, px4_topics
    bag = tmp_path / 'old_px4'
    with BagWriter(bag, storage='mcap') as w:
        w.add_topic(TOPIC_GPS, SENSOR_GPS, msgdef=OLD_SENSOR_GPS)
        cls = w.types.types[SENSOR_GPS]
        w.write_raw(TOPIC_GPS, 1_781_000_000_200_000_000, bytes(w.types.serialize_cdr(
            cls(timestamp=5_000_000, lat=473977000, lon=85456000, alt=440000, alt_ellipsoid=488000, fix_type=6,
                eph=0.02, epv=0.03, time_utc_usec=1_781_000_000_123_456), SENSOR_GPS)))
    with BagReader(bag) as r:
        text = r.message_definition(TOPIC_GPS)
        assert text.strip() == OLD_SENSOR_GPS.strip()
        [m] = list(r.messages(list(px4_topics(r.topics()))))
    records = Px4Records({SENSOR_GPS: text})
    kind, stamp, fix = records.read(m.msgtype, m.stamp_ns, m.data)
    assert records.recorded == [SENSOR_GPS] and kind == 'fix' and stamp == 1_781_000_000_123_456_000
    assert fix['lat_deg'] == pytest.approx(47.3977) and fix['h_m'] == pytest.approx(488.0) and fix['fix_type'] == 6
    # Read with the shipped v1.15 fields instead, the record does not fit: skipped with the reason, never a wrong fix.
    kind, _, why = Px4Records().read(m.msgtype, m.stamp_ns, m.data)
    assert kind == 'skipped' and 'does not match' in why
