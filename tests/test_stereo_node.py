"""stereo_node over real rclpy topics: two posed keyframes in, one coloured PointCloud2 in `map` out."""
from __future__ import annotations

import time

import numpy as np
import pytest

from photogram_ros import msgs


@pytest.fixture(scope='module')
def two_keyframes():
    from helpers.sim_world import rendered, world
    cfg, _, terrain, _, _ = world('tiny')
    frames = [(1_780_000_000_000_000_000 + int(t * 1e9), T, img) for t, T, img in rendered((2.0, 3.75))]
    return cfg.camera(), terrain, frames, cfg


def _spin_until(executor, cond, timeout_s):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not cond():
        executor.spin_once(timeout_sec=0.05)
    return cond()


def test_two_keyframes_make_a_cloud(rclpy_context, two_keyframes):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
    from stereo_msgs.msg import DisparityImage

    from photogram_ros.nodes.stereo_node import StereoNode

    cam, terrain, frames, cfg = two_keyframes
    node = StereoNode({'publish_disparity': True, 'ground_from_sparse_cloud': False, 'settle_keyframes': 0},
                      context=rclpy_context)
    peer = Node('stereo_test_peer', context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(peer)
    clouds, disps, diags = [], [], []
    reliable = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)
    peer.create_subscription(PointCloud2, '/map/dense_cloud', clouds.append, reliable)
    peer.create_subscription(DisparityImage, '/stereo/disparity', disps.append, 5)
    peer.create_subscription(DiagnosticArray, '/diagnostics', diags.append, 10)
    pub_img = peer.create_publisher(Image, '/keyframes/image', reliable)
    pub_pose = peer.create_publisher(PoseWithCovarianceStamped, '/map/keyframe_pose', reliable)
    pub_info = peer.create_publisher(CameraInfo, '/camera/camera_info', 10)
    try:
        assert _spin_until(ex, lambda: pub_img.get_subscription_count() and pub_pose.get_subscription_count()
                           and pub_info.get_subscription_count(), 10.0)
        pub_info.publish(msgs.camera_info_msg(cam, frames[0][0]))
        # A malformed pose first: the node must report it and go on.
        bad = msgs.pose_with_covariance_from_T(np.eye(4), frames[0][0], 'odom')
        pub_pose.publish(bad)
        for stamp, T, img in frames:
            pub_img.publish(msgs.image_msg(img, stamp))
            cov = np.diag([0.02 ** 2] * 3 + [1e-4] * 3)
            pub_pose.publish(msgs.pose_with_covariance_from_T(T, stamp, 'map', cov))
        assert _spin_until(ex, lambda: clouds and disps, 30.0), node.diag.counts()
        assert _spin_until(ex, lambda: any(
            any(kv.key == 'pairs_done' for kv in s.values) for d in diags for s in d.status), 5.0)
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()
    msg = clouds[0]
    assert msg.header.frame_id == 'map'
    assert msg.header.stamp == msgs.time_from_ns(frames[1][0])
    assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'rgb', 'confidence']
    assert [f.datatype for f in msg.fields[:3]] == [PointField.FLOAT32] * 3   # what RViz2 draws
    pts = msgs.points_from_pointcloud2(msg)
    assert pts.size > 50_000
    dz = np.abs(pts['z'] - terrain.height_at(pts['x'], pts['y']))
    assert np.median(dz) <= cfg.gsd_m and np.percentile(dz, 90) <= 3 * cfg.gsd_m
    counts = node.diag.counts()
    assert counts['pairs_done'] == 1 and counts['problems'] >= 1
    d = disps[0]
    assert d.t == pytest.approx(np.linalg.norm(frames[1][1][:3, 3] - frames[0][1][:3, 3]), rel=1e-6)
    assert d.max_disparity > d.min_disparity > 0
