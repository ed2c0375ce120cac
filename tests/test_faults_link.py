"""Link silences in a bag (issue 48): mavlink_node warns on /diagnostics when the autopilot's raw bytes stop
for longer than link_timeout_s on the node's clock (the bag's in a replay), and when that clock goes back."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.ros


def test_a_silence_of_the_autopilot_in_a_bag_is_warned(rclpy_context):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from photogram_ros import msgs as pm
    from photogram_ros.nodes.mavlink_node import MavlinkNode
    from test_mavlink_node import _gps_stream
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    node = MavlinkNode({'link_timeout_s': 3.0}, context=rclpy_context)
    clock = iter([0.0, 100.0, 100.2, 100.4, 120.4, 120.6, 110.0, 110.2])   # 0: no /clock yet
    node._now_s = lambda: next(clock)
    try:
        for k in range(8):
            node._on_bytes(pm.bytes_msg(_gps_stream(mav, 1, t0_boot=50.0 + k)))
        counts = node.diag.counts()
        assert counts.get('link_silences') == 1 and counts.get('link_clock_back') == 1, counts
        problems = node.diag.recent_problems(10)
        assert any('silent for 20.0 s (clock 100.4 -> 120.4 s' in p for p in problems), problems
        assert any('clock went back 10.6 s' in p for p in problems), problems
    finally:
        node.destroy_node()
