"""What ROS 2 and GIS users trip over first: the conventions a standard tool relies on.

- RViz2's XYZ transformer takes FLOAT32 only: map/dense_cloud carries x, y, z as FLOAT32 (local ENU
  metres in `map`; float32 rounds them by at most 0.5 mm within 8 km of the origin).
- One time base per run: in a replay every node takes the bag's time from /clock, so /diagnostics,
  map/cloud_downsampled and map/ortho_tiles are stamped inside the bag's time span, not with today's date.
- image_transport's convention: remapping camera/image_raw moves its /compressed sibling too.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from sensor_msgs.msg import PointField

from photogram_ros import msgs
from photogram_ros.core.stereo import CLOUD_DTYPE

pytestmark = pytest.mark.ros


def _dense_cloud(n: int, reach_m: float, rng) -> np.ndarray:
    c = np.zeros(n, CLOUD_DTYPE)
    for k in ('x', 'y'):
        c[k] = rng.uniform(-reach_m, reach_m, n)
    c['z'] = rng.uniform(-50.0, 150.0, n)
    c['rgb'] = rng.integers(0, 1 << 24, n, dtype=np.uint32)
    c['confidence'] = rng.uniform(0, 1, n).astype(np.float32)
    return c


def test_dense_cloud_is_float32_xyz_and_round_trips_within_a_millimetre():
    rng = np.random.default_rng(17)
    cloud = _dense_cloud(20000, 8000.0, rng)     # a flight reaching 8 km from the map origin
    msg = msgs.dense_cloud_msg(cloud, 123, 'map')
    types = {f.name: f.datatype for f in msg.fields}
    assert types['x'] == types['y'] == types['z'] == PointField.FLOAT32 == 7
    assert types['rgb'] == PointField.UINT32 and types['confidence'] == PointField.FLOAT32
    assert msg.point_step == 20 and msg.header.frame_id == 'map'
    back = msgs.points_from_pointcloud2(msg)
    err = max(np.abs(back[k].astype(np.float64) - cloud[k]).max() for k in ('x', 'y', 'z'))
    assert err <= 0.5e-3, f'{err * 1e3:.3f} mm'
    assert np.array_equal(back['rgb'], cloud['rgb']) and np.array_equal(back['confidence'], cloud['confidence'])
    # The same read as sensor_msgs_py.point_cloud2.read_points_numpy does it: every field one dtype.
    buf = np.frombuffer(bytes(msg.data), np.uint8).reshape(-1, msg.point_step)
    xyz = np.stack([buf[:, f.offset:f.offset + 4].copy().view('<f4')[:, 0] for f in msg.fields[:3]], axis=1)
    assert np.abs(xyz - np.column_stack([cloud['x'], cloud['y'], cloud['z']])).max() <= 0.5e-3


def test_fusion_of_float32_clouds_matches_float64(two_pair_clouds):
    """The map fuses the published (float32) clouds as it fused the float64 ones: a point within 0.06 mm
    (float32's rounding 1.5 km out) of a cell border may change cells, nothing else changes."""
    from photogram_ros.core.fusion import Fusion, FusionConfig
    a, b = Fusion(FusionConfig(0.08, 256)), Fusion(FusionConfig(0.08, 256))
    for c in two_pair_clouds:
        a.add(c)
        b.add(msgs.points_from_pointcloud2(msgs.dense_cloud_msg(c, 1)))
    pa, pb = a.points(), b.points()
    cells_a = pa['ix'].astype(np.int64) * 2**32 + pa['iy']
    cells_b = pb['ix'].astype(np.int64) * 2**32 + pb['iy']
    common, ia, ib = np.intersect1d(cells_a, cells_b, return_indices=True)
    assert cells_a.size > 100_000 and common.size >= 0.9999 * max(cells_a.size, cells_b.size)
    same = pa['n'][ia] == pb['n'][ib]
    dz = np.abs(pa['z'][ia] - pb['z'][ib])
    assert same.mean() >= 0.995                     # measured 99.78 %: the rest got or lost a border point
    assert dz[same].max() < 1e-4                    # the same points: the same height
    assert dz.mean() < 1e-4 and np.median(dz) == 0  # measured mean 0.009 mm


@pytest.fixture(scope='module')
def two_pair_clouds():
    """Stereo clouds of a simulated flight 1.5 km from the map origin (the tiny world, shifted east)."""
    from helpers.sim_world import rendered, world

    from photogram_ros.core import stereo
    cfg, _, _, _, _ = world('tiny')
    frames = rendered((2.0, 3.75, 5.5))
    out = []
    for (_, Ta, ia), (_, Tb, ib) in zip(frames, frames[1:]):
        Ta, Tb = Ta.copy(), Tb.copy()
        Ta[0, 3] += 1500.0
        Tb[0, 3] += 1500.0
        h = Tb[2, 3]   # the tiny world's ground is near z = 0
        r = stereo.stereo_pair(cfg.camera(), ia, Ta, ib, Tb, stereo.StereoParams(downscale=1.0, fill_holes_m=0.0, edge_step_m=1.0),
                                (0.6 * h, 1.4 * h))   # full resolution: > 100k points a pair
        assert r.ok, r.message
        out.append(r.cloud)
    return out


def _stamps_of_replay(bag, out, context) -> dict:
    """Run a replay of `bag`, listening on /diagnostics, map/cloud_downsampled and map/ortho_tiles:
    topic -> the header stamps (ns) seen."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CompressedImage, PointCloud2

    from photogram_ros.nodes.replay_session import ReplayOptions, run_replay
    seen = {'/diagnostics': [], '/map/cloud_downsampled': [], '/map/ortho_tiles': []}
    node = Node('stamp_listener', context=context)
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)

    def keep(topic):
        return lambda m: seen[topic].append(msgs.ns_from_time(m.header.stamp))
    node.create_subscription(DiagnosticArray, '/diagnostics', keep('/diagnostics'), 100)
    node.create_subscription(PointCloud2, '/map/cloud_downsampled', keep('/map/cloud_downsampled'), qos)
    node.create_subscription(CompressedImage, '/map/ortho_tiles', keep('/map/ortho_tiles'), qos)
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    stop = threading.Event()
    spin = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.05) for _ in iter(stop.is_set, True)],
                            daemon=True)
    spin.start()
    try:
        run_replay(ReplayOptions(bag=str(bag), out=str(out), progress=False, quiet_s=0.5), context=context)
        time.sleep(0.5)
    finally:
        stop.set()
        spin.join(timeout=5)
        node.destroy_node()
    return seen


def test_replay_stamps_diagnostics_and_map_streams_with_bag_time(tiny_flight, tmp_path, rclpy_context):
    from photogram_ros.io.bag import BagReader
    with BagReader(tiny_flight) as r:
        start, end = r.start_ns, r.start_ns + r.duration_ns
    seen = _stamps_of_replay(tiny_flight, tmp_path / 'out', rclpy_context)
    span = f'bag {start * 1e-9:.3f}..{end * 1e-9:.3f} s, wall clock now {time.time():.3f} s'
    wrong = []
    for topic in ('/diagnostics', '/map/cloud_downsampled', '/map/ortho_tiles'):
        stamps = np.array(seen[topic], dtype=np.int64)
        outside = stamps[(stamps < start) | (stamps > end)]
        if not stamps.size or outside.size:
            wrong.append(f'{topic}: {outside.size} of {stamps.size} stamps outside the bag'
                         + (f', {outside.min() * 1e-9:.3f}..{outside.max() * 1e-9:.3f} s' if outside.size else ''))
    assert not wrong, '; '.join(wrong) + f' ({span})'


def test_remapped_image_topic_moves_its_compressed_sibling(rclpy_context):
    import cv2
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CompressedImage

    from photogram_ros.nodes.tracker_node import TrackerNode
    tracker = TrackerNode(context=rclpy_context, cli_args=['--ros-args', '-r', 'camera/image_raw:=/cam0/image'])
    topics = {s.topic_name for s in tracker.subscriptions}
    assert {'/cam0/image', '/cam0/image/compressed'} <= topics, topics
    assert not {'/camera/image_raw', '/camera/image_raw/compressed'} & topics, topics
    peer = Node('cam0_driver', context=rclpy_context)
    pub = peer.create_publisher(CompressedImage, '/cam0/image/compressed',
                                QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE))
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(tracker)
    ex.add_node(peer)
    ok, jpg = cv2.imencode('.jpg', np.full((48, 64, 3), 128, np.uint8))
    msg = CompressedImage(header=msgs.header(5, 'camera_optical'), format='jpeg', data=jpg.tobytes())
    deadline = time.monotonic() + 10
    while tracker.diag.counts().get('frames_received', 0) == 0 and time.monotonic() < deadline:
        if pub.get_subscription_count():
            pub.publish(msg)
        ex.spin_once(timeout_sec=0.1)
    assert tracker.diag.counts().get('frames_received', 0) >= 1
    ex.shutdown()
    tracker.destroy_node()
    peer.destroy_node()


def test_compressed_sibling_keeps_its_own_remapping(rclpy_context):
    from photogram_ros.nodes.tracker_node import TrackerNode
    tracker = TrackerNode(context=rclpy_context, cli_args=[
        '--ros-args', '-r', 'camera/image_raw:=/cam0/image', '-r', 'camera/image_raw/compressed:=/cam0/jpeg'])
    topics = {s.topic_name for s in tracker.subscriptions}
    assert {'/cam0/image', '/cam0/jpeg'} <= topics, topics
    tracker.destroy_node()
