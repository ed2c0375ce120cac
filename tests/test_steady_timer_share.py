"""nodes/diagnostics.steady_timer keeps a slow callback to its share of the time, so that the subscriptions of its
mutually exclusive callback group still get their turns (rclpy's executor takes ready timers first), with real
rclpy nodes on a multi-threaded executor as nodes/graph.py spins them."""

from __future__ import annotations

import threading
import time

import pytest
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import String

from photogram_ros.nodes import qos
from photogram_ros.nodes.diagnostics import steady_timer

MESSAGES = 20


def _received_beside_a_slow_timer(ctx, max_share: float, topic: str) -> tuple[int, int]:
    """(messages the sink received, runs of its slow timer) within 4 s of their publication, 0.6 s after the
    start: the sink's timer (every 0.05 s) takes 0.2 s a run, in the same mutually exclusive group as its
    subscription."""
    sink = Node('sink', context=ctx)
    source = Node('source', context=ctx)
    group = MutuallyExclusiveCallbackGroup()
    got, runs = [], [0]

    def slow():
        runs[0] += 1
        time.sleep(0.2)

    sink.create_subscription(String, topic, lambda m: got.append(m.data), qos.keep_all(), callback_group=group)
    steady_timer(sink, 0.05, slow, group, max_share=max_share)
    pub = source.create_publisher(String, topic, qos.keep_all())
    ex = MultiThreadedExecutor(num_threads=4, context=ctx)
    ex.add_node(sink)
    ex.add_node(source)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    try:
        deadline = time.monotonic() + 5.0
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.6)   # the slow timer at work
        for k in range(MESSAGES):
            pub.publish(String(data=str(k)))
        deadline = time.monotonic() + 4.0
        while len(got) < MESSAGES and time.monotonic() < deadline:
            time.sleep(0.05)
        return len(got), runs[0]
    finally:
        ex.shutdown()
        sink.destroy_node()
        source.destroy_node()


def test_a_slow_timer_leaves_its_group_s_subscription_its_turns(rclpy_context):
    got, runs = _received_beside_a_slow_timer(rclpy_context, 0.5, 'share_half')
    assert got == MESSAGES and runs >= 2


def test_without_the_share_the_slow_timer_starves_the_subscription(rclpy_context):
    # The control: a timer allowed all the time (max_share 1) is always ready, and taken first.
    got, runs = _received_beside_a_slow_timer(rclpy_context, 1.0, 'share_all')
    assert runs >= 5 and got < MESSAGES


@pytest.mark.parametrize('max_share', (0.0, -1.0, 2.0))
def test_a_share_outside_0_1_is_bounded(rclpy_context, max_share):
    got, _ = _received_beside_a_slow_timer(rclpy_context, max_share, f'share_{abs(max_share):g}'.replace('.', '_'))
    assert got == MESSAGES if max_share <= 0 else got < MESSAGES
