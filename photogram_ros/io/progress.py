"""Progress lines a person can follow on a long command: how far, how long so far, how long still to go.

`Progress` counts one job of `total` pieces (frames, photos, pairs, keyframes) and says, at most every
`every_s` seconds, a line such as

    replay: 312/850 frames (37 %), 2.1 min elapsed, ETA 3.6 min

with the time left from a smoothed rate (a time-weighted moving average of the pieces per second, so
a slow start or one slow piece does not swing the estimate); "ETA unknown" while no rate is known or
when the total is not. `finish()` says the summary line (`replay: 850/850 frames (100 %) in 5.7 min`).

`Steps` names the steps of a job as each starts (`export: DSM (step 3/6), 12 s elapsed`) and ends
with the time of the whole and of its longest step.

Both say their lines through `say(text)` (None: silent, as `--quiet` asks) and read the time from
`clock()` (seconds, monotonic; tests give a fake one). No ROS, no I/O of their own.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Callable

Say = Callable[[str], None]
EVERY_S = 5.0    # seconds between two lines of a Progress made without `every_s`


def say_stdout(text: str) -> None:
    """A line on standard output, flushed (progress shows while the command runs, also into a pipe)."""
    print(text, flush=True)


def say_stderr(text: str) -> None:
    """A line on standard error, flushed."""
    print(text, file=sys.stderr, flush=True)


def sayer(progress, default: Say = say_stdout) -> Say | None:
    """What a function's `progress` argument asks: True -> `default`, False/None -> None (silent), a
    function -> that function."""
    if callable(progress):
        return progress
    return default if progress else None


def duration_text(seconds: float) -> str:
    """A duration for a person: '42 s', '2.1 min', '1.3 h'."""
    s = max(0.0, float(seconds))
    if s < 60.0:
        return f'{s:.0f} s'
    if s < 3600.0:
        return f'{s / 60.0:.1f} min'
    return f'{s / 3600.0:.1f} h'


class Progress:
    """Progress of one job of `total` pieces (None or 0: not known), named `what`, counted in `unit`.

    update(done) takes the count done so far (add(n) adds to it); a line is said when `every_s` (default
    EVERY_S) has passed since the start or the last line. The rate is sampled at most every `sample_s` and smoothed
    with the time constant `tau_s`: ETA = (total - done) / rate.
    """

    def __init__(self, what: str, total: int | None = None, unit: str = '', say: Say | None = say_stdout,
                 every_s: float | None = None, clock: Callable[[], float] = time.monotonic, tau_s: float = 30.0,
                 sample_s: float = 1.0):
        self.what, self.unit, self.say, self.clock = what, unit, say, clock
        self.every_s = EVERY_S if every_s is None else every_s
        self.total = int(total) if total else None
        self.tau_s, self.sample_s = tau_s, sample_s
        self.t0 = self._last_said = self._t_sample = clock()
        self.done = self._d_sample = 0
        self.rate: float | None = None     # smoothed pieces per second; None until the first sample
        self.finished = False

    def add(self, n: int = 1, extra: str | Callable[[], str] = '') -> bool:
        """update(done + n)."""
        return self.update(self.done + n, extra)

    def update(self, done: int, extra: str | Callable[[], str] = '') -> bool:
        """`done` pieces so far; says a line (with `extra` appended: a text, or a function giving it, called
        only when a line is said) when one is due. Returns whether it did."""
        now = self.clock()
        self.done = int(done)
        dt = now - self._t_sample
        if dt >= self.sample_s:
            inst = (self.done - self._d_sample) / dt
            w = 1.0 - math.exp(-dt / self.tau_s)
            self.rate = inst if self.rate is None else self.rate + w * (inst - self.rate)
            self._t_sample, self._d_sample = now, self.done
        if self.say is None or self.finished or now - self._last_said < self.every_s:
            return False
        self._last_said = now
        self.say(self.line(extra() if callable(extra) else extra, now))
        return True

    def eta_s(self) -> float | None:
        """Seconds left at the smoothed rate; None when the total or a rate is not known (or nothing moves)."""
        if self.total is None:
            return None
        left = self.total - self.done
        if left <= 0:
            return 0.0
        if not self.rate or self.rate <= 0.0:
            return None
        return left / self.rate

    def _count(self) -> str:
        unit = f' {self.unit}' if self.unit else ''
        if self.total is None:
            return f'{self.done}{unit}'
        pct = min(100, int(100 * self.done / self.total)) if self.total else 100
        return f'{self.done}/{self.total}{unit} ({pct} %)'

    def line(self, extra: str = '', now: float | None = None) -> str:
        """'what: done/total unit (pct %), elapsed, ETA ...[; extra]'."""
        now = self.clock() if now is None else now
        eta = self.eta_s()
        return (f'{self.what}: {self._count()}, {duration_text(now - self.t0)} elapsed, '
                + (f'ETA {duration_text(eta)}' if eta is not None else 'ETA unknown')
                + (f'; {extra}' if extra else ''))

    def finish(self, extra: str | Callable[[], str] = '') -> str:
        """The summary line, said once: 'what: done/total unit (pct %) in duration[; extra]'."""
        extra = extra() if callable(extra) else extra
        text = f'{self.what}: {self._count()} in {duration_text(self.clock() - self.t0)}' + (
            f'; {extra}' if extra else '')
        if self.say is not None and not self.finished:
            self.say(text)
        self.finished = True
        return text

    def callback(self, extra: Callable[[], str] | None = None) -> Callable[[int, int], None]:
        """A `progress(done, total)` function for code that reports so (io/densify.py): updates this
        reporter (its total from the calls) and says the summary when done reaches total."""
        def report(done: int, total: int) -> None:
            self.total = int(total) if total else None
            self.update(done, extra or '')
            if self.total is not None and done >= self.total:
                self.finish(extra or '')
        return report


class Steps:
    """The named steps of one job `what` (`total` of them, None: not counted ahead), each said as it starts."""

    def __init__(self, what: str, total: int | None = None, say: Say | None = say_stdout,
                 clock: Callable[[], float] = time.monotonic):
        self.what, self.total, self.say, self.clock = what, total, say, clock
        self.t0 = clock()
        self.times: list[tuple[str, float]] = []   # (step, its start)
        self.finished = False

    def start(self, name: str) -> None:
        """Step `name` begins: 'what: name (step k/n), elapsed'."""
        now = self.clock()
        self.times.append((name, now))
        k = len(self.times)
        of = f'{k}/{self.total}' if self.total else f'{k}'
        if self.say is not None:
            self.say(f'{self.what}: {name} (step {of}), {duration_text(now - self.t0)} elapsed')

    def durations(self, now: float | None = None) -> list[tuple[str, float]]:
        """(step, seconds) of the steps started so far; the last one lasts until `now`."""
        now = self.clock() if now is None else now
        ends = [t for _, t in self.times[1:]] + [now]
        return [(name, end - t) for (name, t), end in zip(self.times, ends)]

    def progress(self, name: str, total: int | None, unit: str, every_s: float | None = None) -> Progress:
        """A step counted in pieces: starts the step and gives its Progress ('what: name: 3/40 unit ...')."""
        self.start(name)
        return Progress(f'{self.what}: {name}', total, unit, self.say, every_s, self.clock)

    def finish(self) -> str:
        """The summary line, said once: 'what: N steps in duration (longest: name duration)'."""
        now = self.clock()
        steps = self.durations(now)
        text = f'{self.what}: {len(steps)} steps in {duration_text(now - self.t0)}'
        if steps:
            name, s = max(steps, key=lambda d: d[1])
            text += f' (longest: {name}, {duration_text(s)})'
        if self.say is not None and not self.finished:
            self.say(text)
        self.finished = True
        return text
