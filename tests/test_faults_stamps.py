"""Stamp jumps and repeats (issue 48): tracker_node drops a frame whose stamp repeats the last tracked frame's or
goes back (a camera clock reset, a bag recorded twice over), counts it (stamps_repeated, stamps_back) and names it
on /diagnostics as a WARN, with the span of the frames dropped once time goes on; the frames after it are tracked.
Over real rclpy topics."""

from __future__ import annotations

import time

import pytest

pytestmark = pytest.mark.ros

BACK_NS = 5_000_000_000   # the camera clock jumps back 5 s


def test_frames_whose_stamp_repeats_or_goes_back_are_dropped_and_named(rclpy_context, tmp_path):
    from diagnostic_msgs.msg import DiagnosticStatus

    from photogram_ros import msgs
    from test_tracker_node import _fed_tracker
    sim, tracker, listener, feeder, pub_img, pub_fix, ex = _fed_tracker(rclpy_context, tmp_path, 10.0, depth=100,
                                                                        input_depth=100)
    frames = sim.frames
    assert len(frames) >= 18
    # frames 0..5, frame 5 again (a repeat), frames 6..12, frames 13..16 stamped 5 s back (all before frame 12),
    # the rest as they are.
    sent = [(s, img) for s, img, _ in frames[:6]] + [(frames[5][0], frames[5][1])]
    sent += [(s, img) for s, img, _ in frames[6:13]]
    sent += [(s - BACK_NS, img) for s, img, _ in frames[13:17]] + [(s, img) for s, img, _ in frames[17:]]
    assert all(s < frames[12][0] for s, _ in sent[14:18])
    try:
        for stamp, img in sent:
            pub_img.publish(msgs.image_msg(img, stamp))
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and tracker.frames_done < len(sent):
            time.sleep(0.05)
        tracker.flush(timeout_s=5.0)
        time.sleep(1.5)   # one more /diagnostics period
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and len(listener.features) < tracker.keyframes_published:
            time.sleep(0.05)
    finally:
        ex.shutdown()
    try:
        counts = tracker.diag.counts()
        assert counts.get('stamps_repeated') == 1 and counts.get('stamps_back') == 4, counts
        assert counts.get('frames_dropped_stamp') == 5 and counts.get('frames_tracked') == len(sent) - 5, counts
        problems = tracker.diag.recent_problems(20)
        s5 = frames[5][0] * 1e-9
        assert any(f'frame stamped {s5:.3f} s dropped: its stamp repeats' in p for p in problems), problems
        assert any(f'1 frame(s) stamped {s5:.3f} s dropped' in p for p in problems), problems
        back = (frames[13][0] - BACK_NS) * 1e-9
        assert any(f'frame stamped {back:.3f} s dropped: its stamp goes back 4.500 s' in p for p in problems), problems
        first, last = (frames[13][0] - BACK_NS) * 1e-9, (frames[16][0] - BACK_NS) * 1e-9
        assert any(f'4 frame(s) stamped {first:.3f} to {last:.3f} s dropped' in p for p in problems), problems
        # Said on /diagnostics as a WARN, with the counters.
        mine = [st for arr in listener.diags for st in arr.status if st.name.endswith('tracker_node')]
        warned = [st for st in mine if st.level == DiagnosticStatus.WARN and 'dropped' in st.message]
        assert warned, [st.message for st in mine]
        last_values = {kv.key: kv.value for kv in mine[-1].values}
        assert last_values.get('stamps_back') == '4' and last_values.get('stamps_repeated') == '1', last_values
        # The keyframes that went out never go back in time, and tracking went on after the jump.
        kf = [msgs.ns_from_time(m.header.stamp) for m in listener.features]
        assert len(kf) >= 2 and kf == sorted(set(kf)), kf
        assert kf[-1] >= frames[17][0], (kf, frames[17][0])
    finally:
        tracker.destroy_node()
        listener.node.destroy_node()
        feeder.destroy_node()
