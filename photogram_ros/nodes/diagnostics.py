"""Health reporting on /diagnostics, shared by every node.

Nodes count what they do (`count`), record problems (`problem`) and set values (`set`); a timer
publishes one DiagnosticStatus per node each period. A bad message is a counted, reported event,
never a reason to stop the node.

Time: a status is stamped with the node's clock, the bag's time in a replay (use_sim_time, /clock),
the system clock live; the period runs on the steady clock (`steady_timer`), so health keeps coming
while /clock stands still (a replay waiting for a slow node, the end of flight after the bag).
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from photogram_ros.nodes import qos

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
PROBLEM_SEPARATOR = ' | '


TIMER_MAX_SHARE = 0.5   # the share of the time a steady_timer's callback may take (steady_timer)


def steady_timer(node: Node, period_s: float, callback, callback_group=None, max_share: float = TIMER_MAX_SHARE):
    """A timer of `node` on the steady clock. A node's own clock is the bag's under use_sim_time, and
    its timers stand still whenever /clock does: fine for work paced by the data, wrong for housekeeping
    (health, flushing to disk, streaming the map) that must go on while a replay waits or has ended.

    The callback keeps to `max_share` (0-1] of the time: after a run of d seconds the timer's calls do nothing
    for d x (1 / max_share - 1) s. A callback slower than its period would otherwise keep its timer ready, and
    rclpy's executor takes ready timers before subscriptions: in a mutually exclusive callback group the node's
    subscriptions would get no turn at all (a map whose coverage update took 4 s, each second, received no
    keyframe image or pose for the rest of the flight)."""
    rest = 1.0 / min(max(max_share, 1e-3), 1.0) - 1.0
    until = [0.0]

    def kept_to_its_share():
        start = time.monotonic()
        if start < until[0]:
            return None
        try:
            return callback()
        finally:
            end = time.monotonic()
            until[0] = end + (end - start) * rest

    return node.create_timer(period_s, kept_to_its_share, callback_group=callback_group,
                             clock=Clock(clock_type=ClockType.STEADY_TIME))


class Diagnostics:
    def __init__(self, node: Node, period_s: float = 1.0, hardware_id: str = 'photogram_ros'):
        self.node = node
        self.name = node.get_fully_qualified_name()
        self.hardware_id = hardware_id
        self._lock = threading.Lock()
        self._counts = Counter()
        self._values: dict[str, str] = {}
        self._problems: deque = deque(maxlen=20)
        self._unpublished: list[str] = []   # problems since the last status: all of them are published
        self._level = OK
        self._rate_marks: dict[str, deque] = {}
        self._pub = node.create_publisher(DiagnosticArray, '/diagnostics', qos.diagnostics())
        self._timer = steady_timer(node, period_s, self.publish)

    def count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._counts[key] += n
            marks = self._rate_marks.setdefault(key, deque(maxlen=200))
            marks.append(time.monotonic())

    def rate_hz(self, key: str, window_s: float = 5.0) -> float:
        with self._lock:
            marks = self._rate_marks.get(key)
            if not marks:
                return 0.0
            now = time.monotonic()
            recent = [m for m in marks if now - m <= window_s]
        return len(recent) / window_s

    def set(self, key: str, value) -> None:
        with self._lock:
            self._values[key] = f'{value:.6g}' if isinstance(value, float) else str(value)

    def problem(self, what: str, level: int = WARN) -> None:
        """Record a problem (bad message, outage); the node logs it once per kind and goes on."""
        with self._lock:
            first = not any(p[1] == what for p in self._problems)
            self._problems.append((time.time(), what))
            if what not in self._unpublished:
                self._unpublished.append(what)
            self._counts['problems'] += 1
            self._level = max(self._level, level)
        if first:
            self.node.get_logger().warning(what)

    def counts(self) -> dict:
        with self._lock:
            return dict(self._counts)

    def recent_problems(self, n: int = 5) -> list[str]:
        """The texts of the last `n` problems, oldest first."""
        with self._lock:
            return [what for _, what in list(self._problems)[-n:]]

    def status(self) -> DiagnosticStatus:
        with self._lock:
            kv = [KeyValue(key=k, value=str(v)) for k, v in sorted(self._counts.items())]
            kv += [KeyValue(key=k, value=v) for k, v in sorted(self._values.items())]
            # Every problem since the last status, so none hides behind a later one in the same period.
            msg = (PROBLEM_SEPARATOR.join(self._unpublished) if self._unpublished
                   else 'OK' if not self._problems else self._problems[-1][1])
            self._unpublished = []
            level = self._level
            self._level = OK if not self._problems or time.time() - self._problems[-1][0] > 10 else self._level
        return DiagnosticStatus(level=level, name=self.name, message=msg[:1000], hardware_id=self.hardware_id,
                                values=kv)

    def publish(self) -> None:
        """One status, stamped with the node's clock; none while that clock reads 0 (use_sim_time before the
        first /clock: no time to give it yet), the problems wait for the next."""
        now = self.node.get_clock().now()
        if now.nanoseconds == 0:
            return
        arr = DiagnosticArray()
        arr.header.stamp = now.to_msg()
        arr.status = [self.status()]
        self._pub.publish(arr)
