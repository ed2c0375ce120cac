"""The frame tree where it can be checked here: recordings are MCAP with zstd chunks and the real ROS distro in
their metadata; the adjusted trajectory's /tf, /tf_static and map/path go into an MCAP through rosbags' type
store (no tf2_msgs among the PyPI wheels), and map -> camera_optical looked up from it at a keyframe's stamp is
the keyframe's pose within 1 mm; the live /tf publisher runs where tf2_msgs imports (a ROS 2 install)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT


def _poses(n: int = 12, seed: int = 4):
    """Camera poses of a nadir line at 80 m (z down, image top along the track), small tilts."""
    from photogram_ros.core.frames import BASE_T_OPTICAL_NADIR
    from photogram_ros.core.rotations import R_from_rotvec
    rng = np.random.default_rng(seed)
    Ts, stamps = [], []
    for k in range(n):
        T = np.eye(4)
        T[:3, :3] = R_from_rotvec([0, 0, 0.3]) @ R_from_rotvec(rng.normal(0, 0.05, 3)) @ BASE_T_OPTICAL_NADIR[:3, :3]
        T[:3, 3] = [4.0 * k + rng.normal(0, 0.1), 2.0 + rng.normal(0, 0.1), 80.0 + rng.normal(0, 0.2)]
        Ts.append(T)
        stamps.append(1_700_000_000_000_000_000 + k * 1_500_000_000 + int(rng.integers(0, 1000)))
    return stamps, Ts


def _rot_deg(A, B) -> float:
    c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


@pytest.mark.parametrize('compression', ['zstd', ''])
def test_mcap_recordings_are_zstd_chunked_and_name_the_ros_distro(tmp_path, compression):
    from std_msgs.msg import String
    from photogram_ros.io.bag import ROS_DISTRO, BagReader, BagWriter
    from photogram_ros.io.bag_storage import McapScan, read_metadata
    out = tmp_path / 'rec'
    with BagWriter(out, storage='mcap', compression=compression) as bag:
        for k in range(2000):
            bag.write('/chatter', 1_000 + k, String(data=f'message {k} ' + 'x' * 200))
    assert ROS_DISTRO == 'jazzy'
    meta, why = read_metadata(out)
    assert not why and meta.ros_distro == 'jazzy' and meta.storage == 'mcap'
    mcap = next(out.glob('*.mcap'))
    raw = mcap.read_bytes()
    assert b'ros_distro: jazzy' in raw and b'ros_distro: rosbags' not in raw    # the MCAP's own rosbag2 record
    scan = McapScan(mcap)
    assert sum(1 for _ in scan.messages()) == 2000 and not scan.stopped
    assert scan.compressions == {compression}
    if compression:
        assert mcap.stat().st_size < 2000 * 200 / 5         # the repeated text compresses
    with BagReader(out) as r:
        assert not r.damaged and r.topics()['/chatter'].count == 2000


def test_unknown_compression_is_refused(tmp_path):
    from photogram_ros.errors import BagError
    from photogram_ros.io.bag import BagWriter
    with pytest.raises(BagError, match='compression'):
        BagWriter(tmp_path / 'x', storage='mcap', compression='lz4')


def test_trajectory_mcap_gives_map_to_camera_optical_at_each_keyframe(tmp_path):
    from rosbags.typesys import Stores, get_typestore
    from photogram_ros.errors import BagError
    from photogram_ros.io.bag import BagReader
    from photogram_ros.io.bag_storage import McapScan, read_metadata
    from photogram_ros.io.tf_bag import TfBuffer, write_trajectory_mcap
    stamps, Ts = _poses()
    out = write_trajectory_mcap(tmp_path / 'trajectory', stamps, Ts, namespace='/drone1')
    buf = TfBuffer.from_bag(out)
    assert buf.frames() == {'map', 'drone1/odom', 'drone1/base_link', 'drone1/camera_optical'}
    for s, T in zip(stamps, Ts):
        got = buf.lookup('map', 'drone1/camera_optical', s)
        assert np.abs(got[:3, 3] - T[:3, 3]).max() < 1e-3 and _rot_deg(got, T) < 1e-4
    # base_link is FLU above a nadir camera: its z axis points up, its x along the track (yaw 0.3 rad).
    body = buf.lookup('map', 'drone1/base_link', stamps[0])
    assert body[2, 2] > 0.99 and abs(np.arctan2(body[1, 0], body[0, 0]) - 0.3) < 0.2
    # Between two keyframes tf interpolates; before the first it does not extrapolate.
    mid = buf.lookup('map', 'drone1/camera_optical', (stamps[3] + stamps[4]) // 2)
    assert np.abs(mid[:3, 3] - (Ts[3][:3, 3] + Ts[4][:3, 3]) / 2).max() < 1e-3
    with pytest.raises(BagError, match='extrapolate'):
        buf.lookup('map', 'drone1/camera_optical', stamps[0] - 1)
    with pytest.raises(BagError, match='not connected'):
        buf.lookup('map', 'drone2/camera_optical', stamps[0])
    meta, _ = read_metadata(out)
    assert meta.ros_distro == 'jazzy' and set(meta.topics) == {'/tf', '/tf_static', 'map/path'}
    assert meta.topics['/tf_static'][2][0]['durability'] == 'transient_local'      # latched
    scan = McapScan(next(out.glob('*.mcap')))
    assert sum(1 for _ in scan.messages()) == len(Ts) + 2 and scan.compressions == {'zstd'}
    store = get_typestore(Stores.ROS2_JAZZY)
    with BagReader(out) as bag:
        (m,) = list(bag.messages(topics=['map/path']))
    path = store.deserialize_cdr(m.data, m.msgtype)
    assert path.header.frame_id == 'map' and len(path.poses) == len(Ts)
    p = path.poses[5].pose.position
    assert np.allclose([p.x, p.y, p.z], Ts[5][:3, 3], atol=1e-9)


def test_flight_report_trajectory_writes_the_tf_recording(tmp_path):
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.io.flight_report import write_trajectory
    from photogram_ros.io.tf_bag import TfBuffer
    stamps, Ts = _poses(6)
    kfs = [{'stamp_ns': s, 'image_path': tmp_path / f'kf{k}.jpg', 'map_T_cam': T}
           for k, (s, T) in enumerate(zip(stamps, Ts))]
    for _ in range(2):     # a report made again in the same folder replaces the recording
        write_trajectory(tmp_path, kfs, LocalFrame(47.3977, 8.5456, 488.0), 'EPSG:32632')
    buf = TfBuffer.from_bag(tmp_path / 'trajectory')
    got = buf.lookup('map', 'camera_optical', stamps[2])
    assert np.abs(got[:3, 3] - Ts[2][:3, 3]).max() < 1e-3 and _rot_deg(got, Ts[2]) < 1e-4


def test_live_tf_publisher_where_tf2_msgs_imports(rclpy_context):
    """A ROS 2 install: the bundle node's publisher sends the tree; the PyPI wheels: a note on /diagnostics."""
    from rclpy.node import Node
    from photogram_ros.nodes.tf_publisher import NOT_AVAILABLE, TfPublisher, tf2_available
    node = Node('tf_probe', namespace='/drone1', context=rclpy_context)
    try:
        pub = TfPublisher(node)
        assert pub.frames['base_link'] == 'drone1/base_link'
        if not tf2_available():
            assert not pub.available and 'tf2_msgs' in NOT_AVAILABLE
            pub.poses([(np.eye(4), 1, None)])         # nothing to publish with, and no error
            pytest.skip('tf2_msgs is not importable (the PyPI wheels have none): the live /tf is not exercised here')
        from tf2_msgs.msg import TFMessage
        got = []
        node.create_subscription(TFMessage, '/tf', got.append, 10)
        stamps, Ts = _poses(3)
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        ex = SingleThreadedExecutor(context=rclpy_context)
        ex.add_node(node)
        pub.poses([(T, s, None) for s, T in zip(stamps, Ts)])
        for _ in range(50):
            ex.spin_once(timeout_sec=0.1)
            if got:
                break
        assert got and [t.child_frame_id for t in got[0].transforms] == ['drone1/base_link'] * 3
        del rclpy
    finally:
        node.destroy_node()


def test_bundle_node_says_on_diagnostics_when_tf_is_not_published(rclpy_context):
    from photogram_ros.nodes.bundle_node import BundleNode
    from photogram_ros.nodes.tf_publisher import NOT_AVAILABLE, tf2_available
    node = BundleNode(context=rclpy_context)
    try:
        values = dict((kv.key, kv.value) for kv in node.diag.status().values)
        if tf2_available():
            assert 'tf' not in values
        else:
            assert values.get('tf') == NOT_AVAILABLE
    finally:
        node.destroy_node()


@pytest.mark.slow
@pytest.mark.ros
def test_sample_flight_replay_records_the_tf_tree(sample_bag, tmp_path):
    """The sample flight replayed: trajectory/ holds /tf whose map -> camera_optical at each keyframe's stamp
    is the keyframe's adjusted pose in the map folder within 1 mm."""
    from photogram_ros.io.tf_bag import TfBuffer
    out = tmp_path / 'sample'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(sample_bag), '--out', str(out),
                        '--quiet'], cwd=ROOT, capture_output=True, text=True, timeout=1800)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    buf = TfBuffer.from_bag(out / 'trajectory')
    kf_files = sorted((out / 'map' / 'keyframes').glob('*.json'))
    assert len(kf_files) >= 50
    worst_m, worst_deg = 0.0, 0.0
    for f in kf_files:
        body = json.loads(f.read_text())
        T = np.asarray(body['map_T_cam'], float).reshape(4, 4)
        got = buf.lookup('map', 'camera_optical', int(body['stamp_ns']))
        worst_m, worst_deg = max(worst_m, np.abs(got[:3, 3] - T[:3, 3]).max()), max(worst_deg, _rot_deg(got, T))
    print(f'{len(kf_files)} keyframes: worst {worst_m * 1000:.4f} mm, {worst_deg:.2e} deg')
    assert worst_m < 1e-3 and worst_deg < 1e-4
