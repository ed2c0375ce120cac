"""The map's flush beside its fusion: a cloud is fused while the flush makes the cells durable (fsync), both in
the stage (the sync runs outside its lock) and in the node (flush_beside_fusion: the flush timer in a callback group
of its own, so the multi-threaded executor runs a cloud's callback meanwhile)."""

import threading

import numpy as np
import pytest
from helpers.clouds import pair_cloud

from photogram_ros.params import from_dict
from photogram_ros.stages.map import MapParams, MapStage
from photogram_ros.stages.report import DiagnosticsLog

ORIGIN = dict(use_origin_params=True, origin_lat_deg=47.3977, origin_lon_deg=8.5456, origin_h_m=488.0)


def surface(x, y):
    return 3.0 + 0.05 * x - 0.02 * y


def test_a_cloud_is_fused_while_the_flush_syncs(tmp_path):
    stage = MapStage(from_dict(MapParams, {'map_dir': str(tmp_path / 'map'), 'cell_m': 0.08, **ORIGIN}),
                     DiagnosticsLog())
    rng = np.random.default_rng(3)
    stage.add_cloud('map', 1, pair_cloud(rng, surface, 0.0, 0.0, 6.0, 4.0, 150.0))
    in_sync, release = threading.Event(), threading.Event()
    sync = stage.store.sync

    def slow_sync():
        in_sync.set()
        assert release.wait(10.0)
        sync()

    stage.store.sync = slow_sync
    flusher = threading.Thread(target=stage.flush)
    flusher.start()
    try:
        assert in_sync.wait(10.0)
        fused = threading.Thread(target=stage.add_cloud,
                                 args=('map', 2, pair_cloud(rng, surface, 20.0, 0.0, 6.0, 4.0, 150.0)))
        fused.start()
        fused.join(5.0)
        assert not fused.is_alive()      # not held by the fsync
        assert stage.diag.counts()['clouds'] == 2
    finally:
        release.set()
        flusher.join(10.0)
    stage.store.sync = sync
    stage.close()


def _called(timer):
    """What a timer calls: the function nodes/diagnostics.steady_timer keeps to its share (its `callback`)."""
    import inspect
    return inspect.getclosurevars(timer.callback).nonlocals.get('callback', timer.callback)


@pytest.mark.ros
@pytest.mark.parametrize('beside', [True, False])
def test_the_flush_timer_has_a_callback_group_of_its_own(rclpy_context, tmp_path, beside):
    from photogram_ros.nodes.map_node import MapNode
    node = MapNode({'map_dir': str(tmp_path / 'map'), 'cell_m': 0.08, 'flush_beside_fusion': beside, **ORIGIN},
                   context=rclpy_context)
    try:
        flush = [t for t in node.timers if _called(t) == node.flush]
        cloud = [s for s in node.subscriptions if s.topic_name.endswith('map/dense_cloud')]
        assert len(flush) == 1 and len(cloud) == 1
        assert (flush[0].callback_group is not cloud[0].callback_group) == beside
        others = {t.callback_group for t in node.timers
                  if getattr(_called(t), '__self__', None) is node and _called(t) != node.flush}
        assert len(others) == 1 and others == {cloud[0].callback_group}   # the map's other timers: its one group
    finally:
        node.destroy_node()
