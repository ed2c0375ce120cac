"""What a stage reports besides its results: diagnostics levels and an in-memory diagnostics sink.

A stage reports through any object with count(key, n=1), set(key, value), problem(text, level) and
rate_hz(key, window_s) (a node passes its /diagnostics, nodes/stage_diagnostics.py); `DiagnosticsLog`
keeps them for a caller without ROS (tests, offline commands).
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque

OK, WARN, ERROR = 0, 1, 2   # diagnostic_msgs/DiagnosticStatus levels, as ints


class DiagnosticsLog:
    """Diagnostics kept in memory: counts, values (as given), problems as (level, text) in order."""

    def __init__(self):
        self._lock = threading.Lock()
        self._counts, self.values, self.problems = Counter(), {}, []
        self._marks: dict[str, deque] = {}

    def count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._counts[key] += n
            self._marks.setdefault(key, deque(maxlen=200)).append(time.monotonic())

    def rate_hz(self, key: str, window_s: float = 5.0) -> float:
        """Counts of `key` per second over the last window_s (each count call one event)."""
        with self._lock:
            now = time.monotonic()
            return sum(now - m <= window_s for m in self._marks.get(key, ())) / window_s

    def set(self, key: str, value) -> None:
        with self._lock:
            self.values[key] = value

    def problem(self, what: str, level: int = WARN) -> None:
        with self._lock:
            self.problems.append((level, what))
            self._counts['problems'] += 1

    def counts(self) -> dict:
        with self._lock:
            return dict(self._counts)

    def level(self) -> int:
        """The worst level of every problem so far (OK without one)."""
        with self._lock:
            return max((lv for lv, _ in self.problems), default=OK)
