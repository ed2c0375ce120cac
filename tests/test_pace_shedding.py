"""The pace on a small computer (core/pace.py): the CPU share stereo and the ortho tiles keep to, stereo shedding
what is over it (counted, said), reduced keyframe images and a niced pairing worker in stereo_node, and the
companion profile's parameters."""

from __future__ import annotations

import threading

import cv2
import numpy as np
import pytest

from photogram_ros.core.pace import CpuShare, limit_threads, nice_this_thread
from photogram_ros.errors import ConfigError
from test_stereo_node import _run_three, three_keyframes  # noqa: F401  (three_keyframes: the fixture)


def test_cpu_share_counts_the_work_in_its_window():
    now = [100.0]
    share = CpuShare(0.4, window_s=10.0, clock=lambda: now[0])
    assert not share.over()
    now[0] = 110.0
    share.add(3.0)                  # 3 CPU s in the last 10 s: 0.3 of a core
    assert share.used() == pytest.approx(0.3) and not share.over()
    share.add(2.0)
    assert share.over()             # 0.5 > 0.4
    now[0] = 121.0                  # both out of the window
    assert share.used() == 0.0 and not share.over()
    assert not CpuShare(0.0).over(now=1e9)   # 0: no limit
    with pytest.raises(ConfigError):
        CpuShare(-1.0)


def test_measure_counts_the_threads_cpu_time():
    share = CpuShare(1.0, window_s=1000.0)
    with share.measure():
        x = np.random.default_rng(0).random((300, 300))
        for _ in range(20):
            x = x @ x.T / 300.0
    assert share.used() > 0


def test_nice_applies_to_the_calling_thread_only():
    import os
    main = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    seen = []
    t = threading.Thread(target=lambda: seen.append(nice_this_thread(5)))
    t.start()
    t.join()
    assert seen == [min(main + 5, 19)]
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == main
    with pytest.raises(ConfigError):
        nice_this_thread(-1)


def test_limit_threads_caps_opencv():
    before = cv2.getNumThreads()
    try:
        assert limit_threads(cv_threads=1)['cv_threads'] == 1
        assert limit_threads() == {}
    finally:
        cv2.setNumThreads(before)


def test_companion_profile_is_read_by_every_node():
    from conftest import ROOT
    from photogram_ros.nodes.bundle_node import BundleNodeParams
    from photogram_ros.nodes.map_node import MapParams
    from photogram_ros.nodes.stereo_node import StereoNodeParams
    from photogram_ros.nodes.tracker_node import TrackerNodeParams
    from photogram_ros.params import from_dict, load_params_file
    sections = load_params_file(str(ROOT / 'config' / 'companion.yaml'))
    got = {node: from_dict(cls, sections[node], node) for node, cls in (
        ('tracker_node', TrackerNodeParams), ('bundle_node', BundleNodeParams), ('stereo_node', StereoNodeParams),
        ('map_node', MapParams))}
    assert got['stereo_node'].cpu_share > 0 and got['stereo_node'].worker_nice > 0
    assert got['map_node'].ortho_cpu_share > 0 and got['tracker_node'].cv_threads > 0


def test_stereo_over_its_share_sheds_pairs_and_says_so(rclpy_context, three_keyframes):  # noqa: F811
    cam, frames = three_keyframes
    params = {'downscale': 0.5, 'fill_holes_m': 0.0}
    whole, _ = _run_three(rclpy_context, frames, cam, params, 0.05)
    assert whole.get('pairs_done', 0) >= 2 and not whole.get('keyframes_shed')
    # A share no pair fits in: after the first pair, the next keyframe's pairs are shed (it stays a partner).
    shed, node = _run_three(rclpy_context, frames, cam, {**params, 'cpu_share': 1e-4}, 0.05)
    assert shed.get('pairs_done', 0) >= 1 and shed.get('keyframes_shed', 0) >= 1
    assert shed['pairs_done'] < whole['pairs_done']
    assert any('shed' in t and 'export --densify' in t for t in node.diag.recent_problems(10))


def test_stereo_pairs_reduced_images_in_a_niced_worker(rclpy_context, three_keyframes):  # noqa: F811
    """Keyframe images at half size (camera_info at full size), paired in a worker thread: the same pairs."""
    cam, frames = three_keyframes
    half = [(s, T, cv2.resize(img, (cam.width // 2, cam.height // 2), interpolation=cv2.INTER_AREA))
            for s, T, img in frames]
    _, node = _run_three(rclpy_context, half, cam, {'worker_nice': 5}, 0.05)
    counts = node.diag.counts()   # after destroy_node joined the worker (the counts _run_three saw may be short)
    assert counts.get('pairs_done', 0) >= 2 and not counts.get('pairs_failed')
    assert node.gsd.downscale == 0.5 and node.gsd.width_px == cam.width   # the full camera's GSD settings
    values = {kv.key: kv.value for kv in node.diag.status().values}
    assert int(values['worker_nice']) >= 5


def test_ortho_batches_over_their_share_wait_for_a_later_period(tmp_path):
    from photogram_ros.core.stereo import CLOUD_DTYPE
    from photogram_ros.params import from_dict
    from photogram_ros.stages.map import MapOutputs, MapParams, MapStage

    class Tiles(MapOutputs):
        def __init__(self):
            self.tiles = []

        def ortho_tile(self, z, x, y, png, stamp_ns):
            self.tiles.append((z, x, y))

    def stage(share):
        out = Tiles()
        st = MapStage(from_dict(MapParams, {
            'map_dir': str(tmp_path / f'map{share}'), 'use_origin_params': True, 'origin_lat_deg': 39.86,
            'origin_lon_deg': -4.02, 'origin_h_m': 500.0, 'coverage': False, 'cell_m': 0.17, 'ortho_max_tiles': 2,
            'ortho_cpu_share': share}), out=out)
        rng = np.random.default_rng(0)
        c = np.zeros(100_000, CLOUD_DTYPE)
        c['x'], c['y'] = rng.uniform(0, 120, c.size), rng.uniform(0, 80, c.size)
        c['rgb'], c['confidence'] = rng.integers(0, 2 ** 24, c.size), 1.0
        st.add_cloud('map', 1, c)
        return st, out
    free, free_out = stage(0.0)
    free.stream_ortho(True)
    free.stream_ortho(True)
    capped, capped_out = stage(1e-6)
    capped.stream_ortho(True)      # the first batch goes out: nothing was spent yet
    capped.stream_ortho(True)      # over the share now: deferred, the tiles still pending
    assert len(capped_out.tiles) < len(free_out.tiles) and capped_out.tiles
    assert capped.diag.counts()['ortho_batches_deferred'] == 1
    assert not free.diag.counts().get('ortho_batches_deferred')
    free.close()
    capped.close()
