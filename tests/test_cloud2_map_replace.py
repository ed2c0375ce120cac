"""The map follows a keyframe's pose (issue #43): a pair cloud fused with a provisional pose is said provisional
and placed again when the pose turns final or moves by replace_move_m (stages/map.py replace_moved); one whose
record was dropped for memory is counted and said, not silently kept. And stereo_node pairs keyframes on
provisional poses, each cloud preceded by its placement (map/dense_cloud_pose), labelled provisional."""
from __future__ import annotations

import numpy as np
from helpers.clouds import pair_cloud

from photogram_ros.params import from_dict
from photogram_ros.stages.map import MapParams, MapStage
from photogram_ros.stages.report import DiagnosticsLog


def _spin_until(executor, cond, timeout_s):
    import time
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not cond():
        executor.spin_once(timeout_sec=0.05)
    return cond()


def _flat(x, y):
    return 2.0 + 0.0 * x


def _stage(tmp_path, **kw):
    p = from_dict(MapParams, {'map_dir': str(tmp_path / 'map'), 'cell_m': 0.1, 'use_origin_params': True,
                              'origin_lat_deg': 47.3977, 'origin_lon_deg': 8.5456, 'origin_h_m': 488.0,
                              'coverage': False, 'ortho': False, 'replace_move_m': 0.25, **kw})
    return MapStage(p, DiagnosticsLog())


def _pose(x, y, z=40.0):
    T = np.diag([1.0, -1.0, -1.0, 1.0])   # nadir
    T[:3, 3] = x, y, z
    return T


def test_a_cloud_fused_with_a_provisional_pose_is_placed_again_when_the_pose_turns_final(tmp_path):
    rng = np.random.default_rng(2)
    stage = _stage(tmp_path)
    other = pair_cloud(rng, _flat, 0.0, 0.0, 6.0, 6.0, 150.0, 0.01)
    stage.set_cloud_placement(1, _pose(0.0, 0.0), False)
    stage.add_cloud('map', 1, other)
    cloud = pair_cloud(rng, _flat, 20.0, 0.0, 6.0, 6.0, 150.0, 0.01, rgb=0xFF0000)
    stage.set_cloud_placement(2, _pose(20.0, 0.0), True)     # placed with a provisional pose
    stage.add_cloud('map', 2, cloud)
    stage.update_diag()
    assert stage.diag.values['keyframes_fused_provisional'] == 1
    before = stage.fusion.points()
    red = before['r'] > 200
    assert abs(np.mean(before['x'][red]) - 20.0) < 0.2

    # A provisional refinement smaller than replace_move_m: nothing moves.
    stage.set_keyframe_pose(2, _pose(20.02, 0.0), True)
    assert stage.replace_moved() == 0
    # The final pose, 3 m east of the provisional one: the cloud leaves its old cells and lands 3 m east.
    stage.set_keyframe_pose(2, _pose(23.0, 0.0), False)
    stage.set_keyframe_pose(1, _pose(0.0, 0.0), False)       # the other keyframe did not move: stays
    assert stage.replace_moved() == 1
    after = stage.fusion.points()
    red = after['r'] > 200
    assert abs(np.mean(after['x'][red]) - 23.0) < 0.2 and after['x'][red].min() > 16.5
    # Cells only the old placement covered are empty now; the other keyframe's cells are as they were.
    assert not np.any((after['x'] > 14.5) & (after['x'] < 16.5))
    keep = before['x'] < 7.0
    assert np.array_equal(np.sort(after['z'][after['x'] < 7.0]), np.sort(before['z'][keep]))
    stage.update_diag()
    assert stage.diag.values['keyframes_fused_provisional'] == 0
    assert stage.diag.counts()['clouds_replaced'] == 1
    assert stage.replace_moved() == 0                       # placed where its pose is: nothing more to do
    stage.close()


def test_placing_again_keeps_to_its_cpu_share_in_flight_and_finishes_at_the_end(tmp_path):
    rng = np.random.default_rng(8)
    stage = _stage(tmp_path, replace_cpu_share=0.001)
    for k in range(3):
        stage.set_cloud_placement(k, _pose(12.0 * k, 0.0), True)
        stage.add_cloud('map', k, pair_cloud(rng, _flat, 12.0 * k, 0.0, 5.0, 5.0, 150.0, 0.01))
    for k in range(3):
        stage.set_keyframe_pose(k, _pose(12.0 * k + 1.0, 0.0), False)
    assert stage.replace_moved(budget_s=10.0) == 1            # the share is spent by the first one
    assert stage.diag.counts()['replace_rounds_deferred'] == 1
    assert stage.replace_moved() == 2                          # the end (close) places every one left
    stage.update_diag()
    assert stage.diag.values['keyframes_fused_provisional'] == 0


def test_a_move_that_cannot_be_followed_is_counted_and_said(tmp_path):
    rng = np.random.default_rng(4)
    stage = _stage(tmp_path, replace_memory_mb=0.0)          # nothing kept to place again
    stage.set_cloud_placement(5, _pose(0.0, 0.0), False)
    stage.add_cloud('map', 5, pair_cloud(rng, _flat, 0.0, 0.0, 5.0, 5.0, 100.0, 0.01))
    stage.set_keyframe_pose(5, _pose(1.0, 0.0), False)
    assert stage.replace_moved() == 0
    stage.update_diag()
    assert stage.diag.values['clouds_moved_not_replaced'] == 1
    assert any('clouds_moved_not_replaced' in text for _, text in stage.diag.problems)


def test_the_cell_follows_the_gsd_from_provisional_poses_before_the_first_final_one(tmp_path):
    from photogram_ros.core.camera import PinholeCamera
    rng = np.random.default_rng(6)
    stage = _stage(tmp_path, cell_m=-1.0)
    stage.set_camera(PinholeCamera(5472, 3648, 4666.0, 4666.0, 2736.0, 1824.0))
    stage.set_keyframe_pose(3, _pose(0.0, 0.0, 82.0), True)
    stage.set_cloud_placement(3, _pose(0.0, 0.0, 82.0), True)
    stage.add_cloud('map', 3, pair_cloud(rng, _flat, 0.0, 0.0, 5.0, 5.0, 50.0, 0.01))
    assert not stage.diag.problems
    assert stage.gsd is not None and abs(stage.gsd.flying_height_m - 80.0) < 0.5


def test_stereo_pairs_provisional_poses_and_says_the_placement(rclpy_context):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from helpers.sim_world import rendered, world
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2

    from photogram_ros import msgs
    from photogram_ros.core.pose_status import provisional_covariance
    from photogram_ros.nodes import qos
    from photogram_ros.nodes.stereo_node import StereoNode

    cfg = world('tiny')[0]
    cam = cfg.camera()
    frames = [(1_780_000_000_000_000_000 + int(t * 1e9), T, img) for t, T, img in rendered((2.0, 3.8, 5.6))]
    node = StereoNode({'ground_from_sparse_cloud': False, 'downscale': 0.5, 'fill_holes_m': 0.0,
                       'settle_keyframes': 0, 'pair_provisional': True}, context=rclpy_context)
    peer = Node('cloud2_peer', context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(peer)
    got = []
    peer.create_subscription(PoseWithCovarianceStamped, '/map/dense_cloud_pose',
                             lambda m: got.append(('pose', msgs.ns_from_time(m.header.stamp),
                                                   msgs.pose_is_provisional(m))), qos.reliable(20))
    peer.create_subscription(PointCloud2, '/map/dense_cloud',
                             lambda m: got.append(('cloud', msgs.ns_from_time(m.header.stamp), None)),
                             qos.reliable(20))
    pub_img = peer.create_publisher(Image, '/keyframes/image', qos.keyframes())
    pub_pose = peer.create_publisher(PoseWithCovarianceStamped, '/map/keyframe_pose', qos.keyframes())
    pub_info = peer.create_publisher(CameraInfo, '/camera/camera_info', qos.reliable())

    def spin(cond, timeout_s):
        return _spin_until(ex, cond, timeout_s)
    try:
        assert spin(lambda: pub_img.get_subscription_count() and pub_pose.get_subscription_count()
                    and pub_info.get_subscription_count(), 10.0)
        pub_info.publish(msgs.camera_info_msg(cam, frames[0][0]))
        spin(lambda: node.camera is not None, 5.0)
        cov = provisional_covariance(np.diag([0.02 ** 2] * 3 + [1e-6] * 3), (1.0, 0.0, 0.0))
        for stamp, T, img in frames:
            pub_img.publish(msgs.image_msg(img, stamp))
            pub_pose.publish(msgs.pose_with_covariance_from_T(T, stamp, 'map', cov))
            spin(lambda: False, 0.3)
        assert spin(lambda: sum(k == 'cloud' for k, _, _ in got) >= 2, 10.0)
        counts = node.diag.counts()
        assert counts.get('keyframes_paired_provisional', 0) >= 2 and counts.get('pairs_done', 0) >= 2
        assert not counts.get('poses_provisional_held')
        # Each cloud comes after its placement, for the same keyframe, said provisional.
        for i, (kind, stamp, _) in enumerate(got):
            if kind == 'cloud':
                placements = [g for g in got[:i] if g[0] == 'pose' and g[1] == stamp]
                assert placements and all(prov for _, _, prov in placements)
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()


def map_node_with_peer(rclpy_context, tmp_path, **params):
    """A map node (cell 0.1 m, no ortho, coverage or keyframes) and a peer publishing to it: (node, executor,
    publishers of map/dense_cloud_pose, map/dense_cloud, map/keyframe_pose, peer), once they are linked."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from photogram_ros.nodes.map_node import MapNode

    node = MapNode({'map_dir': str(tmp_path / 'map'), 'cell_m': 0.1, 'use_origin_params': True,
                    'origin_lat_deg': 47.3977, 'origin_lon_deg': 8.5456, 'origin_h_m': 488.0, 'ortho': False,
                    'coverage': False, 'save_keyframes': False, **params}, context=rclpy_context)
    peer = Node('cloud2_map_peer', context=rclpy_context)
    reliable = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1, reliability=ReliabilityPolicy.RELIABLE)
    pubs = (peer.create_publisher(PoseWithCovarianceStamped, '/map/dense_cloud_pose', reliable),
            peer.create_publisher(PointCloud2, '/map/dense_cloud', reliable),
            peer.create_publisher(PoseWithCovarianceStamped, '/map/keyframe_pose', reliable))
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(peer)
    assert _spin_until(ex, lambda: all(p.get_subscription_count() for p in pubs), 10.0)
    return node, ex, *pubs, peer


def test_map_node_places_a_cloud_again_when_its_provisional_pose_turns_final(rclpy_context, tmp_path):
    from photogram_ros import msgs
    from photogram_ros.core.pose_status import provisional_covariance

    node, ex, pub_place, pub_cloud, pub_pose, peer = map_node_with_peer(rclpy_context, tmp_path, replace_move_m=0.25)

    def spin(cond, timeout_s):
        return _spin_until(ex, cond, timeout_s)
    try:
        final_cov = np.diag([0.02 ** 2] * 3 + [1e-6] * 3)
        prov_cov = provisional_covariance(final_cov, (1.0, 0.0, 0.0))
        stamp = 7 * 10**9
        cloud = pair_cloud(np.random.default_rng(1), _flat, 20.0, 0.0, 5.0, 5.0, 150.0, 0.01)
        pub_place.publish(msgs.pose_with_covariance_from_T(_pose(20.0, 0.0), stamp, 'map', prov_cov))
        pub_cloud.publish(msgs.dense_cloud_msg(cloud, stamp, 'map'))
        assert spin(lambda: node.diag.counts().get('clouds', 0) == 1, 10.0)
        x0 = float(np.mean(node.fusion.points()['x']))
        pub_pose.publish(msgs.pose_with_covariance_from_T(_pose(22.0, 1.0), stamp, 'map', final_cov))
        assert spin(lambda: node.diag.counts().get('clouds_replaced', 0) == 1, 10.0)
        pts = node.fusion.points()
        assert abs(float(np.mean(pts['x'])) - x0 - 2.0) < 0.05 and abs(float(np.mean(pts['y'])) - 1.0) < 0.1
    finally:
        ex.shutdown()
        peer.destroy_node()
        node.destroy_node()
