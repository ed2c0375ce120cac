"""Clouds fused on provisional poses follow the pose once it turns final, and only they keep a record
(issue #43, the pace: the first line's clouds no longer wait for the first turn). core/placements.py with
keep_final false and stages/map.py replace_provisional (the default, replace_move_m 0)."""
from __future__ import annotations

import numpy as np
from helpers.clouds import pair_cloud
from test_cloud2_map_replace import _flat, _pose, _spin_until, map_node_with_peer

from photogram_ros.core.placements import Placements
from photogram_ros.params import from_dict
from photogram_ros.stages.map import MapParams, MapStage
from photogram_ros.stages.report import DiagnosticsLog


class _Contribution:
    def __init__(self, nbytes):
        self.nbytes = nbytes
        self.median_z_m = 0.0


def _stage(tmp_path, **kw):
    p = from_dict(MapParams, {'map_dir': str(tmp_path / 'map'), 'cell_m': 0.1, 'use_origin_params': True,
                              'origin_lat_deg': 47.3977, 'origin_lon_deg': 8.5456, 'origin_h_m': 488.0,
                              'coverage': False, 'ortho': False, **kw})
    return MapStage(p, DiagnosticsLog())


def test_only_provisional_placements_keep_their_record_until_placed_final():
    pl = Placements(0.0, 10_000, keep_final=False)
    pl.placed_with(1, _pose(0, 0), False)
    assert not pl.wants_record(1)           # a final placement: fused without a record
    pl.fused(1, None)
    pl.placed_with(2, _pose(10, 0), True)
    assert pl.wants_record(2)
    pl.fused(2, _Contribution(400))
    assert pl.wants_record(3)               # placement not come yet: recorded, released if it comes final
    pl.fused(3, _Contribution(300))
    assert pl.nbytes == 700
    pl.placed_with(3, _pose(20, 0), False)
    assert pl.nbytes == 400
    # Final poses that moved: only the provisional placement is due (move_m 0: final ones never are).
    pl.pose(1, _pose(5, 0), False)
    pl.pose(2, _pose(10.01, 0), True)
    assert pl.due() == []                   # still provisional: nothing to do
    pl.pose(2, _pose(13, 0), False)
    assert pl.due() == [(2, 0)]
    pl.replaced(2, 0, _Contribution(420))
    assert pl.nbytes == 0 and pl.part(2, 0).contribution is None and not pl.part(2, 0).provisional
    pl.pose(2, _pose(16, 0), False)
    assert pl.due() == [] and pl.moved_not_replaced == 0
    assert pl.provisional_keyframes() == 0


def test_keep_final_keeps_every_record_and_follows_moves():
    pl = Placements(0.25, 10_000, keep_final=True)
    pl.placed_with(1, _pose(0, 0), False)
    assert pl.wants_record(1)
    pl.fused(1, _Contribution(100))
    pl.pose(1, _pose(1, 0), False)
    assert pl.due() == [(1, 0)] and pl.nbytes == 100


def test_the_map_places_a_provisional_cloud_again_by_default_and_keeps_no_record_of_final_ones(tmp_path):
    rng = np.random.default_rng(5)
    stage = _stage(tmp_path)
    assert stage.follows_poses
    stage.set_cloud_placement(1, _pose(0.0, 0.0), False)
    stage.add_cloud('map', 1, pair_cloud(rng, _flat, 0.0, 0.0, 6.0, 6.0, 150.0, 0.01))
    stage.set_cloud_placement(2, _pose(20.0, 0.0), True)
    stage.add_cloud('map', 2, pair_cloud(rng, _flat, 20.0, 0.0, 6.0, 6.0, 150.0, 0.01, rgb=0xFF0000))
    stage.update_diag()
    assert stage.diag.values['keyframes_fused_provisional'] == 1
    assert stage.diag.values['replace_memory_mb'] > 0
    kept_mb = stage.placements.nbytes
    # A final keyframe's pose moving does not move its cloud (replace_move_m 0).
    stage.set_keyframe_pose(1, _pose(2.0, 0.0), False)
    assert stage.replace_moved() == 0
    stage.set_keyframe_pose(2, _pose(23.0, 0.0), False)
    assert stage.replace_moved() == 1
    after = stage.fusion.points()
    red = after['r'] > 200
    assert abs(np.mean(after['x'][red]) - 23.0) < 0.2
    stage.update_diag()
    assert stage.diag.values['keyframes_fused_provisional'] == 0
    assert stage.placements.nbytes == 0 < kept_mb
    assert stage.diag.values['clouds_moved_not_replaced'] == 0
    stage.close()


def test_without_replace_provisional_the_map_follows_no_pose(tmp_path):
    stage = _stage(tmp_path, replace_provisional=False)
    assert not stage.follows_poses and stage.placements is None


def test_map_node_by_default_places_a_provisional_cloud_again_and_leaves_a_final_one(rclpy_context, tmp_path):
    from photogram_ros import msgs
    from photogram_ros.core.pose_status import provisional_covariance
    from photogram_ros.nodes.stereo_node import StereoNodeParams

    assert StereoNodeParams().pair_provisional   # stereo sends clouds on provisional poses by default
    node, ex, pub_place, pub_cloud, pub_pose, peer = map_node_with_peer(rclpy_context, tmp_path)
    try:
        final_cov = np.diag([0.02 ** 2] * 3 + [1e-6] * 3)
        prov_cov = provisional_covariance(final_cov, (1.0, 0.0, 0.0))
        rng = np.random.default_rng(1)
        # Keyframe 3: fused final at x = 0; keyframe 7: fused provisional at x = 20.
        pub_place.publish(msgs.pose_with_covariance_from_T(_pose(0.0, 0.0), 3 * 10**9, 'map', final_cov))
        pub_cloud.publish(msgs.dense_cloud_msg(pair_cloud(rng, _flat, 0.0, 0.0, 5.0, 5.0, 150.0, 0.01),
                                               3 * 10**9, 'map'))
        pub_place.publish(msgs.pose_with_covariance_from_T(_pose(20.0, 0.0), 7 * 10**9, 'map', prov_cov))
        pub_cloud.publish(msgs.dense_cloud_msg(pair_cloud(rng, _flat, 20.0, 0.0, 5.0, 5.0, 150.0, 0.01),
                                               7 * 10**9, 'map'))
        assert _spin_until(ex, lambda: node.diag.counts().get('clouds', 0) == 2, 10.0)
        # Both poses come final and moved 2 m east: only the provisional cloud follows.
        pub_pose.publish(msgs.pose_with_covariance_from_T(_pose(2.0, 0.0), 3 * 10**9, 'map', final_cov))
        pub_pose.publish(msgs.pose_with_covariance_from_T(_pose(22.0, 0.0), 7 * 10**9, 'map', final_cov))
        assert _spin_until(ex, lambda: node.diag.counts().get('clouds_replaced', 0) == 1, 10.0)
        _spin_until(ex, lambda: False, 1.0)
        assert node.diag.counts().get('clouds_replaced', 0) == 1
        x = node.fusion.points()['x']
        assert abs(float(np.mean(x[x > 10])) - 22.0) < 0.1 and abs(float(np.mean(x[x < 10]))) < 0.1
    finally:
        ex.shutdown()
        peer.destroy_node()
        node.destroy_node()
