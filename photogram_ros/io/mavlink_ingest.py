"""From decoded MAVLink messages to what the node publishes: fixes, attitude, camera triggers.

`Ingest` maps the autopilot's boot clock to UNIX/host time (SYSTEM_TIME, TIMESYNC), turns
GPS_RAW_INT / GPS2_RAW into `core.gnss_fix.GnssFix` (one `FixEvent` per fix, routed to /gps/fix and the
per-receiver topics), ATTITUDE(_QUATERNION) into `Attitude` (FLU in ENU) and CAMERA_FEEDBACK /
CAMERA_TRIGGER into `Trigger`. It has no ROS in it, so `photogram-ros fixes` prints exactly what
the node publishes.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np

from photogram_ros.core import gnss_fix as gf
from photogram_ros.core.rotations import quat_enu_flu_from_quat_ned_frd, quat_ned_frd_from_euler
from photogram_ros.core.timesync import BootClock
from photogram_ros.errors import ConfigError


@dataclass
class Attitude:
    t_s: float                    # on the output clock (UNIX / ROS), s
    q_enu_flu_xyzw: np.ndarray
    rates_flu_rad_s: np.ndarray | None
    source: str


@dataclass
class Trigger:
    """One camera exposure and the camera position at it: a GnssFix stamped at the exposure, WGS84 and
    ellipsoidal, with the quality and accuracy of the receiver fix it came from."""

    t_s: float                    # the exposure on the output clock (UNIX / ROS), s
    seq: int
    source: str                   # 'CAMERA_FEEDBACK' or 'CAMERA_TRIGGER' (position interpolated from fixes)
    fix: gf.GnssFix


@dataclass
class FixEvent:
    """A decoded fix and where it goes: an event about a `gf.GnssFix` (its routing), not another fix type."""

    fix: gf.GnssFix
    best: bool                    # goes to /gps/fix (the chosen receiver, newer than the last one there)
    per_receiver: bool = True     # goes to /gps/fix_<receiver + 1> (False: it went there already)


def _exposure_fix(t_s: float, lat: float, lon: float, h: float, ref: gf.GnssFix | None, source: str) -> gf.GnssFix:
    """The camera position at an exposure with the quality and covariance of the fix `ref` it came from (none:
    no fix, covariance unknown)."""
    if ref is None:
        return gf.GnssFix(lat, lon, h, np.zeros((3, 3)), int(round(t_s * 1e9)), cov_type=gf.COV_UNKNOWN,
                          quality=gf.Q_NONE, source=source, quality_native=gf.NO_FIX, native_scale='GPS_FIX_TYPE')
    return gf.GnssFix(lat, lon, h, np.diag(ref.var_enu_m2), int(round(t_s * 1e9)), cov_type=ref.cov_type,
                      quality=ref.quality, source=source, quality_native=ref.quality_native,
                      native_scale=ref.native_scale, receiver=ref.receiver, sats=ref.sats, hdop=ref.hdop)


def raw_gnss(m, receiver: int) -> gf.RawGnss:
    """GPS_RAW_INT / GPS2_RAW -> RawGnss (extension fields read as 0 when the sender omitted them)."""
    g = getattr
    return gf.RawGnss(receiver=receiver, time_usec=int(m.time_usec), fix_type=int(m.fix_type), lat_e7=int(m.lat),
                      lon_e7=int(m.lon), alt_msl_mm=int(m.alt), alt_ellipsoid_mm=int(g(m, 'alt_ellipsoid', 0) or 0),
                      eph=int(m.eph), epv=int(m.epv), h_acc_mm=int(g(m, 'h_acc', 0) or 0),
                      v_acc_mm=int(g(m, 'v_acc', 0) or 0), sats=int(m.satellites_visible),
                      sysid=m.get_header().srcSystem, compid=m.get_header().srcComponent)


class Ingest:
    """Decoded messages -> FixEvent / Attitude / Trigger, stamped on the UNIX (or host) clock.

    Items that need the boot clock wait (a few seconds at most) until the first SYSTEM_TIME or
    TIMESYNC arrives, then come out in order.
    """

    GPS_TYPES = {'GPS_RAW_INT': 0, 'GPS2_RAW': 1}
    REBOOT_CONFIRM = 3      # distinct boot times going backwards before the data says "reboot"

    def __init__(self, clock_source: str = 'auto', error_model: gf.ErrorModel | None = None,
                 max_fix_age_s: float = 1.0, trigger_source: str = 'auto', on_problem=None,
                 max_pending: int = 200):
        if clock_source not in ('auto', 'system_time', 'arrival'):
            raise ConfigError(f'clock_source {clock_source!r} must be auto, system_time or arrival')
        if trigger_source not in ('auto', 'feedback', 'trigger'):
            raise ConfigError(f'trigger_source {trigger_source!r} must be auto, feedback or trigger')
        self.clock = BootClock()
        self.clock_source = clock_source
        self.error_model = error_model or gf.ErrorModel()
        self.max_fix_age_s = max_fix_age_s
        self.trigger_source = trigger_source
        self.on_problem = on_problem or (lambda what: self.problems.append(what))
        self.problems: list = []
        self.counts = Counter()
        self.latest: dict = {}               # receiver -> GnssFix
        self.best_receiver = None
        self.rtk: dict = {}                  # receiver -> last GPS_RTK fields
        self._pending: deque = deque()       # (msg, arrival_s) waiting for the clock
        self._max_pending = max_pending
        self._best_history: deque = deque(maxlen=50)
        self._triggers: list = []            # CAMERA_TRIGGER waiting for a later fix
        self._feedback_seen = False
        self._last_quat_boot_ms = -10 ** 9
        self._last_fix_t: dict = {}
        self._max_boot_s = -math.inf
        self._back: list = []                # (msg, arrival_s, boot_s) whose boot time went backwards
        self._back_ref_s = -math.inf         # the latest boot time when the first of them came
        self._fit_source = None
        self._last_best_t = -math.inf

    # --- time --------------------------------------------------------------------------------------

    def _t(self, time_us: int | None = None, boot_ms: int | None = None) -> float | None:
        if time_us is not None and time_us > gf.UNIX_THRESHOLD_US:
            return time_us * 1e-6
        boot_s = time_us * 1e-6 if time_us is not None else boot_ms * 1e-3
        return self.clock.to_time(boot_s, self.clock_source)

    def synced(self) -> bool:
        return self.clock.fit(self.clock_source) is not None

    # --- messages ----------------------------------------------------------------------------------

    def handle(self, m, arrival_s: float | None) -> list:
        """One decoded message (and its arrival time on the host clock, if known) -> events."""
        mtype = m.get_type()
        self.counts[mtype] += 1
        try:
            if mtype == 'SYSTEM_TIME':
                ev = self.clock.add_system_time(int(m.time_boot_ms), int(m.time_unix_usec))
                if arrival_s is not None and m.time_boot_ms > 0:
                    ev2 = self.clock.add_arrival(m.time_boot_ms * 1e-3, arrival_s)
                    ev = ev2 if ev == 'ignored' else ev
                return self._after_clock_update(ev)
            if mtype == 'TIMESYNC':
                if m.tc1 == 0 and m.ts1 > 0 and arrival_s is not None:
                    return self._after_clock_update(self.clock.add_arrival(m.ts1 * 1e-9, arrival_s))
                return []
            if mtype in ('GPS_RAW_INT', 'GPS2_RAW', 'ATTITUDE', 'ATTITUDE_QUATERNION', 'CAMERA_FEEDBACK',
                         'CAMERA_TRIGGER'):
                if not self.synced() and not self._has_unix_time(m):
                    if len(self._pending) >= self._max_pending:
                        self._pending.popleft()
                        self.counts['dropped_before_time_sync'] += 1
                    self._pending.append((m, arrival_s))
                    return []
                return self._timed(m, arrival_s)
            if mtype in ('GPS_RTK', 'GPS2_RTK'):
                self.rtk[0 if mtype == 'GPS_RTK' else 1] = {
                    'baseline_m': math.sqrt(m.baseline_a_mm ** 2 + m.baseline_b_mm ** 2 + m.baseline_c_mm ** 2)
                    * 1e-3, 'iar_num_hypotheses': int(m.iar_num_hypotheses), 'accuracy_mm': int(m.accuracy),
                    'nsats': int(m.nsats), 'rtk_health': int(m.rtk_health)}
        except (ValueError, OverflowError, TypeError, AttributeError) as exc:
            self.on_problem(f'{mtype} could not be used: {exc}')
        return []

    def _has_unix_time(self, m) -> bool:
        t = getattr(m, 'time_usec', None)
        return t is not None and t > gf.UNIX_THRESHOLD_US

    def _after_clock_update(self, ev: str) -> list:
        self._clock_event(ev)
        fit = self.clock.fit(self.clock_source)
        src = fit.source if fit is not None else None
        if src is not None and self._fit_source not in (None, src):
            # UNIX (SYSTEM_TIME) and host (arrival) clocks can differ by seconds: times may step.
            self.counts['clock_source_changed'] += 1
            self.on_problem(f'time sync now uses {src} instead of {self._fit_source}; stamps may step')
            self._last_fix_t.clear()
        if src is not None:
            self._fit_source = src
        return self._flush_pending()

    def _clock_event(self, ev: str) -> None:
        if ev in ('outlier', 'jump', 'reboot', 'implausible'):
            self.counts[f'clock_{ev}'] += 1
            self.on_problem(f'autopilot clock: {ev} ({self.clock.detail or "SYSTEM_TIME/TIMESYNC disagrees with the fit"})')
            if ev == 'reboot':
                self.latest.clear()
                self._last_fix_t.clear()
                self._last_best_t = -math.inf
                # Data boot times are compared with data boot times only (pending data lags the
                # clock messages by seconds); a reboot seen on the clock restarts that comparison.
                self._max_boot_s = -math.inf

    def _flush_pending(self) -> list:
        out = []
        if self.synced():
            while self._pending:
                m, arr = self._pending.popleft()
                out += self._timed(m, arr)
        return out

    def _boot_time_s(self, m, mtype: str):
        if mtype in self.GPS_TYPES or mtype in ('CAMERA_FEEDBACK', 'CAMERA_TRIGGER'):
            t = int(m.time_usec)
            return t * 1e-6 if 0 < t <= gf.UNIX_THRESHOLD_US else None
        return int(m.time_boot_ms) * 1e-3

    def _timed(self, m, arrival_s) -> list:
        mtype = m.get_type()
        boot_s = self._boot_time_s(m, mtype)
        if boot_s is not None:
            if boot_s < self._max_boot_s - 1.0:
                # Data stamped far before what we have seen: the autopilot rebooted, if it repeats
                # (one wild time_boot_ms, e.g. 0, is not a reboot). Held until then; on a reboot the
                # old clock fit is void: they wait for the new SYSTEM_TIME/TIMESYNC.
                if self._back and boot_s < self._back[-1][2] - 1.0:
                    self._drop_back()
                if not self._back:
                    self._back_ref_s = self._max_boot_s
                self._back.append((m, arrival_s, boot_s))
                if len({b for _, _, b in self._back}) < self.REBOOT_CONFIRM:
                    return []
                self.clock.reset()
                self.clock.detail = 'data boot times started again: the autopilot rebooted'
                self._clock_event('reboot')
                self._max_boot_s = min(b for _, _, b in self._back)   # they come back through here, in order
                self._pending.extend((bm, ba) for bm, ba, _ in self._back)
                self._back = []
                return []
            if self._back and boot_s > self._back_ref_s + 2.0:
                # The old boot clock ran on for 2 s more (stragglers sent before a reboot stop sooner).
                self._drop_back()
            self._max_boot_s = max(self._max_boot_s, boot_s)
        if mtype in self.GPS_TYPES:
            return self._gps(m, self.GPS_TYPES[mtype], arrival_s)
        if mtype == 'ATTITUDE_QUATERNION' or mtype == 'ATTITUDE':
            return self._attitude(m, mtype, arrival_s)
        if mtype == 'CAMERA_FEEDBACK':
            return self._feedback(m)
        return self._trigger(m)

    def _drop_back(self) -> None:
        """The boot times that went backwards did not repeat: wild values, not a reboot."""
        n, self._back = len(self._back), []
        self.counts['boot_time_outliers'] += n
        self.on_problem(f'{n} message(s) with a boot time before the ones seen (e.g. time_boot_ms 0) ignored: '
                        'not a reboot')

    def _gps(self, m, receiver: int, arrival_s=None) -> list:
        raw = raw_gnss(m, receiver)
        if raw.time_usec == 0:
            # Receivers without a time yet send 0: the arrival time is the best we have.
            t = arrival_s
            if t is None and self.synced() and self._max_boot_s > -math.inf:
                t = self._t(boot_ms=int(self._max_boot_s * 1000))
        else:
            t = self._t(time_us=raw.time_usec)
        if t is None:
            self.counts['fix_without_time'] += 1
            return []
        last = self._last_fix_t.get(receiver)
        if last is not None and t <= last and raw.fix_type >= gf.FIX_2D:
            self.counts['fix_time_not_increasing'] += 1
            self.on_problem(f'receiver {receiver}: fix time {t:.3f} is not after the previous {last:.3f}; dropped')
            return []
        res = gf.make_fix(raw, t, self.error_model)
        if res.fix is None or res.problem:
            self.counts['fix_rejected'] += 1
            self.on_problem(f'receiver {receiver}: {res.problem}')
            return []
        fix = res.fix
        if fix.has_position:
            self._last_fix_t[receiver] = t
        self.latest[receiver] = fix
        self.counts[f'fix_{receiver}_{gf.fix_name(fix.fix_type)}'] += 1
        best = gf.choose_best(self.latest, t, self.max_fix_age_s)
        if best is None:
            # No receiver has a position: the no-fix state of the chosen one is itself news on /gps/fix.
            best = self.best_receiver if self.best_receiver in self.latest else receiver
        switched = best != self.best_receiver
        self.best_receiver = best
        # /gps/fix carries at most one position per epoch, in strictly increasing time.
        is_best = best == receiver and (fix.t_s > self._last_best_t or not fix.has_position)
        out = [FixEvent(fix, is_best)]
        if not is_best and switched and best is not None and best != receiver:
            # Another receiver just became the best one: its latest fix (already on its own topic)
            # goes to /gps/fix now rather than one epoch late.
            other = self.latest[best]
            if other.has_position and other.t_s > self._last_best_t:
                out.append(FixEvent(other, True, per_receiver=False))
                fix_best = other
            else:
                fix_best = None
        else:
            fix_best = fix if is_best else None
        if fix_best is not None and fix_best.has_position:
            self._last_best_t = fix_best.t_s
            self._best_history.append(fix_best)
            out += self._resolve_triggers()
        return out

    def _attitude(self, m, mtype: str, arrival_s) -> list:
        if mtype == 'ATTITUDE_QUATERNION':
            self._last_quat_boot_ms = int(m.time_boot_ms)
            q = np.array([m.q2, m.q3, m.q4, m.q1], float)
            norm = float(np.linalg.norm(q))
            if not np.all(np.isfinite(q)) or not 0.9 < norm < 1.1:
                self.counts['attitude_rejected'] += 1
                self.on_problem(f'ATTITUDE_QUATERNION with a non-unit quaternion (|q| = {norm:.3g})')
                return []
            q_ned_frd = (m.q2 / norm, m.q3 / norm, m.q4 / norm, m.q1 / norm)
        else:
            if abs(int(m.time_boot_ms) - self._last_quat_boot_ms) < 1000:
                return []   # quaternions are flowing: same attitude, without Euler's gimbal lock
            angles = (m.roll, m.pitch, m.yaw)
            if not all(math.isfinite(a) for a in angles):
                self.counts['attitude_rejected'] += 1
                self.on_problem('ATTITUDE with non-finite angles')
                return []
            q_ned_frd = quat_ned_frd_from_euler(*angles)
        rates = np.array([m.rollspeed, -m.pitchspeed, -m.yawspeed], float)
        t = self._t(boot_ms=int(m.time_boot_ms))
        if t is None:
            return []
        q_out = np.array(quat_enu_flu_from_quat_ned_frd(q_ned_frd))
        return [Attitude(t, q_out, rates if np.all(np.isfinite(rates)) else None, mtype)]

    def _feedback(self, m) -> list:
        if self.trigger_source == 'trigger':
            return []
        self._feedback_seen = True
        t = self._t(time_us=int(m.time_usec))
        if t is None:
            return []
        # The trigger of this very exposure, if it came first, is superseded by the feedback.
        self._triggers = [tr for tr in self._triggers if abs(tr[0] - t) > 0.05]
        lat, lon = m.lat * 1e-7, m.lng * 1e-7
        if not (-90 <= lat <= 90 and -180 <= lon <= 180) or (m.lat == 0 and m.lng == 0) \
                or not math.isfinite(m.alt_msl):
            self.counts['trigger_rejected'] += 1
            self.on_problem(f'CAMERA_FEEDBACK {m.img_idx} without a usable position')
            return []
        h = float(m.alt_msl) + gf.undulation_m(lat, lon)
        ref = self.latest.get(self.best_receiver) if self.best_receiver is not None else None
        return [Trigger(t, int(m.img_idx), 'CAMERA_FEEDBACK', _exposure_fix(t, lat, lon, h, ref, 'CAMERA_FEEDBACK'))]

    def _trigger(self, m) -> list:
        if self.trigger_source == 'feedback' or (self.trigger_source == 'auto' and self._feedback_seen):
            return []
        t = self._t(time_us=int(m.time_usec))
        if t is None:
            return []
        self._triggers.append((t, int(m.seq)))
        return self._resolve_triggers() if self.trigger_source == 'trigger' else []

    def _resolve_triggers(self) -> list:
        """CAMERA_TRIGGER events between two fixes of the chosen receiver get an interpolated position."""
        if not self._triggers or len(self._best_history) < 2:
            return []
        out, keep = [], []
        hist = list(self._best_history)
        for t, seq in self._triggers:
            if self.trigger_source == 'auto' and self._feedback_seen:
                continue
            if t > hist[-1].t_s:
                keep.append((t, seq))
                continue
            for a, b in zip(hist[:-1], hist[1:]):
                if a.t_s <= t <= b.t_s and b.t_s - a.t_s < 2.0:
                    lat, lon, h = gf.interpolate(a, b, t)
                    worse = a if a.sigma_h_m >= b.sigma_h_m else b
                    out.append(Trigger(t, seq, 'CAMERA_TRIGGER', _exposure_fix(t, lat, lon, h, worse, 'CAMERA_TRIGGER')))
                    break
            else:
                self.counts['trigger_without_fix'] += 1
        self._triggers = keep
        return out

    def flush(self) -> list:
        """End of input: whatever still waits on the clock is lost; count it."""
        if self._pending:
            self.counts['dropped_before_time_sync'] += len(self._pending)
            self._pending.clear()
        return []

    def diagnostics(self) -> dict:
        d = {}
        best = self.latest.get(self.best_receiver) if self.best_receiver is not None else None
        if best is not None:
            d.update({'fix_type': gf.fix_name(best.fix_type), 'satellites': best.sats,
                      'best_receiver': best.receiver, 'sigma_h_m': best.sigma_h_m})
        for rx, rtk in self.rtk.items():
            for k, v in rtk.items():
                d[f'rtk{rx + 1}_{k}'] = v
        for k, v in self.clock.quality(self.clock_source).items():
            d[f'time_sync_{k}'] = v
        return d


def fixes_from_messages(messages, **ingest_kwargs) -> tuple[list, Ingest]:
    """[(msg, arrival_s)] -> every FixEvent in order (what the node publishes), and the Ingest used."""
    ing = Ingest(**ingest_kwargs)
    out = []
    for m, t in messages:
        for ev in ing.handle(m, t):
            if isinstance(ev, FixEvent):
                out.append(ev)
    ing.flush()
    return out, ing


class TlogFixes:
    """A MAVLink telemetry log (.tlog) as a GnssSource (io/gnss_source.py): the fixes the MAVLink node publishes on
    /gps/fix (the best receiver's; `all_receivers`: every receiver's as well), from `read_tlog` and `Ingest` with
    `ingest_kwargs`; counts: the link's (io/mavlink_framing.py LinkStats) and the fixes given."""

    def __init__(self, path, all_receivers: bool = False, **ingest_kwargs):
        self.name = str(path)
        self.all_receivers = all_receivers
        self.ingest_kwargs = ingest_kwargs
        self._counts: dict = {}

    def fixes(self):
        from photogram_ros.io.mavlink_framing import read_tlog
        messages, stats = read_tlog(self.name)
        events, _ = fixes_from_messages(messages, **self.ingest_kwargs)
        out = [ev.fix for ev in events if ev.best or self.all_receivers]
        self._counts = {'messages': len(messages), 'fixes': len(out),
                        **{k: v for k, v in stats.as_dict().items() if k != 'by_type'}}
        yield from out

    def counts(self) -> dict:
        return dict(self._counts)
