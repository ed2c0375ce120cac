"""Recorded MAVROS and PX4 uXRCE-DDS topics (tests/data/autopilot, see its README.md) read back and replayed.

The recordings hold the sample flight's autopilot topics only, as each interface publishes them; the camera frames
are the sample bag's. Fast: each recording reads back as the fixes and attitudes mavlink_node decodes from the
sample flight's MAVLink stream; the player's MAVROS renames. Slow: the camera frames and one recording joined into
one bag and replayed (`photogram-ros replay`): the sample flight maps from them, and its products name their EPSG
codes and vertical datum (rasterio, laspy)."""

from __future__ import annotations

import json
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import ROOT

DATA = ROOT / 'tests' / 'data' / 'autopilot'
MAVROS_BAG = DATA / 'mavros_sample_flight'
PX4_BAG = DATA / 'px4_sample_flight'
CAMERA_TOPICS = ('/camera/camera_info', '/camera/image_raw/compressed')
MAVROS_FIX = '/mavros/global_position/raw/fix'
MAVROS_IMU = '/mavros/imu/data'
UTM = 32632                # the sample flight, near Zurich


def _flight(sample_bag):
    """mavlink_node's fixes and attitudes of the sample flight (tests/test_house_px4_replay.py)."""
    from test_house_px4_replay import _px4_flight

    from photogram_ros.io.mavlink_ingest import Attitude
    events = [ev for _, ev in _px4_flight(sample_bag)]
    return [e for e in events if not isinstance(e, Attitude)], [e for e in events if isinstance(e, Attitude)]


def _angle_rad(q1, q2) -> float:
    from photogram_ros.core.rotations import R_from_quat
    dR = R_from_quat(q1).T @ R_from_quat(q2)
    return float(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))


def test_the_recordings_are_small_mcap_of_the_autopilot_topics_only():
    from photogram_ros.io.bag import BagReader
    size = sum(f.stat().st_size for f in DATA.rglob('*') if f.is_file())
    assert size < 1_000_000, size           # tests/data kept small (both recordings: about 130 kB)
    with BagReader(MAVROS_BAG) as r:
        assert {t: i.msgtype for t, i in r.topics().items()} == {
            MAVROS_FIX: 'sensor_msgs/msg/NavSatFix', MAVROS_IMU: 'sensor_msgs/msg/Imu'}
    with BagReader(PX4_BAG) as r:
        assert {t: i.msgtype for t, i in r.topics().items()} == {
            '/fmu/out/vehicle_gps_position': 'px4_msgs/msg/SensorGps',
            '/fmu/out/vehicle_attitude': 'px4_msgs/msg/VehicleAttitude'}
        assert 'float64 latitude_deg' in r.message_definition('/fmu/out/vehicle_gps_position')
    for bag in (MAVROS_BAG, PX4_BAG):
        assert next(bag.glob('*.mcap')).exists()


def test_the_mavros_recording_reads_back_as_the_flights_fixes_and_attitudes(sample_bag):
    from sensor_msgs.msg import NavSatStatus

    from photogram_ros import msgs
    from photogram_ros.io.bag import BagReader, deserialize
    want_fixes, want_att = _flight(sample_bag)
    fixes, atts = [], []
    with BagReader(MAVROS_BAG) as r:
        for m in r.messages([MAVROS_FIX, MAVROS_IMU]):
            (fixes if m.topic == MAVROS_FIX else atts).append(deserialize(m.msgtype, m.data))
    assert len(fixes) == len(want_fixes) > 300 and len(atts) == len(want_att) > 300
    for f, w in zip(fixes, want_fixes):
        assert msgs.ns_from_time(f.header.stamp) == int(round(w.t_s * 1e9))
        assert abs(f.latitude - w.lat_deg) < 1e-12 and abs(f.longitude - w.lon_deg) < 1e-12
        assert abs(f.altitude - w.h_m) < 1e-9            # ellipsoidal, as MAVROS's raw/fix
        assert f.status.status == NavSatStatus.STATUS_FIX and f.header.frame_id == 'base_link'
        assert f.position_covariance[8] == pytest.approx(w.var_enu_m2[2])
    worst = max(_angle_rad([a.orientation.x, a.orientation.y, a.orientation.z, a.orientation.w], w.q_enu_flu_xyzw)
                for a, w in zip(atts, want_att))
    assert worst < 1e-7           # arccos of a trace near 3: its own rounding
    assert all(msgs.ns_from_time(a.header.stamp) == int(round(w.t_s * 1e9)) for a, w in zip(atts, want_att))


def test_the_px4_recording_reads_back_as_the_flights_fixes_and_attitudes(sample_bag):
    from photogram_ros.io.bag import BagReader
    from photogram_ros.io.bag_px4 import Px4Records, px4_topics
    want_fixes, want_att = _flight(sample_bag)
    with BagReader(PX4_BAG) as r:
        px4 = px4_topics(r.topics())
        records = Px4Records({m: r.message_definition(t) for t, m in px4.items()})
        got = [records.read(m.msgtype, m.stamp_ns, m.data) for m in r.messages(list(px4))]
    fixes = [g for g in got if g[0] == 'fix']
    atts = [g for g in got if g[0] == 'attitude']
    skipped = [g for g in got if g[0] == 'skipped']
    assert len(fixes) == len(want_fixes) > 300 and len(atts) + len(skipped) == len(want_att)
    assert len(skipped) <= 5      # attitudes before the first fix with a UTC time (2): PX4's boot clock
    for (_, stamp, f), w in zip(fixes, want_fixes):
        assert stamp == int(round(w.t_s * 1e6)) * 1000
        assert abs(f['lat_deg'] - w.lat_deg) < 1e-9 and abs(f['lon_deg'] - w.lon_deg) < 1e-9
        assert abs(f['h_m'] - w.h_m) < 1e-6 and f['fix_type'] == w.fix_type
    worst = max(_angle_rad(q, w.q_enu_flu_xyzw) for (_, _, q), w in zip(atts, want_att[len(skipped):]))
    assert worst < 1e-6           # float32 quaternions


def test_the_player_plays_mavros_topics_as_the_mappers_unless_the_bag_has_another_source():
    from photogram_ros.nodes.player_node import mavros_remaps
    info = SimpleNamespace
    nav, imu = info(msgtype='sensor_msgs/msg/NavSatFix'), info(msgtype='sensor_msgs/msg/Imu')
    cam = {'/camera/image_raw/compressed': info(msgtype='sensor_msgs/msg/CompressedImage')}
    both = {**cam, MAVROS_FIX: nav, MAVROS_IMU: imu}
    assert mavros_remaps(both, {}) == {MAVROS_FIX: '/gps/fix', MAVROS_IMU: '/mavlink/attitude'}
    # A rename the user gave wins; the mapper's own topic recorded is the source, not MAVROS's.
    assert mavros_remaps(both, {MAVROS_FIX: '/other'}) == {MAVROS_IMU: '/mavlink/attitude'}
    assert mavros_remaps({**both, '/gps/fix': nav}, {}) == {MAVROS_IMU: '/mavlink/attitude'}
    # Raw MAVLink decoded by mavlink_node, or PX4's records, give both already.
    assert mavros_remaps({**both, '/mavlink/from_fcu': info(msgtype='mavros_msgs/msg/Mavlink')}, {}) == {}
    px4 = {'/fmu/out/vehicle_gps_position': info(msgtype='px4_msgs/msg/SensorGps'),
           '/fmu/out/vehicle_attitude': info(msgtype='px4_msgs/msg/VehicleAttitude')}
    assert mavros_remaps({**both, **px4}, {}) == {}
    assert mavros_remaps(cam, {}) == {}


@pytest.mark.ros
def test_the_player_publishes_the_stored_mavros_topics_as_the_mappers(rclpy_context):
    from photogram_ros.nodes.player_node import PlayerNode
    for mavros, want in ((True, {'/gps/fix': 389, '/mavlink/attitude': 778}),
                         (False, {MAVROS_FIX: 389, MAVROS_IMU: 778})):
        node = PlayerNode(overrides={'bag': str(MAVROS_BAG), 'rate': 0.0, 'discovery_s': 0.0, 'mavros': mavros},
                          context=rclpy_context)
        try:
            summary = node.play()
        finally:
            node.destroy_node()
        assert summary.counts == want and not summary.errors and not summary.skipped, mavros


def join_camera_frames(sample_bag, recording, out) -> None:
    """One MCAP bag: the sample bag's camera frames and every topic of `recording` (with its recorded definitions),
    each message at its recorded bag time."""
    from photogram_ros.io.bag import BagReader, BagWriter
    with BagReader(sample_bag) as cam, BagReader(recording) as rec, BagWriter(out, storage='mcap') as w:
        cam_topics = cam.topics()
        for t in CAMERA_TOPICS:
            w.add_topic(t, cam_topics[t].msgtype)
        for t, i in rec.topics().items():
            w.add_topic(t, i.msgtype, msgdef=rec.message_definition(t) if i.msgtype.startswith('px4_msgs/') else None)
        merged = sorted([(m.stamp_ns, 0, m.topic, m.data) for m in cam.messages(list(CAMERA_TOPICS))]
                        + [(m.stamp_ns, 1, m.topic, m.data) for m in rec.messages()])
        for stamp_ns, _, topic, data in merged:
            w.write_raw(topic, stamp_ns, data)


def _replay(bag, out, sample_bag):
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(bag), '--out', str(out), '--quiet',
                        '--truth', str(sample_bag)], cwd=ROOT, capture_output=True, text=True, timeout=1800)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r.stdout, json.loads((out / 'report.json').read_text())


def _products_name_their_crs(out) -> None:
    """rasterio's to_epsg() the UTM code for the ortho, DSM and DTM; the DSM's vertical datum from its keys;
    laspy's parsed CRS an EPSG id."""
    import laspy
    import rasterio

    from photogram_ros.io.crs_tags import read_vertical
    for name in ('ortho.tif', 'dsm.tif', 'dtm.tif'):
        with rasterio.open(out / name) as ds:
            assert ds.crs.to_epsg() == UTM, name
    v = read_vertical(out / 'dsm.tif')
    assert v['HEIGHTS'] == 'ellipsoidal' and v['VERTICAL_CRS'] == 'EPSG:4979' and v['unit'] == 'metre'
    assert laspy.read(out / 'cloud.laz').header.parse_crs().to_epsg() == UTM


def _mapped_from(recording, sample_bag, tmp_path):
    """The sample bag's camera frames and `recording` replayed: every keyframe oriented, the check points measured,
    the products naming their CRS. Returns (stdout, report.json)."""
    bag = tmp_path / f'{recording.name}_with_frames'
    join_camera_frames(sample_bag, recording, bag)
    stdout, rep = _replay(bag, tmp_path / 'out', sample_bag)
    cp = rep['check_points']['rmse']
    print(f"{recording.name}: {rep['keyframes_oriented']}/{rep['keyframes_taken']} keyframes oriented; check points "
          f"{cp['horizontal_m'] * 100:.1f} cm H, {cp['z_m'] * 100:.1f} cm V over {cp['count']}; cameras against "
          f"truth {rep['trajectory_vs_truth']}; body lever arm left out: {'body lever arm' in stdout}")
    assert rep['mapping']['mapped'] and rep['keyframes_oriented'] == rep['keyframes_taken'] >= 50
    assert cp['count'] >= 6
    _products_name_their_crs(tmp_path / 'out')
    return stdout, rep


def _within_e2e_gates(rep, sample_bag) -> None:
    """test_e2e_replay's gates (the same flight from its MAVLink stream; 1.5x the figures they guard)."""
    from test_e2e_replay import gate

    from photogram_ros.sim.truth import GroundTruth
    gsd_m = GroundTruth.load(sample_bag).gsd_m
    cp = rep['check_points']['rmse']
    assert cp['horizontal_m'] <= gate('check_h') * gsd_m and cp['z_m'] <= gate('check_v') * gsd_m
    assert rep['trajectory_vs_truth']['rmse_m'] <= gate('cameras_m')


@pytest.mark.slow
@pytest.mark.ros
def test_sample_flight_maps_from_the_recorded_px4_topics(sample_bag, tmp_path):
    stdout, rep = _mapped_from(PX4_BAG, sample_bag, tmp_path)
    assert 'body lever arm' not in stdout          # the attitude came: the body lever arm is applied
    _within_e2e_gates(rep, sample_bag)


@pytest.mark.slow
@pytest.mark.ros
def test_sample_flight_maps_from_the_recorded_mavros_topics(sample_bag, tmp_path):
    """MAVROS's raw fix and imu/data, played by the player as /gps/fix and /mavlink/attitude. The fixes carry no
    RTK status (MAVROS marks every 3D fix STATUS_FIX): each is weighted by its own covariance."""
    stdout, rep = _mapped_from(MAVROS_BAG, sample_bag, tmp_path)
    assert 'body lever arm' not in stdout          # imu/data came: the body lever arm is applied
    _within_e2e_gates(rep, sample_bag)
