"""map_node over real rclpy topics: fusion, best-effort stream, keyframe saving, bad input, kill -9."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from helpers.clouds import pair_cloud
from helpers.processes import reaped

pytestmark = pytest.mark.ros
ROOT = Path(__file__).resolve().parents[1]
ORIGIN = dict(use_origin_params=True, origin_lat_deg=47.3977, origin_lon_deg=8.5456, origin_h_m=488.0)


def surface(x, y):
    return 3.0 + 0.05 * x - 0.02 * y


def _spin_until(executor, cond, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not cond():
        executor.spin_once(timeout_sec=0.05)
    return cond()


@pytest.fixture
def graph(rclpy_context, tmp_path):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    from photogram_ros.nodes.map_node import MapNode

    node = MapNode({'map_dir': str(tmp_path / 'map'), 'flush_interval_s': 0.2, 'stream_period_s': 0.2,
                    'stream_max_points': 3000, 'cell_m': 0.08, **ORIGIN}, context=rclpy_context)
    peer = Node('map_test_peer', context=rclpy_context)
    got = []
    peer.create_subscription(PointCloud2, '/map/cloud_downsampled', got.append,
                             QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    pub = peer.create_publisher(PointCloud2, '/map/dense_cloud',
                                QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE))
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(peer)
    _spin_until(ex, lambda: pub.get_subscription_count() > 0, 5.0)
    yield node, peer, pub, got, ex, tmp_path / 'map'
    ex.shutdown()
    peer.destroy_node()
    node.destroy_node()



@contextlib.contextmanager
def _map_node_process(map_dir, *params):
    """map_node as its own process (the console-script path), with `-p name:=value` parameters, named
    `proc.node_name` (one no other node has: its /diagnostics are its own); killed on leaving the block
    if it still runs."""
    name = f'map_node_{uuid.uuid4().hex[:8]}'
    cmd = [sys.executable, '-m', 'photogram_ros.nodes.map_node', '--ros-args', '-r', f'__node:={name}',
           '-p', f'map_dir:={map_dir}',
           '-p', 'cell_m:=0.08']   # these tests read the map with 0.08 m cells (not from the GSD)
    for prm in params:
        cmd += ['-p', prm]
    with reaped(subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ), stdout=subprocess.DEVNULL,
                                 stderr=subprocess.PIPE)) as proc:
        proc.node_name = f'/{name}'
        yield proc


def _cells(cloud) -> set:
    """The 0.08 m cells (ix, iy) a pair cloud's points fall in."""
    return set(zip(np.floor(cloud['x'] / 0.08).astype(int).tolist(), np.floor(cloud['y'] / 0.08).astype(int).tolist()))


def _cloud_feeder(name, context):
    """A publisher of pair clouds, returned once the map node in the other process has matched it."""
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    peer = Node(name, context=context)
    pub = peer.create_publisher(PointCloud2, '/map/dense_cloud',
                                QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
    deadline = time.monotonic() + 20
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    return peer, pub

def test_fuses_streams_and_persists(graph):
    from photogram_ros import msgs
    from photogram_ros.core.fusion import Fusion, FusionConfig
    from photogram_ros.io.map_store import MapStore

    node, peer, pub, got, ex, map_dir = graph
    rng = np.random.default_rng(1)
    clouds = [pair_cloud(rng, surface, 10.0 * k, 0.0, 8.0, 6.0, 150.0, 0.02) for k in range(3)]
    for k, c in enumerate(clouds):
        pub.publish(msgs.pointcloud2_msg(c, 1000 + k, 'map'))
    assert _spin_until(ex, lambda: node.diag.counts().get('clouds', 0) == 3)
    assert _spin_until(ex, lambda: len(got) >= 2)
    streamed = np.concatenate([msgs.points_from_pointcloud2(m) for m in got])
    assert all(m.width <= 3000 for m in got)                  # size-limited
    assert streamed.size < sum(c.size for c in clouds) / 10   # downsampled
    assert np.abs(streamed['z'] - surface(streamed['x'], streamed['y'])).max() < 0.1
    assert streamed['x'].min() > -8.5 and streamed['x'].max() < 28.5
    fused = node.fusion.points()
    node.flush()
    on_disk = Fusion(FusionConfig(0.08, 256), MapStore(map_dir)).points()
    assert on_disk['x'].size == fused['x'].size > 10000
    assert np.allclose(np.sort(on_disk['z']), np.sort(fused['z']))
    assert MapStore(map_dir).origin.lat_deg == pytest.approx(47.3977)


def test_bad_messages_are_counted_not_fatal(graph):
    from photogram_ros import msgs
    node, peer, pub, got, ex, _ = graph
    rng = np.random.default_rng(2)
    no_z = np.zeros(10, dtype=[('x', np.float32), ('y', np.float32)])
    pub.publish(msgs.pointcloud2_msg(no_z, 1, 'map'))
    pub.publish(msgs.pointcloud2_msg(pair_cloud(rng, surface, 0, 0, 2, 2, 100), 2, 'camera_optical'))
    pub.publish(msgs.pointcloud2_msg(pair_cloud(rng, surface, 0, 0, 2, 2, 100), 3, 'map'))
    assert _spin_until(ex, lambda: node.diag.counts().get('clouds', 0) == 1)
    assert node.diag.counts().get('problems', 0) == 2


def test_keyframes_saved_for_the_orthomosaic(graph):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import CameraInfo, Image
    from photogram_ros import msgs
    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.core.rotations import make_T
    from photogram_ros.io.map_store import MapStore

    node, peer, pub, got, ex, map_dir = graph
    rel = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pi = peer.create_publisher(Image, '/keyframes/image', rel)
    pp = peer.create_publisher(PoseWithCovarianceStamped, '/map/keyframe_pose', rel)
    pc = peer.create_publisher(CameraInfo, '/camera/camera_info', qos_profile_sensor_data)
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    T = make_T(np.diag([1.0, -1.0, -1.0]), np.array([1.0, 2.0, 40.0]))
    _spin_until(ex, lambda: pi.get_subscription_count() and pp.get_subscription_count(), 5.0)
    img = np.zeros((48, 64, 3), np.uint8)
    img[:, :32] = 200
    for _ in range(3):
        pc.publish(msgs.camera_info_msg(cam, 5))
        ex.spin_once(timeout_sec=0.05)
    pi.publish(msgs.image_msg(img, 123_000_000_000))
    pp.publish(msgs.pose_with_covariance_from_T(T, 123_000_000_000))
    store = MapStore(map_dir)
    assert _spin_until(ex, lambda: len(store.keyframes()) == 1 and store.load_camera() is not None)
    kf = store.keyframes()[0]
    assert kf['stamp_ns'] == 123_000_000_000 and np.allclose(kf['map_T_cam'], T)
    assert store.load_camera() == cam


def _diag_clouds(rclpy_context, timeout_s, want, node_name):
    """Number of clouds the map node `node_name` reports on /diagnostics (polls until `want` or timeout)."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    n = Node('diag_watch', context=rclpy_context)
    seen = {'clouds': 0}

    def on_diag(msg):
        for st in msg.status:
            if st.name == node_name:
                for kv in st.values:
                    if kv.key == 'clouds':
                        seen['clouds'] = int(kv.value)
    n.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(n)
    _spin_until(ex, lambda: seen['clouds'] >= want, timeout_s)
    ex.shutdown()
    n.destroy_node()
    return seen['clouds']


def test_kill_9_loses_only_the_last_seconds(rclpy_context, tmp_path):
    """A map_node process is killed with SIGKILL mid-flight; what it fused earlier is on disk and reloads."""
    from photogram_ros import msgs
    from photogram_ros.core.fusion import Fusion, FusionConfig
    from photogram_ros.io.map_store import MapStore

    map_dir = tmp_path / 'map'
    with _map_node_process(map_dir, 'flush_interval_s:=0.5', 'max_tiles_in_memory:=4') as proc:
        peer, pub = _cloud_feeder('crash_feeder', rclpy_context)
        assert pub.get_subscription_count() > 0, 'map_node did not start'
        rng = np.random.default_rng(3)
        # A track 200 m long: clouds along it, each 16 m x 12 m, so tiles are also evicted to disk.
        early = [pair_cloud(rng, surface, 0.0, 14.0 * k, 8.0, 6.0, 120.0, 0.02) for k in range(12)]
        for k, c in enumerate(early):
            pub.publish(msgs.pointcloud2_msg(c, k, 'map'))
        assert _diag_clouds(rclpy_context, 20.0, len(early), proc.node_name) >= len(early)
        time.sleep(1.5)                       # > flush_interval_s: the early clouds must now be durable
        late = pair_cloud(rng, surface, 0.0, 14.0 * 12, 8.0, 6.0, 120.0, 0.02)
        for k in range(5):                    # still arriving when the process dies
            pub.publish(msgs.pointcloud2_msg(late, 100 + k, 'map'))
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        assert proc.returncode == -signal.SIGKILL
        peer.destroy_node()

    pts = Fusion(FusionConfig(0.08, 256), MapStore(map_dir)).points()
    have = set(zip(pts['ix'].tolist(), pts['iy'].tolist()))
    for c in early:
        assert _cells(c) <= have, 'a cloud fused 1.5 s before the kill is missing on disk'
    assert np.abs(pts['z'] - surface(pts['x'], pts['y'])).max() < 0.15
    # A restarted node reloads the map and goes on.
    from photogram_ros.nodes.map_node import MapNode
    node = MapNode({'map_dir': str(map_dir)}, context=rclpy_context)
    try:
        assert node.fusion.points()['x'].size == pts['x'].size
    finally:
        node.destroy_node()


def test_origin_from_georeference_topic(rclpy_context, tmp_path):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import NavSatFix
    from photogram_ros import msgs
    from photogram_ros.io.map_store import MapStore
    from photogram_ros.nodes.map_node import MapNode

    peer = Node('georef_pub', context=rclpy_context)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = peer.create_publisher(NavSatFix, '/map/georeference', latched)
    pub.publish(msgs.navsatfix_msg(0, 47.3977, 8.5456, 488.0, 2, [0.01, 0.01, 0.02], 2))   # before the map starts
    node = MapNode({'map_dir': str(tmp_path / 'm')}, context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(peer)
    try:
        assert _spin_until(ex, lambda: MapStore(tmp_path / 'm').origin is not None)
        o = MapStore(tmp_path / 'm').origin
        assert (o.lat_deg, o.lon_deg, o.h_m) == (47.3977, 8.5456, 488.0)
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_sigint_and_sigterm_flush_everything(rclpy_context, tmp_path, sig):
    from photogram_ros import msgs
    from photogram_ros.core.fusion import Fusion, FusionConfig
    from photogram_ros.io.map_store import MapStore

    map_dir = tmp_path / 'map'
    # A flush interval far longer than the test: only the shutdown path can have written the map.
    with _map_node_process(map_dir, 'flush_interval_s:=600.0') as proc:
        peer, pub = _cloud_feeder('stop_feeder', rclpy_context)
        rng = np.random.default_rng(6)
        clouds = [pair_cloud(rng, surface, 0.0, 14.0 * k, 8.0, 6.0, 120.0, 0.02) for k in range(3)]
        for k, c in enumerate(clouds):
            pub.publish(msgs.pointcloud2_msg(c, k, 'map'))
        assert _diag_clouds(rclpy_context, 20.0, len(clouds), proc.node_name) >= len(clouds)
        proc.send_signal(sig)
        proc.wait(20)
        assert proc.returncode == 0, proc.stderr.read().decode()[-2000:]
        peer.destroy_node()
    pts = Fusion(FusionConfig(0.08, 256), MapStore(map_dir)).points()
    assert set(zip(pts['ix'].tolist(), pts['iy'].tolist())) == set().union(*map(_cells, clouds))


def _map_node(rclpy_context, tmp_path, **params):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from photogram_ros.nodes.map_node import MapNode
    node = MapNode({'map_dir': str(tmp_path / 'map'), 'flush_interval_s': 60.0, **ORIGIN, **params},
                   context=rclpy_context)
    peer = Node('map_test_peer2', context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(peer)
    return node, peer, ex


def _publishers(peer):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2
    rel = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    return (peer.create_publisher(CameraInfo, '/camera/camera_info', qos_profile_sensor_data),
            peer.create_publisher(PoseWithCovarianceStamped, '/map/keyframe_pose', rel),
            peer.create_publisher(Image, '/keyframes/image', rel),
            peer.create_publisher(PointCloud2, '/map/dense_cloud', rel))


@pytest.mark.parametrize('camera, height_m, want_cell_m', [((640, 480, 520.0), 40.0, 0.12),
                                                          ((1920, 1080, 1220.0), 166.0, 0.48)])
def test_the_cell_follows_the_gsd_of_the_first_pair_cloud(rclpy_context, tmp_path, camera, height_m, want_cell_m):
    # cell_m left at -1: the simulator's camera at 40 m gets the 0.12 m its configs held, a 1080p
    # camera at 166 m four times that (core/gsd.py), and the map folder says so.
    from photogram_ros import msgs
    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.core.rotations import make_T
    from photogram_ros.io.map_store import MapStore
    node, peer, ex = _map_node(rclpy_context, tmp_path)
    try:
        pc, pp, _, pub = _publishers(peer)
        w, h, f = camera
        cam = PinholeCamera(w, h, f, f, w / 2 - 0.5, h / 2 - 0.5)
        _spin_until(ex, lambda: pub.get_subscription_count() and pp.get_subscription_count(), 5.0)
        for _ in range(3):
            pc.publish(msgs.camera_info_msg(cam, 5))
            ex.spin_once(timeout_sec=0.05)
        pp.publish(msgs.pose_with_covariance_from_T(make_T(np.diag([1.0, -1.0, -1.0]),
                                                           np.array([0.0, 0.0, 3.0 + height_m])), 7))
        assert _spin_until(ex, lambda: node._camera is not None and node.posed_keyframes, 5.0)
        pub.publish(msgs.pointcloud2_msg(pair_cloud(np.random.default_rng(3), surface, 0, 0, 20, 20, 20), 9, 'map'))
        assert _spin_until(ex, lambda: node.diag.counts().get('clouds', 0) == 1)
        assert node.cell_m == pytest.approx(want_cell_m)
        node.flush()
        assert MapStore(tmp_path / 'map').cell_m == pytest.approx(want_cell_m)
        assert node.gsd is not None and node.gsd.flying_height_m == pytest.approx(height_m, abs=1.0)
    finally:
        ex.shutdown()
        peer.destroy_node()
        node.destroy_node()


def test_nothing_fused_for_n_keyframes_is_a_warning_with_the_reason(rclpy_context, tmp_path):
    from diagnostic_msgs.msg import DiagnosticStatus
    from photogram_ros import msgs
    node, peer, ex = _map_node(rclpy_context, tmp_path, warn_unfused_keyframes=2, cell_m=0.1)
    try:
        _, _, pi, _ = _publishers(peer)
        _spin_until(ex, lambda: pi.get_subscription_count(), 5.0)
        for k in range(5):          # before any fused cloud the limit is 3 x 2 keyframes: no warning yet
            pi.publish(msgs.image_msg(np.zeros((48, 64, 3), np.uint8), 1000 + k))
        assert _spin_until(ex, lambda: node.diag.counts().get('keyframes_saved', 0) == 5)
        node._update_diag()
        assert not any('nothing fused' in p for p in node.diag.recent_problems())
        pi.publish(msgs.image_msg(np.zeros((48, 64, 3), np.uint8), 2000))
        assert _spin_until(ex, lambda: node.diag.counts().get('keyframes_saved', 0) == 6)
        node._update_diag()
        problems = node.diag.recent_problems()
        assert any('nothing fused for 6+ keyframes' in p and 'stereo_node sent no pair cloud' in p for p in problems)
        assert node.diag.status().level == DiagnosticStatus.WARN
    finally:
        ex.shutdown()
        peer.destroy_node()
        node.destroy_node()


def test_a_full_disk_counts_write_failures_on_diagnostics(rclpy_context, tmp_path, monkeypatch):
    import builtins
    import errno
    from diagnostic_msgs.msg import DiagnosticStatus
    from photogram_ros import msgs
    from photogram_ros.io import map_store
    node, peer, ex = _map_node(rclpy_context, tmp_path, cell_m=0.1)
    try:
        _, _, _, pub = _publishers(peer)
        _spin_until(ex, lambda: pub.get_subscription_count(), 5.0)
        pub.publish(msgs.pointcloud2_msg(pair_cloud(np.random.default_rng(4), surface, 0, 0, 5, 5, 100), 9, 'map'))
        assert _spin_until(ex, lambda: node.diag.counts().get('clouds', 0) == 1)

        def full(path, mode='r', *a, **k):
            if 'a' in mode or 'w' in mode:
                raise OSError(errno.ENOSPC, 'No space left on device', str(path))
            return builtins.open(path, mode, *a, **k)
        monkeypatch.setattr(map_store, 'open', full, raising=False)
        node.flush()
        node.flush()
        st = node.diag.status()
        values = {kv.key: kv.value for kv in st.values}
        assert int(values['write_failures']) >= 2 and node.store.write_failures >= 2
        assert st.level == DiagnosticStatus.ERROR and 'disk' in st.message and 'full' in st.message
        assert not list((tmp_path / 'map').rglob('*.tmp'))
    finally:
        monkeypatch.undo()
        ex.shutdown()
        peer.destroy_node()
        node.destroy_node()


def test_a_provisional_pose_is_held_and_the_final_one_taken(graph):
    """A pose labelled provisional (core/pose_status.py: the roll about the first line assumed) is not draped:
    counted as held; the same keyframe's final pose is taken."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from photogram_ros import msgs
    from photogram_ros.core.pose_status import provisional_covariance
    node, peer, _, _, ex, _ = graph
    pub = peer.create_publisher(PoseWithCovarianceStamped, '/map/keyframe_pose', QoSProfile(
        history=HistoryPolicy.KEEP_ALL, depth=1, reliability=ReliabilityPolicy.RELIABLE))
    _spin_until(ex, lambda: pub.get_subscription_count() > 0, 5.0)
    T = np.eye(4)
    T[:3, 3] = (10.0, 5.0, 80.0)
    final = np.diag([0.01, 0.01, 0.02, 1e-6, 1e-6, 1e-6])
    pub.publish(msgs.pose_with_covariance_from_T(T, 10**9, covariance=provisional_covariance(final, (1, 0, 0))))
    assert _spin_until(ex, lambda: node.diag.counts().get('poses_provisional_held', 0) == 1, 5.0)
    pub.publish(msgs.pose_with_covariance_from_T(T, 10**9, covariance=final))
    _spin_until(ex, lambda: False, 0.5)
    assert node.diag.counts().get('poses_provisional_held', 0) == 1
