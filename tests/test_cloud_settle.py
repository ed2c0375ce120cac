"""stereo_node pairs a keyframe once its pose has settled (issue #43: the fused cloud within seconds of the
exposure): early when its last refinement barely moved it, when its pose stood still for settle_s (the flight's
end), at the latest after settle_keyframes newer poses; keyframes waiting for a pose are not the first evicted."""
from __future__ import annotations

import time

import numpy as np
import pytest

from photogram_ros import msgs


@pytest.fixture(scope='module')
def three_keyframes():
    from helpers.sim_world import rendered, world
    cfg = world('tiny')[0]
    frames = [(1_780_000_000_000_000_000 + int(t * 1e9), T, img) for t, T, img in rendered((2.0, 3.8, 5.6))]
    return cfg.camera(), frames


def _spin_until(executor, cond, timeout_s):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not cond():
        executor.spin_once(timeout_sec=0.05)
    return cond()


def _run(rclpy_context, frames, cam, params, steps, wait):
    """`steps`: ('image', i) / ('pose', i, dx_m) messages in turn; returns the node's counts once `wait(counts)`
    holds (or after 8 s)."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image

    from photogram_ros.nodes import qos
    from photogram_ros.nodes.stereo_node import StereoNode
    node = StereoNode({'ground_from_sparse_cloud': False, 'downscale': 0.5, 'fill_holes_m': 0.0, **params},
                      context=rclpy_context)
    peer = Node('stereo_settle_peer', context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(peer)
    pub_img = peer.create_publisher(Image, '/keyframes/image', qos.keyframes())
    pub_pose = peer.create_publisher(PoseWithCovarianceStamped, '/map/keyframe_pose', qos.keyframes())
    pub_info = peer.create_publisher(CameraInfo, '/camera/camera_info', qos.reliable())
    try:
        assert _spin_until(ex, lambda: pub_img.get_subscription_count() and pub_pose.get_subscription_count()
                           and pub_info.get_subscription_count(), 10.0)
        pub_info.publish(msgs.camera_info_msg(cam, frames[0][0]))
        _spin_until(ex, lambda: node.camera is not None, 5.0)
        cov = np.diag([0.02 ** 2] * 3 + [1e-6] * 3)
        for step in steps:
            stamp, T, img = frames[step[1]]
            if step[0] == 'image':
                pub_img.publish(msgs.image_msg(img, stamp))
            else:
                T = T.copy()
                T[0, 3] += step[2]
                pub_pose.publish(msgs.pose_with_covariance_from_T(T, stamp, 'map', cov))
            _spin_until(ex, lambda: False, 0.3)
        _spin_until(ex, lambda: wait(node.diag.counts()), 8.0)
        return node.diag.counts()
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()


ALL_POSED = [('image', 0), ('image', 1), ('image', 2), ('pose', 0, 0.0), ('pose', 1, 0.0), ('pose', 2, 0.0)]
LATE = {'settle_keyframes': 10, 'settle_min_keyframes': 2, 'settle_move_m': 0.05, 'settle_s': 0.0}


def test_a_refinement_that_barely_moves_the_pose_settles_it(rclpy_context, three_keyframes):
    cam, frames = three_keyframes
    counts = _run(rclpy_context, frames, cam, LATE, ALL_POSED + [('pose', 0, 0.01)],
                  lambda c: c.get('keyframes', 0) >= 1)
    assert counts.get('keyframes') == 1 and counts.get('keyframes_settled_early') == 1
    # A refinement that moved it by more than settle_move_m: it waits (for settle_keyframes newer poses).
    counts = _run(rclpy_context, frames, cam, LATE, ALL_POSED + [('pose', 0, 0.5)], lambda c: False)
    assert not counts.get('keyframes')


def test_a_pose_that_stands_still_pairs_at_the_flights_end(rclpy_context, three_keyframes):
    cam, frames = three_keyframes
    counts = _run(rclpy_context, frames, cam, {**LATE, 'settle_s': 0.5}, ALL_POSED,
                  lambda c: c.get('keyframes', 0) >= 3 and c.get('pairs_done', 0) >= 2)
    assert counts.get('keyframes') == 3 and counts.get('pairs_done', 0) >= 2
    assert counts.get('keyframes_settled_still', 0) >= 3


def test_a_keyframe_waiting_for_its_pose_outlives_paired_ones(rclpy_context, three_keyframes):
    """max_keyframes 2: keyframe 0's image waits for its pose while 1 and 2 come and pair; the paired 1 is
    evicted, not 0, which pairs when its pose comes."""
    cam, frames = three_keyframes
    steps = [('image', 0), ('image', 1), ('pose', 1, 0.0), ('image', 2), ('pose', 2, 0.0), ('pose', 0, 0.0)]
    counts = _run(rclpy_context, frames, cam, {'settle_keyframes': 0, 'max_keyframes': 2}, steps,
                  lambda c: c.get('keyframes', 0) >= 3)
    assert counts.get('keyframes') == 3 and not counts.get('keyframes_dropped_unpaired')
    assert counts.get('keyframes_dropped', 0) >= 1


def test_pairs_later_than_max_pair_lag_are_shed_and_said(rclpy_context, three_keyframes):
    cam, frames = three_keyframes
    poses_first = ALL_POSED[3:] + ALL_POSED[:3]   # each pair's turn comes 0.3 s or more after its final pose
    counts = _run(rclpy_context, frames, cam, {'settle_keyframes': 0, 'max_pair_lag_s': 0.1}, poses_first,
                  lambda c: c.get('keyframes', 0) >= 3)
    assert counts.get('keyframes') == 3 and counts.get('pairs_shed_late', 0) >= 2
    assert counts.get('keyframes_shed', 0) >= 2 and not counts.get('pairs_done')
