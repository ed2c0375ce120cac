"""tracker_node over real rclpy topics: the sample bag played in, keyframes + features + fixes out."""

from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np
import pytest

pytestmark = pytest.mark.ros


class Listener:
    def __init__(self, context):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image, NavSatFix, PointCloud2
        self.node = Node('kf_listener', context=context)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.images, self.features, self.fixes, self.diags = [], [], [], []
        self.node.create_subscription(Image, '/keyframes/image', self.images.append, qos)
        self.node.create_subscription(PointCloud2, '/keyframes/features', self.features.append, qos)
        self.node.create_subscription(NavSatFix, '/keyframes/fix', self.fixes.append, qos)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self.diags.append, 50)


def _spin(nodes, context):
    from rclpy.executors import MultiThreadedExecutor
    ex = MultiThreadedExecutor(num_threads=2, context=context)
    for n in nodes:
        ex.add_node(n)
    t = threading.Thread(target=ex.spin, daemon=True)
    t.start()
    return ex, t


def test_sample_bag_gives_keyframes_with_matching_stamps(sample_bag, rclpy_context):
    from photogram_ros.msgs import features_from_keyframe_msg, image_from_msg, ns_from_time
    from photogram_ros.nodes.player_node import PlayerNode
    from photogram_ros.nodes.tracker_node import TrackerNode
    from photogram_ros.sim.truth import GroundTruth

    # The flight's surveyed targets: searched in each keyframe only where they can be (target_search regions).
    tracker = TrackerNode(overrides={'reliable_input': True, 'queue_size': 100, 'input_depth': 100,
                                     'control_file': str(sample_bag / 'targets.txt')}, context=rclpy_context)
    listener = Listener(rclpy_context)
    player = PlayerNode(overrides={'bag': str(sample_bag), 'rate': 4.0, 'wait_for_subscribers': 3,
                                   'topics': '/camera/image_raw/compressed,/camera/camera_info,/gps/fix'},
                        context=rclpy_context)
    ex, thread = _spin([tracker, listener.node], rclpy_context)
    try:
        summary = player.play()
        assert summary.counts['/camera/image_raw/compressed'] == 76
        tracker.flush(timeout_s=20.0)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and (len(listener.features) < tracker.keyframes_published
                                               or len(listener.images) < tracker.keyframes_published):
            time.sleep(0.05)
        counts = tracker.diag.counts()
        s = tracker.tracker.stats
        print(f'{tracker.keyframes_published} keyframes from {s.frames} frames, {counts}, {s}')
        # 3 lines of ~90 m at 80 % overlap of a ~37 m footprint: a keyframe every ~7 m -> dozens.
        why = f'{tracker.keyframes_published} keyframes, {counts}, {s}'
        assert s.frames >= 70 and counts.get('drops', 0) == 0, why
        assert tracker.keyframes_published >= 20, why
        assert len(listener.images) == len(listener.features) == tracker.keyframes_published, \
            (len(listener.images), len(listener.features), why)
        img_stamps = [ns_from_time(m.header.stamp) for m in listener.images]
        feat_stamps = [ns_from_time(m.header.stamp) for m in listener.features]
        assert img_stamps == feat_stamps and img_stamps == sorted(img_stamps)
        truth = GroundTruth.load(sample_bag)
        assert all(truth.frame_by_stamp(t, tol_ns=0) is not None for t in img_stamps)
        fix_stamps = [ns_from_time(m.header.stamp) for m in listener.fixes]
        assert len(fix_stamps) >= 0.9 * len(img_stamps) and set(fix_stamps) <= set(img_stamps), \
            (len(fix_stamps), len(img_stamps), why)
        # Interpolated fix close to the true antenna position (RTK fixed: cm level).
        f0 = listener.fixes[len(listener.fixes) // 2]
        enu = truth.origin.geodetic_to_enu(f0.latitude, f0.longitude, f0.altitude)
        true_ant = truth.frame_by_stamp(ns_from_time(f0.header.stamp), tol_ns=0).antenna_enu
        assert np.linalg.norm(np.asarray(enu).ravel() - true_ant) < 0.2
        feats = features_from_keyframe_msg(listener.features[3])
        img = image_from_msg(listener.images[3])
        assert img.shape == (480, 640, 3) and len(feats) >= 100
        assert feats['u'].min() >= 0 and feats['u'].max() < 640 and feats['v'].max() < 480
        # Consecutive keyframes share tracks (the graph is connected along the flight).
        a, b = features_from_keyframe_msg(listener.features[3]), features_from_keyframe_msg(listener.features[4])
        assert len(np.intersect1d(a['track_id'], b['track_id'])) >= 30
        _check_target_rows(listener.features, truth, tracker)
    finally:
        ex.shutdown()
        player.destroy_node()
        tracker.destroy_node()
        listener.node.destroy_node()


def _check_target_rows(features, truth, tracker):
    """The ArUco targets ride in the features table (msgs.py's reserved ids) at their true projections."""
    from photogram_ros.core.rotations import invert_T, transform_points
    from photogram_ros.msgs import keyframe_table_from_msg, ns_from_time
    by_id = {t.marker_id: t for t in truth.targets}
    err, seen = [], set()
    for m in features:
        feats, targets = keyframe_table_from_msg(m)
        assert len(feats) + len(targets) == m.width and len(set(targets['marker_id'].tolist())) == len(targets)
        T = truth.frame_by_stamp(ns_from_time(m.header.stamp), tol_ns=0).map_T_cam
        for row in targets:
            t = by_id[int(row['marker_id'])]   # no marker the truth does not have
            uv, _ = truth.camera.project(transform_points(invert_T(T), t.center_enu[None]))
            err.append(np.hypot(row['u'] - uv[0, 0], row['v'] - uv[0, 1]))
            seen.add(t.name)
    err = np.array(err)
    ms = float({kv.key: kv.value for kv in tracker.diag.status().values}['target_detection_ms'])
    print(f'{len(err)} target detections of {len(seen)} targets in {len(features)} keyframes: centre error median '
          f'{np.median(err):.2f} px, max {err.max():.2f} px; last detection {ms:.1f} ms')
    assert len(seen) == len(truth.targets) and len(err) >= 2 * len(truth.targets)
    assert np.median(err) < 0.5 and err.max() < 1.5   # JPEG q85 and the renderer: 0.30 / 0.68 px measured
    assert tracker.diag.counts()['targets_detected'] == len(err)


def test_bad_calibration_is_a_diagnostics_error_and_node_survives(rclpy_context):
    from diagnostic_msgs.msg import DiagnosticStatus
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image

    from photogram_ros import msgs
    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.nodes.tracker_node import TrackerNode

    tracker = TrackerNode(overrides={'reliable_input': True, 'queue_size': 50}, context=rclpy_context)
    listener = Listener(rclpy_context)
    pub_img = listener.node.create_publisher(Image, '/camera/image_raw',
                                             QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
    pub_info = listener.node.create_publisher(CameraInfo, '/camera/camera_info', 10)
    ex, thread = _spin([tracker, listener.node], rclpy_context)
    try:
        rng = np.random.default_rng(1)
        img = (rng.random((120, 160, 3)) * 255).astype(np.uint8)
        deadline = time.monotonic() + 5
        while pub_img.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        def unused_reaches(n):
            end = time.monotonic() + 10
            while time.monotonic() < end and tracker.diag.counts().get('frames_unused', 0) < n:
                time.sleep(0.05)

        pub_img.publish(msgs.image_msg(img, 1_000_000_000))           # no camera_info yet
        unused_reaches(1)
        bad = CameraInfo(width=160, height=120, distortion_model='plumb_bob', d=[0.0] * 5,
                         k=[0.0, 0, 80, 0, 0.0, 60, 0, 0, 1])          # fx = 0: never filled in
        pub_info.publish(bad)
        time.sleep(0.3)
        pub_img.publish(msgs.image_msg(img, 2_000_000_000))
        unused_reaches(2)
        good = msgs.camera_info_msg(PinholeCamera(320, 240, 260, 260, 160, 120), 0)   # wrong image size
        pub_info.publish(good)
        time.sleep(0.3)
        pub_img.publish(msgs.image_msg(img, 3_000_000_000))
        unused_reaches(3)
        counts = tracker.diag.counts()
        assert counts.get('frames_unused', 0) == 3 and tracker.keyframes_published == 0
        messages = [p[1] for p in tracker.diag._problems]
        assert any('no camera_info' in m for m in messages)
        assert any('focal length' in m for m in messages)
        assert any('calibration is for 320x240' in m for m in messages)
        time.sleep(1.2)
        status = [s for d in listener.diags for s in d.status if s.name.endswith('tracker_node')]
        assert status and max(s.level for s in status) == DiagnosticStatus.ERROR
        # A good calibration for this size: the same node now tracks.
        pub_info.publish(msgs.camera_info_msg(PinholeCamera(160, 120, 130, 130, 80, 60), 0))
        time.sleep(0.3)
        pub_img.publish(msgs.image_msg(img, 4_000_000_000))
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and tracker.diag.counts().get('frames_tracked', 0) < 1:
            time.sleep(0.05)
        assert tracker.diag.counts().get('frames_tracked', 0) == 1
    finally:
        ex.shutdown()
        tracker.destroy_node()
        listener.node.destroy_node()


def _queue_frames(tracker, n: int) -> None:
    """`n` black frames 1 ms apart into `tracker`'s queue (call it holding tracker._track_lock: a busy tracker,
    nothing leaves the queue)."""
    from photogram_ros import msgs
    for k in range(n):
        tracker._on_image(msgs.image_msg(np.zeros((8, 8), np.uint8), (k + 1) * 1_000_000))


def queued_stamps(tracker) -> list[int]:
    from photogram_ros import msgs
    return [msgs.ns_from_time(m.header.stamp) for m in tracker._frames]


def test_frames_faster_than_the_tracker_are_dropped_oldest_first(rclpy_context):
    from photogram_ros.nodes.tracker_node import TrackerNode

    tracker = TrackerNode(overrides={'queue_size': 2}, context=rclpy_context)
    try:
        with tracker._track_lock:   # a busy tracker: nothing leaves the queue
            _queue_frames(tracker, 10)
            kept = queued_stamps(tracker)
        assert kept == [9_000_000, 10_000_000] and tracker.diag.counts()['drops'] == 8
        assert any("dropped: frames come faster than the tracker" in m and "without a GNSS position" in m
                   for _, m in tracker.diag._problems)
    finally:
        tracker.destroy_node()


def test_a_stopped_flight_drops_the_queued_frames_but_the_next_in_line(rclpy_context):
    """drop_queued(keep): the frames a stopped flight's budget cannot take go at once, the next `keep` stay."""
    from photogram_ros.nodes.tracker_node import TrackerNode

    tracker = TrackerNode(overrides={'queue_size': 10}, context=rclpy_context)
    try:
        with tracker._track_lock:   # a busy tracker: nothing leaves the queue
            _queue_frames(tracker, 6)
            assert tracker.drop_queued(keep=2) == 4
            kept = queued_stamps(tracker)
        assert kept == [1_000_000, 2_000_000]
        assert tracker.drop_queued() == 2 and len(tracker._frames) == 0
    finally:
        tracker.destroy_node()


def test_photo_rate_frames_the_chain_needs_are_kept_and_redundant_ones_dropped_with_the_reason(rclpy_context):
    """The queue's drop rule in the node (core/frame_queue.py, tests/test_tracker_frame_queue.py): photos 30 m apart
    with keyframes 30 m apart are all kept past queue_size 2; a burst of frames 1 m apart is dropped as redundant,
    said on /diagnostics."""
    from photogram_ros import msgs
    from photogram_ros.core.gnss_fix import GnssFix
    from photogram_ros.nodes.tracker_node import TrackerNode

    tracker = TrackerNode(overrides={'queue_size': 2}, context=rclpy_context)
    tracker.tracker.keyframe_spacing_m = lambda: 30.0
    m_per_deg = 6371008.8 * np.pi / 180.0
    try:
        with tracker._track_lock:   # a busy tracker: nothing leaves the queue
            for k in range(6):
                stamp = (k + 1) * 1_000_000_000
                tracker._on_fix(msgs.navsatfix_from_gnss_fix(
                    GnssFix(47.0 + 30.0 * k / m_per_deg, 8.0, 500.0, np.eye(3) * 0.01, stamp)))
                tracker._on_image(msgs.image_msg(np.zeros((8, 8), np.uint8), stamp))
            assert len(tracker._frames) == 6 and 'drops' not in tracker.diag.counts()
            for k in range(1, 5):   # then four frames 1 m apart past the last photo
                stamp = 6_000_000_000 + k * 100_000_000
                tracker._on_fix(msgs.navsatfix_from_gnss_fix(
                    GnssFix(47.0 + (150.0 + k) / m_per_deg, 8.0, 500.0, np.eye(3) * 0.01, stamp)))
                tracker._on_image(msgs.image_msg(np.zeros((8, 8), np.uint8), stamp))
            kept = [msgs.ns_from_time(m.header.stamp) for m in tracker._frames]
        counts = tracker.diag.counts()
        assert kept[:6] == [(k + 1) * 1_000_000_000 for k in range(6)], kept
        assert counts['drops'] == counts['drops_redundant'] == 3 and kept[-1] == 6_400_000_000, (kept, counts)
        assert any('dropped as redundant' in m for _, m in tracker.diag._problems)
    finally:
        tracker.destroy_node()


def test_the_node_keeps_each_fix_once_in_the_trackers_buffer(rclpy_context):
    """One store of the fixes: a NavSatFix goes into the tracker's buffer, which the drop rule reads too."""
    from photogram_ros.nodes.tracker_node import TrackerNode
    tracker = TrackerNode(context=rclpy_context)
    try:
        assert tracker.tracker.fixes is tracker._fixes
        tracker._on_fix(_fix_at(1_000_000_000))
        tracker._on_fix(_fix_at(2_000_000_000))
        assert len(tracker.tracker.fixes) == 2 and tracker._fixes.added == 2
        mid = tracker.tracker.fixes.at(1_500_000_000)
        assert mid is not None and mid.interpolated and mid.lat_deg == pytest.approx(47.0 + 1.5e-9, abs=1e-12)
        assert not [k for k, v in vars(tracker).items() if 'fix' in k and isinstance(v, (list, deque))]
    finally:
        tracker.destroy_node()


def _fix_at(stamp):
    """A NavSatFix at `stamp` (ns) whose latitude carries the stamp."""
    from photogram_ros import msgs
    from photogram_ros.core.gnss_fix import GnssFix
    return msgs.navsatfix_from_gnss_fix(GnssFix(47.0 + stamp * 1e-18, 8.0, 500.0, np.eye(3) * 0.01, stamp))


def _fed_tracker(rclpy_context, tmp_path, sim_s: float, depth: int, **overrides):
    """A tracker node on `sim_s` s of rendered frames (its calibration from a file, no targets), a Listener, and
    a feeder node's reliable image and fix publishers of history `depth`, all spinning once the tracker
    subscribes: (sim, tracker, listener, feeder, pub_img, pub_fix, executor)."""
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image, NavSatFix

    from photogram_ros.core.camera import save_opencv_yaml
    from photogram_ros.nodes.tracker_node import TrackerNode
    from test_tracker import SimFrames
    sim = SimFrames(sim_s)
    save_opencv_yaml(sim.camera, tmp_path / 'cam.yaml')
    tracker = TrackerNode(overrides={'calibration_file': str(tmp_path / 'cam.yaml'), 'reliable_input': True,
                                     'queue_size': 100, 'detect_targets': False, **overrides}, context=rclpy_context)
    listener = Listener(rclpy_context)
    feeder = Node('feeder', context=rclpy_context)
    qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
    pub_img = feeder.create_publisher(Image, 'camera/image_raw', qos)
    pub_fix = feeder.create_publisher(NavSatFix, 'gps/fix', qos)
    ex, _ = _spin([tracker, listener.node, feeder], rclpy_context)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and pub_img.get_subscription_count() == 0:
        time.sleep(0.05)
    return sim, tracker, listener, feeder, pub_img, pub_fix, ex


def test_flush_takes_the_fixes_that_came_after_the_last_frame(rclpy_context, tmp_path):
    """The last keyframe's fix arrives after its frame was tracked (a 1 Hz receiver): flush() at the end
    of the flight finds it in the tracker's fix buffer (the node's one store of fixes), so that keyframe gets its
    fix."""
    from photogram_ros import msgs
    sim, tracker, listener, feeder, pub_img, pub_fix, ex = _fed_tracker(rclpy_context, tmp_path, 2.0,
                                                                        depth=100)
    try:
        stamps = [s for s, _, _ in sim.frames]
        pub_fix.publish(_fix_at(stamps[0] - 10**8))
        for stamp, img, _ in sim.frames:
            pub_img.publish(msgs.image_msg(img, stamp))
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and tracker.frames_done < len(stamps):
            time.sleep(0.05)
        pub_fix.publish(_fix_at(stamps[-1] + 10**8))     # after the last frame was tracked
        time.sleep(0.5)
        tracker.flush(timeout_s=10.0)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and len(listener.features) < tracker.keyframes_published:
            time.sleep(0.05)
    finally:
        ex.shutdown()
    fix_stamps = {msgs.ns_from_time(m.header.stamp) for m in listener.fixes}
    kf_stamps = [msgs.ns_from_time(m.header.stamp) for m in listener.features]
    print(f'{len(kf_stamps)} keyframes, {len(fix_stamps)} with a fix')
    # (The first keyframe waited fix_wait_s for a later fix and went without: the tracker's rule.)
    assert len(kf_stamps) >= 2 and kf_stamps[-1] in fix_stamps
    tracker.destroy_node()
    listener.node.destroy_node()
    feeder.destroy_node()


def test_flush_waits_for_the_fixes_of_every_keyframe_still_waiting(rclpy_context, tmp_path):
    """At the end of a replay the fix stream trails the keyframes by several of them (an executor that
    delivers fixes late under load): flush() waits while it trails the newest keyframe still waiting and
    keeps coming, so every keyframe gets its fix, not only the oldest."""
    import threading

    from photogram_ros import msgs
    sim, tracker, listener, feeder, pub_img, pub_fix, ex = _fed_tracker(rclpy_context, tmp_path, 6.0, depth=200,
                                                                        input_depth=100, fix_wait_s=10.0)
    stamps = [s for s, _, _ in sim.frames]
    fix_stamps = list(range(stamps[0] - 10**8, stamps[-1] + 3 * 10**8, 2 * 10**8))   # 5 Hz
    try:
        pub_fix.publish(_fix_at(fix_stamps[0]))
        for stamp, img, _ in sim.frames:
            pub_img.publish(msgs.image_msg(img, stamp))
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and tracker.frames_done < len(stamps):
            time.sleep(0.05)
        flushing = threading.Thread(target=tracker.flush, kwargs={'timeout_s': 20.0})
        flushing.start()
        for stamp in fix_stamps[1:]:       # the rest trickles in while flush() waits
            time.sleep(0.1)
            pub_fix.publish(_fix_at(stamp))
        flushing.join(30.0)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and (len(listener.features) < tracker.keyframes_published
                                               or len(listener.fixes) < tracker.keyframes_published):
            time.sleep(0.05)
    finally:
        ex.shutdown()
    kf_stamps = [msgs.ns_from_time(m.header.stamp) for m in listener.features]
    with_fix = {msgs.ns_from_time(m.header.stamp) for m in listener.fixes}
    print(f'{len(kf_stamps)} keyframes, {len(with_fix)} with a fix, {tracker.diag.counts()}')
    assert not flushing.is_alive()
    assert len(kf_stamps) >= 3 and set(kf_stamps) == with_fix, (kf_stamps, sorted(with_fix))
    tracker.destroy_node()
    listener.node.destroy_node()
    feeder.destroy_node()


def test_flush_waits_for_the_queue_while_the_tracker_takes_frames(rclpy_context, tmp_path, monkeypatch):
    """On a loaded machine the tracker takes its queue slowly: the end of the flight waits for every
    queued frame while frames are being taken (no frame taken for `timeout_s` ends the wait), instead
    of flushing past the queue after a fixed time (those frames then missed the final adjustment)."""
    from photogram_ros.core.camera import save_opencv_yaml
    from photogram_ros.nodes.tracker_node import TrackerNode
    from test_tracker import SimFrames
    save_opencv_yaml(SimFrames(2.0).camera, tmp_path / 'cam.yaml')
    tracker = TrackerNode(overrides={'calibration_file': str(tmp_path / 'cam.yaml'), 'queue_size': 100,
                                     'detect_targets': False}, context=rclpy_context)
    monkeypatch.setattr(tracker, '_handle', lambda msg, cam: time.sleep(0.1))
    try:
        with tracker._cond:
            tracker._frames.extend(object() for _ in range(30))   # 3 s of tracking, 6x the stall bound
            tracker._cond.notify_all()
        tracker.flush(timeout_s=0.5)
        with tracker._cond:
            assert not tracker._frames and tracker.frames_done == 30
    finally:
        tracker.destroy_node()


def test_a_frame_waits_for_its_fix_while_the_fix_stream_is_live(rclpy_context):
    """A frame whose fix has not come yet (the two topics arrive in either order) waits for it, up to
    frame_fix_wait_s and a quarter of the frame interval; a wait that the stream misses is counted and the
    stream is not waited for again until its next fix; a frame whose fix is there does not wait."""
    from types import SimpleNamespace

    from photogram_ros.msgs import time_from_ns
    from photogram_ros.nodes.tracker_node import TrackerNode
    tracker = TrackerNode(overrides={'frame_fix_wait_s': 0.5}, context=rclpy_context)
    s = 1_000_000_000

    def frame(stamp_ns):
        return SimpleNamespace(header=SimpleNamespace(stamp=time_from_ns(stamp_ns)))
    try:
        tracker._on_fix(_fix_at(1 * s))
        tracker._last_stamp_ns = 1 * s

        def late_fix():
            time.sleep(0.1)
            tracker._on_fix(_fix_at(3 * s))
        threading.Thread(target=late_fix).start()
        t0 = time.monotonic()
        with tracker._cond:
            tracker._wait_for_fix(frame(3 * s))      # frames 2 s apart: waits up to 0.5 s
        waited = time.monotonic() - t0
        assert tracker._fixes.latest_ns() == 3 * s and waited < 0.45
        assert tracker.diag.counts().get('frames_fix_late', 0) == 0
        tracker._last_stamp_ns = 3 * s
        t0 = time.monotonic()
        with tracker._cond:
            tracker._wait_for_fix(frame(5 * s))      # no fix comes: the whole wait, then counted
        assert 0.45 < time.monotonic() - t0 < 2.0 and tracker.diag.counts()['frames_fix_late'] == 1
        tracker._last_stamp_ns = 5 * s
        t0 = time.monotonic()
        with tracker._cond:
            tracker._wait_for_fix(frame(7 * s))      # the stream missed a wait and sent nothing since: no wait
        assert time.monotonic() - t0 < 0.1
        tracker._on_fix(_fix_at(8 * s))
        tracker._last_stamp_ns = 8 * s + 300_000_000
        t0 = time.monotonic()
        with tracker._cond:
            tracker._wait_for_fix(frame(8 * s + 400_000_000))   # video pace (0.1 s): at most 25 ms
        assert time.monotonic() - t0 < 0.2 and tracker.diag.counts()['frames_fix_late'] == 2
    finally:
        tracker.destroy_node()
