"""The time budget of a stopped flight's end (issue 48), without ROS: `run` stopped by SIGINT/SIGTERM gives the
end-of-flight steps `--stop-budget-s` in all (nodes/graph.py Graph.finish_flight hands each step what is left);
a step that holds one (`EndBudget`) does what fits in it and says what it left out. A flight that ended by itself
(its photo folder, its bag) has no budget: every step runs to its end.
"""

from __future__ import annotations

import math
import time


class EndBudget:
    """A deadline `budget_s` seconds from now (steady clock); `budget_s` <= 0: none (`left_s()` is infinite)."""

    def __init__(self, budget_s: float = 0.0):
        self.t0 = time.monotonic()
        self.budget_s = float(budget_s)
        self.deadline = self.t0 + self.budget_s if self.budget_s > 0 else math.inf
        self.marks: list[float] = []

    @property
    def bounded(self) -> bool:
        return math.isfinite(self.deadline)

    def left_s(self) -> float:
        """Seconds left (0 once past; infinite without a budget)."""
        return max(self.deadline - time.monotonic(), 0.0)

    def elapsed_s(self) -> float:
        return time.monotonic() - self.t0

    def mark(self) -> None:
        """Note the seconds elapsed now (the end of a step) in `marks`."""
        self.marks.append(self.elapsed_s())

    def fits(self, reserve_s: float = 0.0) -> bool:
        """More than `reserve_s` seconds are left."""
        return self.left_s() > reserve_s


# Seconds a keyframe adds to a final adjustment when no full adjustment was timed in flight: toledo's (2400x1800)
# took 21.6 s for 37 keyframes and 32.1 s for 38, 0.58 and 0.84 s each, on 2 cores at load 5-6 (bench/faults_stop.py's
# run log, bundle_node's "end of flight: ..." line).
FULL_ADJUSTMENT_S_PER_KEYFRAME = 0.8
# The adjuster's count of the keyframes a stopped flight's budget left out, under io/flight_verdict.py's
# AT_END_PREFIX: the report names them "not oriented: left out by the stop budget".
LEFT_OUT_AT_END = 'not_oriented_at_end_left_out_by_the_stop_budget'


def full_adjustment_estimate_s(last_full_s: float | None, n_last: int, n_now: int,
                               per_keyframe_s: float = FULL_ADJUSTMENT_S_PER_KEYFRAME) -> float:
    """What a full adjustment of `n_now` keyframes will take: the last one's `last_full_s` (of `n_last`
    keyframes) scaled by the keyframes, else `per_keyframe_s` each."""
    if last_full_s and n_last > 0:
        return last_full_s * max(n_now, 1) / n_last
    return per_keyframe_s * max(n_now, 1)


def skip_at_end(diag, n: int, level) -> None:
    """`n` keyframes waiting for the adjuster left out of a stopped flight's end (its budget ran out): counted in
    keyframes_skipped_at_end, said at `level` on `diag` (stages/report.py DiagnosticsLog or a node's)."""
    diag.count('keyframes_skipped_at_end', n)
    diag.count(LEFT_OUT_AT_END, n)   # the report's keyframe accounting (io/flight_verdict.py) names the reason
    diag.problem(f'end of flight: {n} keyframes waiting for the adjuster were left out (the stopped flight\'s '
                 'budget, run --stop-budget-s; their images stay in the map folder without a pose): '
                 'run --stop-budget-s 0 adjusts every one', level)


def end_times(t: list[float], n_waiting: int, diag) -> str:
    """The adjuster's end-of-flight step times from the elapsed seconds at each step's end (the batch in progress,
    the waiting keyframes, the second chance, the final adjustment): one line, set as end_of_flight_s on `diag`
    (/diagnostics) and returned (for the log)."""
    names = ('batch in progress', f'{n_waiting} waiting keyframes', 'second chance', 'final adjustment')
    text = ', '.join(f'{name} {b - a:.1f} s' for name, a, b in zip(names, [0.0] + t, t))
    diag.set('end_of_flight_s', text)
    return text
