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


CORE_LENGTHS = {'downscale': 1.0, 'fill_holes_m': 0.0, 'edge_step_m': 1.0, 'relief_m': 20.0, 'depth_margin_m': 4.0}


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
    # The matcher's own defaults (full resolution), not the GSD-derived ones: this tests the node's plumbing.
    node = StereoNode({'publish_disparity': True, 'ground_from_sparse_cloud': False, 'settle_keyframes': 0,
                       **CORE_LENGTHS}, context=rclpy_context)
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


def _run_three(rclpy_context, frames, cam, params, pose_sigma_m, fix_sigma_m=None):
    """Three keyframes through a stereo node with poses of `pose_sigma_m` (and keyframe fixes of
    `fix_sigma_m`, 3D): the node's counts once it has paired them."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image, NavSatFix
    from photogram_ros.nodes.stereo_node import StereoNode
    node = StereoNode({'ground_from_sparse_cloud': False, 'settle_keyframes': 0, **params}, context=rclpy_context)
    peer = Node('stereo_gate_peer', context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(peer)
    reliable = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)
    pub_img = peer.create_publisher(Image, '/keyframes/image', reliable)
    pub_pose = peer.create_publisher(PoseWithCovarianceStamped, '/map/keyframe_pose', reliable)
    pub_info = peer.create_publisher(CameraInfo, '/camera/camera_info', 10)
    pub_fix = peer.create_publisher(NavSatFix, '/keyframes/fix', reliable)
    try:
        assert _spin_until(ex, lambda: pub_img.get_subscription_count() and pub_pose.get_subscription_count()
                           and pub_info.get_subscription_count(), 10.0)
        pub_info.publish(msgs.camera_info_msg(cam, frames[0][0]))
        var = pose_sigma_m ** 2 / 3
        for stamp, T, img in frames:
            if fix_sigma_m is not None:
                v = fix_sigma_m ** 2 / 3
                pub_fix.publish(msgs.navsatfix_msg(stamp, 47.0, 8.0, 500.0, 0, [v, v, v], 2))
                _spin_until(ex, lambda: False, 0.2)
            pub_img.publish(msgs.image_msg(img, stamp))
            pub_pose.publish(msgs.pose_with_covariance_from_T(T, stamp, 'map', np.diag([var] * 3 + [1e-6] * 3)))
        _spin_until(ex, lambda: node.diag.counts().get('keyframes', 0) >= len(frames), 30.0)
        return node.diag.counts(), node
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()


@pytest.fixture(scope='module')
def three_keyframes():
    from helpers.sim_world import rendered, world
    cfg = world('tiny')[0]
    frames = [(1_780_000_000_000_000_000 + int(t * 1e9), T, img) for t, T, img in rendered((2.0, 3.8, 5.6))]
    return cfg.camera(), frames


def test_the_pose_gate_follows_the_fix_mode(rclpy_context, three_keyframes):
    # Poses of 3 m sigma (a plain 3D fix's): refused by the 2 m gate alone, paired when their fixes say
    # 3-4 m (3 x the fix sigma); an RTK flight (2 cm fixes) keeps the 2 m gate.
    cam, frames = three_keyframes
    params = {'downscale': 0.5, 'fill_holes_m': 0.0}
    refused, _ = _run_three(rclpy_context, frames, cam, params, 3.0)
    assert refused.get('pairs_skipped_poor_pose', 0) == 3 and refused.get('pairs_done', 0) == 0
    paired, node = _run_three(rclpy_context, frames, cam, params, 3.0, fix_sigma_m=3.7)
    assert paired.get('pairs_skipped_poor_pose', 0) == 0 and paired.get('pairs_done', 0) >= 2
    rtk, _ = _run_three(rclpy_context, frames, cam, params, 3.0, fix_sigma_m=0.03)
    assert rtk.get('pairs_skipped_poor_pose', 0) == 3


def test_lengths_left_to_the_gsd_are_stated_at_the_first_pair(rclpy_context, three_keyframes):
    cam, frames = three_keyframes
    counts, node = _run_three(rclpy_context, frames, cam, {}, 0.05)
    assert counts.get('pairs_done', 0) >= 2
    assert node.gsd is not None and node.gsd.downscale == 0.5 and node.gsd.relief_m == 25.0
    assert 30.0 < node.gsd.flying_height_m < 50.0
    values = node.diag.status().values
    stated = {kv.key: kv.value for kv in values}
    assert 'downscale 0.5' in stated['gsd_settings'] and 'relief_m 25' in stated['gsd_settings']


def test_keyframes_without_a_partner_are_counted(rclpy_context, three_keyframes):
    # An overlap no pair of the tiny world reaches: the second and third keyframes get no partner (counted),
    # the first has none before it; with the default overlap both pair.
    cam, frames = three_keyframes
    params = {'downscale': 0.5, 'fill_holes_m': 0.0}
    none, _ = _run_three(rclpy_context, frames, cam, {**params, 'min_overlap': 0.999}, 0.05)
    assert none.get('keyframes_no_partner', 0) == 2 and none.get('keyframes_no_earlier_partner', 0) == 1
    assert none.get('pairs_done', 0) == 0
    paired, _ = _run_three(rclpy_context, frames, cam, params, 0.05)
    assert paired.get('pairs_done', 0) >= 2 and not paired.get('keyframes_no_partner')
    assert paired.get('keyframes_no_earlier_partner', 0) == 1
