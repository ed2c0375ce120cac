"""MAVLink in: links (serial, UDP, TCP, .tlog, raw bytes from a bag), framing, signing, decoding.

`MavlinkStream` frames MAVLink 1 and 2 packets out of arbitrary byte chunks and decodes them with
pymavlink (ardupilotmega dialect, which includes common). It does its own framing because
pymavlink's parser, after a false start byte inside damaged data, swallows the length that false
header claims, losing the good packets behind it; here a candidate that fails its CRC is skipped by
one byte only, so every intact packet after damage is still found.

`Ingest` turns decoded messages into what the node publishes (fixes, attitude, camera triggers),
with the boot clock mapped to UNIX/host time. It has no ROS in it, so `photogram-ros fixes` prints
exactly what the node publishes.
"""

from __future__ import annotations

import hashlib
import math
import os
import struct
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from photogram_ros.core import gnss_fix as gf
from photogram_ros.core.timesync import BootClock
from photogram_ros.errors import ConfigError, MavlinkError

STX_V1, STX_V2 = 0xFE, 0xFD
_MIN_LEN = 8                      # shortest MAVLink 1 packet (empty payload)
_TLOG_STAMP_MIN_US = 946684800 * 10 ** 6      # 2000-01-01
_TLOG_STAMP_MAX_US = 4102444800 * 10 ** 6     # 2100-01-01


def signing_key(secret: str) -> bytes:
    """A 32-byte MAVLink 2 key: 64 hex digits as given, anything else hashed like MAVProxy's passphrase."""
    s = secret.strip()
    if len(s) == 64:
        try:
            return bytes.fromhex(s)
        except ValueError:
            pass
    return hashlib.sha256(s.encode('utf-8')).digest()


@dataclass
class LinkStats:
    bytes_in: int = 0
    packets: int = 0               # decoded (accepted) packets
    crc_errors: int = 0            # a packet started where one was due but failed its CRC / length check
    junk_bytes: int = 0            # bytes that belonged to no decodable packet
    unknown_msgid: int = 0
    signature_rejected: int = 0    # signed with a wrong key / replayed timestamp / wrong link id
    unsigned_rejected: int = 0     # unsigned while signing is required
    filtered: int = 0              # from another system or component
    seq_lost: int = 0              # sequence-number gaps (packets lost on the link)
    by_type: Counter = field(default_factory=Counter)

    def as_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != 'by_type'}
        d['by_type'] = dict(self.by_type)
        return d


class MavlinkStream:
    """Feed bytes in, get decoded pymavlink messages out; counts every kind of damage."""

    def __init__(self, secret_key: bytes | None = None, allow_unsigned: bool = False, link_id: int = -1,
                 sysid: int = 0, compid: int = 0, record_gap: int = 0):
        self.mav = mavlink2.MAVLink(None)
        self.mav.robust_parsing = False
        self.require_signed = secret_key is not None and not allow_unsigned
        self.link_id = link_id
        self.sysid, self.compid = sysid, compid
        self.record_gap = record_gap        # bytes between packets (8 in a .tlog: the timestamp)
        self._plain = self.mav
        if secret_key is not None:
            if len(secret_key) != 32:
                raise ConfigError('a MAVLink 2 signing key has 32 bytes (64 hex digits)')
            self.mav.signing.secret_key = secret_key
            # Unsigned packets go through a key-less decoder and are judged in _accept, so that they
            # are counted apart from bad signatures (pymavlink's unsigned callback also lets badly
            # signed packets through).
            self._plain = mavlink2.MAVLink(None)
            self._plain.robust_parsing = False
        self.stats = LinkStats()
        self._buf = bytearray()
        self._expect = record_gap           # offset in _buf where the next packet is due (-1: unknown)
        self._consumed = 0
        self._last_seq: dict = {}

    def feed(self, data: bytes, final: bool = False, with_offsets: bool = False) -> list:
        """Add bytes; return the messages completed by them (with their buffer offsets if asked).

        `final` says no more bytes follow (end of a file), so a truncated candidate at the end is
        given up instead of waited for.
        """
        self.stats.bytes_in += len(data)
        buf = self._buf
        if data:
            buf += data
        out = []
        i = 0
        n = len(buf)
        decode, decode_plain = self.mav.decode, self._plain.decode
        stats = self.stats
        while n - i >= _MIN_LEN:
            b0 = buf[i]
            if b0 != STX_V2 and b0 != STX_V1:
                e = self._expect
                if i < e < n and e - i <= self.record_gap and buf[e] in (STX_V1, STX_V2):
                    j = e           # the .tlog timestamp before a due packet
                else:
                    j = self._find_stx(buf, i, n)
                if j < 0:
                    self._junk(i, n)
                    i = n
                    break
                self._junk(i, j)
                i = j
                if n - i < _MIN_LEN:
                    break
                b0 = buf[i]
            if b0 == STX_V2:
                flags = buf[i + 2]
                if flags & 0xFE:
                    i = self._skip(i)
                    continue
                total = buf[i + 1] + (25 if flags & 1 else 12)
            else:
                total = buf[i + 1] + 8
            if i + total > n:
                if not final:
                    break
                i = self._skip(i)
                continue
            pkt = buf[i:i + total]
            try:
                m = decode(pkt) if b0 == STX_V1 or flags & 1 else decode_plain(pkt)
            except mavlink2.MAVError as exc:
                if 'signature' in str(exc.message):
                    stats.signature_rejected += 1
                    i += total
                    self._expect = i + self.record_gap
                else:
                    i = self._skip(i)
                continue
            except Exception:   # pymavlink raises bare struct/value errors on some malformed payloads
                i = self._skip(i)
                continue
            if isinstance(m, mavlink2.MAVLink_unknown):
                # An unknown id cannot be CRC-checked: trust its framing only where a packet was due,
                # another one follows it, and no good packet hides inside the span it claims.
                nxt = i + total + self.record_gap
                if i == self._expect and nxt + _MIN_LEN > n and not final:
                    break                       # decide when the next packet is here
                if i == self._expect and (nxt >= n or self._decodes_at(buf, nxt)) \
                        and not self._packet_inside(buf, i + 1, i + total):
                    stats.unknown_msgid += 1
                    i += total
                    self._expect = nxt
                else:
                    i = self._skip(i)
                continue
            start = i
            i += total
            self._expect = i + self.record_gap
            if not self._accept(m, pkt, flags if b0 == STX_V2 else 0):
                continue
            out.append((m, start) if with_offsets else m)
        if final and i < n:
            self._junk(i, n)
            i = n
        if i:
            del buf[:i]
            self._expect = self._expect - i if self._expect >= i else -1
            self._consumed += i
        return out

    @staticmethod
    def _find_stx(buf, i: int, n: int) -> int:
        # Bounded windows: an unbounded find of a start byte absent from the rest of a large buffer
        # would rescan it for every packet.
        while i < n:
            end = min(n, i + 1024)
            j2, j1 = buf.find(b'\xfd', i, end), buf.find(b'\xfe', i, end)
            if j2 >= 0 or j1 >= 0:
                return j1 if j2 < 0 else (j2 if j1 < 0 else min(j1, j2))
            i = end
        return -1

    def _decodes_at(self, buf, i: int) -> bool:
        """Whether a known, CRC-valid packet starts at buf[i] (checks the framing of an unknown one)."""
        b0 = buf[i]
        if b0 == STX_V2 and i + 3 <= len(buf) and not buf[i + 2] & 0xFE:
            total = buf[i + 1] + (25 if buf[i + 2] & 1 else 12)
        elif b0 == STX_V1 and i + 2 <= len(buf):
            total = buf[i + 1] + 8
        else:
            return False
        if i + total > len(buf):
            return False
        try:
            m = self._plain.decode(buf[i:i + total]) if self._plain is not self.mav or b0 == STX_V1 \
                else self.mav.decode(buf[i:i + total])
        except Exception:
            return False
        return not isinstance(m, mavlink2.MAVLink_unknown)

    def _packet_inside(self, buf, i: int, j: int) -> bool:
        while i < j:
            k2, k1 = buf.find(b'\xfd', i, j), buf.find(b'\xfe', i, j)
            k = k1 if k2 < 0 else (k2 if k1 < 0 else min(k1, k2))
            if k < 0:
                return False
            if self._decodes_at(buf, k):
                return True
            i = k + 1
        return False

    def _junk(self, i: int, j: int) -> None:
        """Count bytes [i, j) as junk, except a record gap (the .tlog timestamp) before a due packet."""
        e = self._expect
        if e >= 0 and self.record_gap:
            overlap = max(0, min(j, e) - max(i, e - self.record_gap))
            self.stats.junk_bytes += (j - i) - overlap
        else:
            self.stats.junk_bytes += j - i

    def _skip(self, i: int) -> int:
        if i == self._expect:
            self.stats.crc_errors += 1
            self._expect = -1
        self._junk(i, i + 1)
        return i + 1

    def _accept(self, m, pkt, flags: int) -> bool:
        stats = self.stats
        hdr = m._header
        if self.require_signed and not (flags & 1):
            stats.unsigned_rejected += 1
            return False
        if flags & 1 and self.mav.signing.secret_key is not None:
            if self.link_id >= 0 and pkt[-13] != self.link_id:
                stats.signature_rejected += 1
                return False
        src = (hdr.srcSystem, hdr.srcComponent)
        last = self._last_seq.get(src)
        if last is not None:
            gap = (hdr.seq - last - 1) & 0xFF
            if gap and gap < 128:          # larger "gaps" are reordering or a restarted sender
                stats.seq_lost += gap
        self._last_seq[src] = hdr.seq
        if (self.sysid and hdr.srcSystem != self.sysid) or (self.compid and hdr.srcComponent != self.compid):
            stats.filtered += 1
            return False
        stats.packets += 1
        stats.by_type[m.get_type()] += 1
        return True

    @property
    def consumed(self) -> int:
        """Bytes consumed from the start of the stream (offsets from feed() are relative to this)."""
        return self._consumed


def read_tlog(path, stream: MavlinkStream | None = None):
    """Every message of a Mission Planner .tlog with its recorded UNIX time (s, or None if unreadable).

    The file is framed as a byte stream (so damage anywhere only costs the packets it hits); each
    packet's time is the big-endian microsecond stamp in the 8 bytes before it.
    """
    try:
        with open(path, 'rb') as f:
            data = f.read()
    except OSError as exc:
        raise MavlinkError(f'cannot read telemetry log {path}: {exc}') from exc
    stream = stream or MavlinkStream(record_gap=8)
    if stream.record_gap != 8:
        raise ConfigError('read_tlog needs a MavlinkStream made with record_gap=8')
    out = []
    for m, off in stream.feed(data, final=True, with_offsets=True):
        t = None
        if off >= 8:
            us = struct.unpack_from('>Q', data, off - 8)[0]
            if _TLOG_STAMP_MIN_US < us < _TLOG_STAMP_MAX_US:
                t = us * 1e-6
        out.append((m, t))
    return out, stream.stats


# --- live links ----------------------------------------------------------------------------------

_URL_PREFIXES = ('udpin:', 'udpout:', 'udp:', 'udpbcast:', 'tcp:', 'tcpin:')


def is_live_url(url: str) -> bool:
    return url.startswith(_URL_PREFIXES) or url.startswith('/dev/') or url.upper().startswith('COM')


class Link:
    """A live byte link opened through pymavlink's transports; read() hands back raw bytes."""

    def __init__(self, url: str, baud: int = 57600):
        from pymavlink import mavutil
        if not is_live_url(url):
            raise MavlinkError(f'{url!r} is not a link: use udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, '
                               'tcpin:HOST:PORT or a serial device such as /dev/ttyUSB0')
        self.url = url
        try:
            self.conn = mavutil.mavlink_connection(url, baud=baud, autoreconnect=True, source_system=255,
                                                   source_component=191)
        except Exception as exc:   # pymavlink raises socket, serial and OS errors alike
            raise MavlinkError(f'cannot open MAVLink link {url}: {exc}') from exc

    def read(self, timeout_s: float = 0.2) -> bytes:
        if not self.conn.select(timeout_s):
            return b''
        data = self.conn.recv()
        return bytes(data) if data else b''

    def close(self) -> None:
        try:
            self.conn.close()
        except Exception:
            pass


# --- from messages to fixes, attitude and triggers -----------------------------------------------


# Attitude conversions run at 10-50 Hz per vehicle: plain quaternion algebra, (x, y, z, w) order.
_H = math.sqrt(0.5)
_Q_ENU_NED = (_H, _H, 0.0, 0.0)      # 180 deg about (x + y) / sqrt(2): swaps x/y, flips z
_Q_FRD_FLU = (1.0, 0.0, 0.0, 0.0)    # 180 deg about x


def _qmul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)


def quat_ned_frd_from_euler(roll: float, pitch: float, yaw: float):
    """Aerospace ZYX Euler angles -> quaternion of body FRD in NED (x, y, z, w)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def enu_flu_quat(q_ned_frd):
    """Quaternion of FRD in NED -> quaternion of FLU in ENU (REP-103), w >= 0."""
    q = _qmul(_qmul(_Q_ENU_NED, q_ned_frd), _Q_FRD_FLU)
    return q if q[3] >= 0 else tuple(-v for v in q)


@dataclass
class Attitude:
    t_s: float
    q_enu_flu_xyzw: np.ndarray
    rates_flu_rad_s: np.ndarray | None
    source: str


@dataclass
class Trigger:
    t_s: float
    seq: int
    lat_deg: float
    lon_deg: float
    h_m: float
    source: str                   # 'CAMERA_FEEDBACK' or 'CAMERA_TRIGGER' (position interpolated from fixes)
    fix_type: int
    cov_enu_m2: tuple
    cov_type: int


@dataclass
class FixEvent:
    fix: gf.Fix
    best: bool                    # goes to /gps/fix (the chosen receiver, newer than the last one there)
    per_receiver: bool = True     # goes to /gps/fix_<receiver + 1> (False: it went there already)


def raw_gnss(m, receiver: int) -> gf.RawGnss:
    """GPS_RAW_INT / GPS2_RAW -> RawGnss (extension fields read as 0 when the sender omitted them)."""
    g = getattr
    return gf.RawGnss(receiver=receiver, time_usec=int(m.time_usec), fix_type=int(m.fix_type), lat_e7=int(m.lat),
                      lon_e7=int(m.lon), alt_msl_mm=int(m.alt), alt_ellipsoid_mm=int(g(m, 'alt_ellipsoid', 0) or 0),
                      eph=int(m.eph), epv=int(m.epv), h_acc_mm=int(g(m, 'h_acc', 0) or 0),
                      v_acc_mm=int(g(m, 'v_acc', 0) or 0), sats=int(m.satellites_visible),
                      sysid=m._header.srcSystem, compid=m._header.srcComponent)


class Ingest:
    """Decoded messages -> FixEvent / Attitude / Trigger, stamped on the UNIX (or host) clock.

    Items that need the boot clock wait (a few seconds at most) until the first SYSTEM_TIME or
    TIMESYNC arrives, then come out in order.
    """

    GPS_TYPES = {'GPS_RAW_INT': 0, 'GPS2_RAW': 1}

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
        self.latest: dict = {}               # receiver -> Fix
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
        if ev in ('outlier', 'jump', 'reboot'):
            self.counts[f'clock_{ev}'] += 1
            self.on_problem(f'autopilot clock: {ev} (SYSTEM_TIME/TIMESYNC disagrees with the fit)')
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
                # Data stamped far before what we have seen: the autopilot rebooted. Its old clock
                # fit is void; wait for the new SYSTEM_TIME/TIMESYNC.
                self.clock.reset()
                self._clock_event('reboot')
                self._max_boot_s = boot_s
                self._pending.append((m, arrival_s))
                return []
            self._max_boot_s = max(self._max_boot_s, boot_s)
        if mtype in self.GPS_TYPES:
            return self._gps(m, self.GPS_TYPES[mtype], arrival_s)
        if mtype == 'ATTITUDE_QUATERNION' or mtype == 'ATTITUDE':
            return self._attitude(m, mtype, arrival_s)
        if mtype == 'CAMERA_FEEDBACK':
            return self._feedback(m)
        return self._trigger(m)

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
        q_out = np.array(enu_flu_quat(q_ned_frd))
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
        ft, cov, ct = (ref.fix_type, ref.cov_enu_m2, ref.cov_type) if ref else (gf.NO_FIX, (0.0, 0.0, 0.0),
                                                                               gf.COV_UNKNOWN)
        return [Trigger(t, int(m.img_idx), lat, lon, h, 'CAMERA_FEEDBACK', ft, cov, ct)]

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
                    out.append(Trigger(t, seq, lat, lon, h, 'CAMERA_TRIGGER', worse.fix_type, worse.cov_enu_m2,
                                       worse.cov_type))
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


def file_kind(path: str) -> str:
    low = str(path).lower()
    if low.endswith(('.bin', '.log')) and os.path.isfile(path):
        with open(path, 'rb') as f:
            head = f.read(3)
        if head[:2] == b'\xa3\x95':
            return 'dataflash'
    if os.path.isdir(path):
        return 'bag'
    return 'tlog'

