"""Autopilot boot clock -> UNIX / host time, robust to link jitter and latency.

Flight controllers stamp GPS_RAW_INT, ATTITUDE and friends with time since boot, and that clock
drifts (a few ppm) against UNIX time. Two kinds of evidence tie it to the outside world:

- SYSTEM_TIME pairs (time_boot_ms, time_unix_usec) made *inside* the autopilot: no link latency,
  only millisecond truncation of the boot time. A straight-line fit of offset vs boot time (offset
  + drift), with outlier rejection, maps boot time to UNIX time to well under a millisecond.
- Arrival pairs (boot time carried by a packet, host time when it arrived): latency is always
  positive and jittery, so the honest model is the *lower envelope* of the offsets, i.e. the line
  under every point that is closest to them on average (the packets that travelled fastest).

`BootClock` keeps both in sliding windows and maps with the best one available. A boot time going
backwards (reboot) or a persistent jump of the UNIX time (GPS time acquired) restarts the fit.

A time mapping must not follow evidence it cannot explain: one wild pair would stamp every fix
after it in another century. So a UNIX time outside 2000-2100 is refused outright
('implausible'); a jump of the UNIX time and a boot time going backwards (a reboot) are believed
only once `jump_confirm` pairs agree ('outlier' until then, the fit unchanged); and after a reboot
the new fit must continue the UNIX time from before it (no earlier than the last UNIX time seen
plus the new boot time, no more than a day later), unless as many pairs confirm it.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

# time_boot_ms is truncated to whole milliseconds: the true boot time is half a tick later on average.
_BOOT_MS_HALF_TICK_S = 0.0005
# UNIX times a flight log can carry: 2000-01-01 .. 2100-01-01.
PLAUSIBLE_UNIX_S = (946_684_800.0, 4_102_444_800.0)
# After a reboot the autopilot can have been off this long at most, s.
_MAX_DOWNTIME_S = 86_400.0


@dataclass
class ClockFit:
    """host_or_unix_s = boot_s + offset_s + drift * (boot_s - ref_boot_s)."""

    ref_boot_s: float
    offset_s: float
    drift: float
    n: int
    span_s: float
    residual_s: float      # robust spread (system time) or median height above the envelope (arrival)
    source: str            # 'system_time' or 'arrival'

    def map(self, boot_s: float) -> float:
        return boot_s + self.offset_s + self.drift * (boot_s - self.ref_boot_s)


def _fit_line(x: np.ndarray, y: np.ndarray, min_span_s: float, max_drift: float):
    """Least-squares offset + drift; offset only (median) while the span is too short to see drift."""
    ref = float(x[-1])
    span = float(x.max() - x.min())
    if len(x) < 3 or span < min_span_s:
        return ref, float(np.median(y)), 0.0
    slope, intercept = np.polyfit(x - ref, y, 1)
    slope = float(np.clip(slope, -max_drift, max_drift))
    return ref, float(np.median(y - slope * (x - ref))), slope


def lower_envelope(x: np.ndarray, y: np.ndarray):
    """Line (slope, intercept) under all points minimising the mean height above it.

    The minimiser of mean(y - a - b x) subject to y >= a + b x touches the lower convex hull at the
    mean of x, so it is the hull edge spanning mean(x).
    """
    order = np.argsort(x, kind='stable')
    x, y = x[order], y[order]
    hull: list[int] = []
    for i in range(len(x)):
        while len(hull) >= 2:
            i0, i1 = hull[-2], hull[-1]
            cross = (x[i1] - x[i0]) * (y[i] - y[i0]) - (y[i1] - y[i0]) * (x[i] - x[i0])
            if cross <= 0:
                hull.pop()
            else:
                break
        hull.append(i)
    if len(hull) == 1 or x[hull[-1]] - x[hull[0]] <= 0:
        return 0.0, float(y.min())
    xm = float(x.mean())
    for i0, i1 in zip(hull[:-1], hull[1:]):
        if x[i0] <= xm <= x[i1] and x[i1] > x[i0]:
            b = (y[i1] - y[i0]) / (x[i1] - x[i0])
            return float(b), float(y[i0] - b * x[i0])
    return 0.0, float(y.min())


class BootClock:
    """Sliding-window maps from autopilot boot time (s) to UNIX time and to host arrival time."""

    def __init__(self, window_s: float = 300.0, min_drift_span_s: float = 20.0, max_drift_ppm: float = 200.0,
                 jump_s: float = 0.25, jump_confirm: int = 3, auto_wait_s: float = 3.0):
        self.window_s = window_s
        self.auto_wait_s = auto_wait_s
        self.min_drift_span_s = min_drift_span_s
        self.max_drift = max_drift_ppm * 1e-6
        self.jump_s = jump_s
        self.jump_confirm = jump_confirm
        self._sys: deque = deque()      # (boot_s, unix_s - boot_s)
        self._arr: deque = deque()      # (boot_s, host_s - boot_s)
        self._sys_fit: ClockFit | None = None
        self._arr_fit: ClockFit | None = None
        self._suspects: list = []
        self._back: list = []            # distinct boot times seen going backwards, not yet a reboot
        self._last_boot_s = None
        self._last_unix_s = None         # the latest UNIX time of a SYSTEM_TIME the fit took (kept by reset)
        self.resets = 0
        self.outliers = 0
        self.implausible = 0
        self.detail = ''                 # what the last 'outlier' / 'implausible' / 'jump' / 'reboot' was

    # --- evidence -------------------------------------------------------------------------------

    def _boot_check(self, boot_s: float) -> str:
        """'ok'; 'suspect': the boot time went backwards by more than a second, not (yet) confirmed;
        'reboot': `jump_confirm` distinct, increasing boot times all went backwards: the clock is reset."""
        if self._last_boot_s is None or boot_s >= self._last_boot_s - 1.0:
            self._back = []
            self._last_boot_s = boot_s if self._last_boot_s is None else max(self._last_boot_s, boot_s)
            return 'ok'
        if not self._back or boot_s > self._back[-1]:
            self._back.append(boot_s)
        elif boot_s < self._back[-1] - 1.0:
            self._back = [boot_s]
        if len(self._back) < self.jump_confirm:
            self.detail = f'boot time {boot_s:.3f} s is before {self._last_boot_s:.3f} s: a reboot only if it repeats'
            return 'suspect'
        self.reset()
        self._last_boot_s = boot_s
        self.detail = 'the boot time started again: the autopilot rebooted'
        return 'reboot'

    def reset(self) -> None:
        self._sys.clear()
        self._arr.clear()
        self._sys_fit = self._arr_fit = None
        self._suspects = []
        self._back = []
        self._last_boot_s = None
        self.resets += 1

    def _unexplained(self, boot_s: float, unix_s: float) -> str:
        """Why a pair starting a fit after a reset cannot continue the UNIX time from before it ('' if it can)."""
        if self._sys_fit is not None or self._last_unix_s is None:
            return ''
        lo, hi = self._last_unix_s + boot_s - 2.0, self._last_unix_s + boot_s + _MAX_DOWNTIME_S
        if lo <= unix_s <= hi:
            return ''
        return (f'UNIX time {unix_s:.0f} s does not continue the {self._last_unix_s:.0f} s seen before the '
                f'reset ({unix_s - self._last_unix_s - boot_s:+.0f} s)')

    def add_system_time(self, time_boot_ms: int, time_unix_usec: int) -> str:
        """One SYSTEM_TIME pair; returns 'ok', 'ignored' (no UNIX time yet), 'implausible', 'outlier',
        'jump' or 'reboot' (`detail` says why for all but the first two)."""
        if time_unix_usec <= 0 or time_boot_ms <= 0:
            return 'ignored'
        unix_s = time_unix_usec * 1e-6
        if not PLAUSIBLE_UNIX_S[0] <= unix_s < PLAUSIBLE_UNIX_S[1]:
            self.implausible += 1
            self.detail = f'SYSTEM_TIME UNIX time {unix_s:.0f} s is outside 2000-2100: ignored'
            return 'implausible'
        boot_s = time_boot_ms * 1e-3 + _BOOT_MS_HALF_TICK_S
        state = self._boot_check(boot_s)
        if state == 'suspect':
            self.outliers += 1
            return 'outlier'
        event = 'reboot' if state == 'reboot' else 'ok'
        y = unix_s - boot_s
        fit = self._sys_fit
        why = self._unexplained(boot_s, unix_s)
        if why or (fit is not None and abs(fit.map(boot_s) - boot_s - y) > self.jump_s):
            # Keep the suspects that agree with the newest one: a real jump repeats, a wild pair does not.
            self._suspects = [p for p in self._suspects if abs(p[1] - y) <= self.jump_s] + [(boot_s, y)]
            if len(self._suspects) < self.jump_confirm:
                self.outliers += 1
                off = why or (f'SYSTEM_TIME disagrees with the clock fit by {fit.map(boot_s) - boot_s - y:+.3f} s')
                self.detail = f'{off}: ignored unless it repeats'
                return 'outlier'
            # Several consistent pairs disagree with the fit: the UNIX time really moved.
            self._sys.clear()
            self._sys.extend(self._suspects)
            self._suspects = []
            self._sys_fit = None
            self.resets += 1
            self.detail = f'{len(self._sys)} SYSTEM_TIME pairs agree on a new UNIX time ({why or "a jump"})'
            event = 'jump'
        else:
            self._suspects = []
            self._sys.append((boot_s, y))
        self._last_unix_s = unix_s
        while self._sys and self._sys[0][0] < boot_s - self.window_s:
            self._sys.popleft()
        # Refitting every pair costs ~1 ms; a pair the fit already explains changes it by nothing.
        fit = self._sys_fit
        if fit is None or event != 'ok' or len(self._sys) < 20 or len(self._sys) % 10 == 0 \
                or abs(fit.map(boot_s) - boot_s - y) > max(3 * fit.residual_s, 0.002):
            self._sys_fit = self._refit_system()
        else:
            self._sys_fit = ClockFit(fit.ref_boot_s, fit.offset_s, fit.drift, len(self._sys),
                                     boot_s - self._sys[0][0], fit.residual_s, fit.source)
        return event

    def _refit_system(self) -> ClockFit:
        arr = np.array(self._sys)
        x, y = arr[:, 0], arr[:, 1]
        ref, off, drift = _fit_line(x, y, self.min_drift_span_s, self.max_drift)
        res = y - (off + drift * (x - ref))
        mad = float(np.median(np.abs(res - np.median(res)))) * 1.4826
        keep = np.abs(res) <= max(4.0 * mad, 0.002)
        if keep.sum() >= 3 and not keep.all():
            ref, off, drift = _fit_line(x[keep], y[keep], self.min_drift_span_s, self.max_drift)
            res = y[keep] - (off + drift * (x[keep] - ref))
        spread = float(np.sqrt(np.mean(res ** 2))) if len(res) else 0.0
        return ClockFit(ref, off, drift, len(x), float(np.ptp(x)), spread, 'system_time')

    def add_arrival(self, boot_s: float, host_s: float) -> str:
        """A packet carrying boot time `boot_s` arrived at host time `host_s`."""
        state = self._boot_check(boot_s)
        if state == 'suspect':
            self.outliers += 1
            return 'outlier'
        event = 'reboot' if state == 'reboot' else 'ok'
        self._arr.append((boot_s, host_s - boot_s))
        while self._arr and self._arr[0][0] < boot_s - self.window_s:
            self._arr.popleft()
        fit = self._arr_fit
        below = fit is not None and host_s < fit.map(boot_s)
        if fit is not None and not below and event == 'ok' and len(self._arr) % 10 != 0:
            # Above the envelope: the fit stays valid (refreshed every tenth pair for the window).
            self._arr_fit = ClockFit(fit.ref_boot_s, fit.offset_s, fit.drift, len(self._arr),
                                     boot_s - self._arr[0][0], fit.residual_s, fit.source)
            return event
        arr = np.array(self._arr)
        x, y = arr[:, 0], arr[:, 1]
        ref = float(x[-1])
        if np.ptp(x) < self.min_drift_span_s:
            slope, icpt = 0.0, float(y.min())
        else:
            slope, icpt = lower_envelope(x - ref, y)
            if abs(slope) > self.max_drift:
                slope, icpt = 0.0, float(y.min())
        above = y - (icpt + slope * (x - ref))
        self._arr_fit = ClockFit(ref, icpt, slope, len(x), float(np.ptp(x)), float(np.median(above)), 'arrival')
        return event

    # --- mapping --------------------------------------------------------------------------------

    def fit(self, source: str = 'auto') -> ClockFit | None:
        if source == 'system_time':
            return self._sys_fit
        if source == 'arrival':
            return self._arr_fit
        if self._sys_fit is not None:
            return self._sys_fit
        # 'auto' waits a little for SYSTEM_TIME (the better clock) before settling for arrival times.
        if self._arr_fit is not None and self._arr_fit.span_s >= self.auto_wait_s:
            return self._arr_fit
        return None

    def to_time(self, boot_s: float, source: str = 'auto') -> float | None:
        """Boot time (s) -> UNIX (system_time) or host (arrival) time, s; None before any evidence."""
        f = self.fit(source)
        return None if f is None else f.map(boot_s)

    def quality(self, source: str = 'auto') -> dict:
        f = self.fit(source)
        if f is None:
            return {'synced': False, 'resets': self.resets, 'outliers': self.outliers}
        return {'synced': True, 'source': f.source, 'offset_s': f.offset_s, 'drift_ppm': f.drift * 1e6,
                'pairs': f.n, 'span_s': f.span_s, 'residual_s': f.residual_s, 'resets': self.resets,
                'outliers': self.outliers}
