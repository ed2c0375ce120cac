"""Camera positions at exposure times from a post-processed antenna track (PPK geotagging).

In: an `AntennaTrack` (antenna solutions in GPS time, ECEF, ENU covariance and quality per epoch on
RTKLIB's scale Q, beside the file's own: what the readers of io/trajectory_formats.py read) and
`CameraEvent`s (exposure times in GPS time, with the antenna -> camera offset of a DJI Timestamp.MRK or the body attitude for a lever arm: what
io/camera_events.py reads). Out: `place_exposures` -> one `PlacedExposure` per event (camera and
antenna WGS84 position, ellipsoidal height, per-axis horizontal and vertical 1-sigma, how it was
found) and the problems of the events it could not place, each naming the event's line.

- Time: every time is seconds since the GPS epoch (1980-01-06 00:00:00) on the GPS time scale;
  UTC inputs are converted with the leap seconds in force (`utc_unix_to_gps_s`, GPST = UTC + 18 s
  since 2017).
- Placement: a track whose epochs are the events themselves (RTKLIB/Emlid `*_events.pos`: every event
  has an epoch within `at_event_tolerance_s`) is read at the events; a trajectory (1-20 Hz) is
  interpolated in ECEF between the two epochs around the exposure, never past its ends and never
  across a gap longer than `max_gap_s`: linearly by default, as the surveyors' PPK tools do (a public
  M300 + Waypoint workflow interpolates latitude, longitude and H-Ell linearly; on a real 5 Hz Waypoint
  track the cubic below differs from it by 0.5 mm median on the lines but up to 2.4 cm in the turns,
  where the epochs' cm-level height noise is amplified), or with `interpolation='cubic'`: Hermite with
  centred-difference velocities from the epochs on either side (exact under constant acceleration,
  where linear interpolation of a 5 Hz track cuts a 3 m/s^2 manoeuvre by up to 1.5 cm), linear next
  to a gap or an end. Every exposure is first moved by `event_delay_s` from its event mark (a
  shutter that opens after the mark); a track of seconds of week without its week
  (`AntennaTrack.week_known`) is put in the events' week (`AntennaTrack.in_week_of`).
- Lever arm: a per-event offset in local north, east, down (the MRK's N, E, V: camera = antenna + N
  north, + E east, height - V), or the antenna's position relative to the camera in the body FRD frame
  (`lever_arm_frd_m`, as the simulator and bundle_node state it) turned by the event's attitude; an
  event without attitude takes the track's direction of travel as heading, level.
- Accuracy: per-axis horizontal sigma sqrt((sdn^2 + sde^2) / 2) and vertical sdu of the epoch (the
  worse of the two around an interpolated exposure), times `sigma_scale`, at least the floor of its
  quality class (`Q_FLOOR_M`: a float or single solution's formal sigma is optimistic).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from photogram_ros.core.geodesy import ecef_R_enu, ecef_to_geodetic, geodetic_to_ecef
from photogram_ros.core.gnss_fix import COV_DIAGONAL_KNOWN, COV_UNKNOWN, Q_NAMES, GnssFix
from photogram_ros.core.rotations import ned_R_frd_from_euler
from photogram_ros.errors import DataError
from photogram_ros.params import param, validate

GPS_EPOCH_UNIX_S = 315964800          # 1980-01-06T00:00:00Z
SECONDS_PER_WEEK = 604800
# GPS - UTC (s) from each UNIX time on (the leap seconds since 2006; 18 s since 2017-01-01).
LEAP_SECONDS = ((1136073600, 14), (1230768000, 15), (1341100800, 16), (1435708800, 17), (1483228800, 18))

# The floor of each quality's per-axis (horizontal, vertical) 1-sigma, m, on the one quality scale
# (core/gnss_fix.py Q_NAMES: RTKLIB's Q).
Q_FLOOR_M = {1: (0.0, 0.0), 2: (0.10, 0.20), 3: (0.5, 1.0), 4: (0.5, 1.0), 5: (1.5, 3.0), 6: (0.05, 0.10)}

# DJI RTK position flag (the MRK's `flag,Q` and a photo's XMP `drone-dji:RtkFlag`; DJI OSDK
# Telemetry::RTK posHealthFlag) -> the common quality scale (RTKLIB Q: 1 fix, 2 float, 3 sbas, 4 dgps,
# 5 single). 48/50 integer (L1, narrow-lane) -> fix; 49 wide-lane integer and 32-34 float -> float;
# 18 SBAS -> sbas; 17 pseudorange differential, 20 OmniSTAR VBS -> dgps; 16 single point, 19 propagated
# by a Kalman filter, 8 Doppler, 1-2 fixed by command -> single. 0 (no solution) maps to nothing.
DJI_RTK_FLAG_Q = {50: 1, 48: 1, 49: 2, 34: 2, 33: 2, 32: 2, 18: 3, 17: 4, 20: 4, 16: 5, 19: 5, 8: 5, 1: 5, 2: 5}
DJI_RTK_FLAG_NAMES = {50: 'fixed (narrow-lane)', 48: 'fixed (L1)', 49: 'wide-lane integer', 34: 'float', 33: 'float',
                      32: 'float', 18: 'SBAS', 17: 'differential', 20: 'OmniSTAR', 16: 'single', 19: 'propagated',
                      8: 'Doppler', 1: 'fixed by command', 2: 'fixed height', 0: 'no solution'}


def leap_seconds(t_unix_s: float) -> int:
    """GPS - UTC in seconds at a UNIX (UTC) time (13 before 2006)."""
    n = 13
    for since, leap in LEAP_SECONDS:
        if t_unix_s >= since:
            n = leap
    return n


def utc_unix_to_gps_s(t_unix_s: float) -> float:
    """UNIX time (UTC) -> seconds since the GPS epoch on the GPS time scale."""
    return float(t_unix_s) - GPS_EPOCH_UNIX_S + leap_seconds(t_unix_s)


def gps_s_to_utc_unix(t_gps_s: float) -> float:
    """Seconds since the GPS epoch (GPS time) -> UNIX time (UTC)."""
    approx = float(t_gps_s) + GPS_EPOCH_UNIX_S
    return approx - leap_seconds(approx - 18)


def week_tow_to_gps_s(week: int, tow_s: float) -> float:
    """GPS week and seconds of week -> seconds since the GPS epoch."""
    return int(week) * SECONDS_PER_WEEK + float(tow_s)


def gps_s_to_week_tow(t_gps_s: float) -> tuple[int, float]:
    week = int(t_gps_s // SECONDS_PER_WEEK)
    return week, float(t_gps_s - week * SECONDS_PER_WEEK)


@dataclass
class AntennaTrack:
    """Antenna solutions of one post-processing run, in time order: the epochs' fixes in columns (`fix(k)`,
    `fixes()`: each a core.gnss_fix.GnssFix, the one fix type; the columns are what interpolation works on)."""

    t_gps_s: np.ndarray        # (N,) seconds since the GPS epoch, GPS time
    ecef_m: np.ndarray         # (N, 3) antenna position, WGS84 ECEF
    cov_enu_m2: np.ndarray     # (N, 3, 3) ENU covariance (zeros where the file gave none)
    q: np.ndarray              # (N,) RTKLIB quality: 1 fix, 2 float, 3 sbas, 4 dgps, 5 single, 6 ppp
    line: np.ndarray           # (N,) line number of each epoch in its file
    source: str = ''           # the file, for messages
    notes: list = field(default_factory=list)
    format: str = ''           # the format it was read as ('RTKLIB .pos', 'NovAtel GrafNav/Inertial Explorer', ...)
    time_system: str = 'GPST'  # the file's own time system (GPST, UTC, ...); t_gps_s is converted to GPS time
    q_native: np.ndarray | None = None   # (N,) the format's own quality number or name, as written
    week_known: bool = True    # False: t_gps_s holds seconds of an unknown GPS week (a file without dates)

    def __len__(self) -> int:
        return len(self.t_gps_s)

    def sigma_enu_m(self) -> np.ndarray:
        """(N, 3) per-epoch 1-sigma east, north, up (0 where the file gave none)."""
        return np.sqrt(np.maximum(np.diagonal(self.cov_enu_m2, axis1=1, axis2=2), 0.0))

    def in_week_of(self, t_gps_s: float) -> 'AntennaTrack':
        """A track of seconds of week (`week_known` False) put in the GPS week of `t_gps_s` (an event's time);
        a track that passes the end of the week goes on into the next one. Itself when its week is known."""
        if self.week_known:
            return self
        week = int(t_gps_s // SECONDS_PER_WEEK)
        sow = np.asarray(self.t_gps_s, float)
        wraps = np.concatenate([[0], np.cumsum(np.diff(sow) < -SECONDS_PER_WEEK / 2)])
        t = week * SECONDS_PER_WEEK + sow + wraps * SECONDS_PER_WEEK
        # the events may start in the week after the one the track starts in
        if t[0] - t_gps_s > SECONDS_PER_WEEK / 2:
            t -= SECONDS_PER_WEEK
        elif t_gps_s - t[-1] > SECONDS_PER_WEEK / 2:
            t += SECONDS_PER_WEEK
        out = AntennaTrack(t, self.ecef_m, self.cov_enu_m2, self.q, self.line, self.source, list(self.notes),
                           self.format, self.time_system, self.q_native, True)
        out.notes.append(f'{self.source}: times are seconds of week; GPS week {int(t[0] // SECONDS_PER_WEEK)} taken '
                         'from the events')
        return out

    def fix(self, k: int) -> GnssFix:
        """Epoch k as a GnssFix: stamped on the UNIX clock (UTC, from GPS time), ellipsoidal, its covariance
        (known where the file gave sigmas), its quality and the file's own beside it, the format as its source."""
        lat, lon, h = (float(v) for v in ecef_to_geodetic(*self.ecef_m[k]))
        cov = self.cov_enu_m2[k]
        native = None if self.q_native is None else self.q_native[k]
        return GnssFix(lat, lon, h, cov, int(round(gps_s_to_utc_unix(self.t_gps_s[k]) * 1e9)),
                       cov_type=COV_DIAGONAL_KNOWN if np.any(cov) else COV_UNKNOWN, quality=int(self.q[k]), source=self.format or self.source,
                       quality_native=int(native) if isinstance(native, (int, np.integer)) else None,
                       native_scale=self.format)

    def fixes(self):
        """Every epoch as a GnssFix (`fix`), in time order."""
        return (self.fix(k) for k in range(len(self)))

    def median_interval_s(self) -> float:
        d = np.diff(self.t_gps_s)
        return float(np.median(d)) if len(d) else math.inf


@dataclass
class CameraEvent:
    """One exposure as the drone recorded it."""

    seq: int                               # the event's own number (MRK index, CAM image number, ...)
    t_gps_s: float                         # exposure time, seconds since the GPS epoch (GPS time)
    line: int                              # line (or message number) in its file
    offset_ned_m: np.ndarray | None = None  # camera - antenna in local north, east, down (MRK), m
    rpy_deg: tuple | None = None           # body roll, pitch, yaw at the exposure (aerospace, NED), degrees
    where: str = ''                        # the file, for messages
    photo: str | None = None               # the photo it belongs to, once matched
    unit: str = 'line'                     # what `line` counts: 'line' (text files) or 'message' (logs)
    logged_llh: tuple | None = None        # the position the log itself wrote: lat_deg, lon_deg, alt_msl_m


@dataclass
class ExposureOptions:
    """How exposures are placed on an antenna track (`photogram-ros geotag`)."""

    max_gap_s: float = param(-1.0, 'longest interval between two epochs an exposure may be interpolated in, s '
                                   '(-1: 2.5 times the track\'s median epoch interval)', min=-1.0, max=600.0)
    at_event_tolerance_s: float = param(0.002, 'an epoch this close to every event makes the track a solution at '
                                               'the events (RTKLIB/Emlid *_events.pos, times written to 1 ms), s',
                                        min=0.0, max=0.1)
    sigma_scale: float = param(1.0, 'factor on the solution\'s formal sigmas', min=0.01, max=100.0)
    lever_arm_frd_m: tuple = param((0.0, 0.0, 0.0), 'the antenna relative to the camera in the body frame, '
                                                    'forward, right, down, m (not with MRK offsets)')
    accept_q: int = param(6, 'worst RTKLIB quality used (1 fix, 2 float, 5 single, 6 all)', min=1, max=6)
    interpolation: str = param('linear', 'between two epochs: linear, as the surveyors\' PPK tools interpolate '
                                         '(robust to the epochs\' cm-level noise), or cubic (Hermite, centred-'
                                         'difference velocities; linear next to a gap or an end)',
                               choices=('cubic', 'linear'))
    event_delay_s: float = param(0.0, 'the exposure this long after its event mark (the shutter\'s delay; '
                                      'negative: before), s; every event is moved by it along the track',
                                 min=-1.0, max=1.0)

    def __post_init__(self):
        validate(self)


@dataclass
class PlacedExposure:
    event: CameraEvent
    lat_deg: float                # camera centre, WGS84
    lon_deg: float
    h_m: float                    # ellipsoidal
    antenna_lat_deg: float
    antenna_lon_deg: float
    antenna_h_m: float
    h_acc_m: float                # per-axis horizontal 1-sigma
    v_acc_m: float
    q: int
    how: str                      # 'at event' or 'interpolated'


@dataclass
class Placement:
    placed: list                  # [PlacedExposure] in event order
    problems: list                # one line per event not placed (naming its line)
    mode: str                     # 'at events' or 'trajectory'
    notes: list = field(default_factory=list)


def accuracy_m(cov_enu_m2: np.ndarray, q: int, scale: float = 1.0) -> tuple[float, float]:
    """(per-axis horizontal, vertical) 1-sigma of one solution, at least its quality's floor."""
    floor_h, floor_v = Q_FLOOR_M.get(int(q), (1.5, 3.0))
    h = scale * math.sqrt(max(0.5 * (cov_enu_m2[0, 0] + cov_enu_m2[1, 1]), 0.0))
    v = scale * math.sqrt(max(cov_enu_m2[2, 2], 0.0))
    return max(h, floor_h), max(v, floor_v)


def _track_heading_rad(track: AntennaTrack, k: int) -> float:
    """Direction of travel (yaw from north, clockwise) of the track around epoch k."""
    a, b = max(k - 1, 0), min(k + 2, len(track) - 1)
    lat, lon, _ = ecef_to_geodetic(*track.ecef_m[a])
    d_enu = ecef_R_enu(lat, lon).T @ (track.ecef_m[b] - track.ecef_m[a])
    return math.atan2(d_enu[0], d_enu[1])


def camera_offset_enu_m(event: CameraEvent, lever_arm_frd_m, heading_rad: float | None) -> tuple[np.ndarray, str]:
    """camera - antenna in local ENU at the exposure, and how it was found."""
    if event.offset_ned_m is not None:
        n, e, d = (float(v) for v in event.offset_ned_m)
        return np.array([e, n, -d]), 'MRK offset'
    lever = np.asarray(lever_arm_frd_m, float)
    if not np.any(lever):
        return np.zeros(3), 'none'
    if event.rpy_deg is not None:
        r, p, y = np.radians(event.rpy_deg)
        how = 'lever arm with the event attitude'
    else:
        r, p, y = 0.0, 0.0, heading_rad or 0.0
        how = 'lever arm, level, heading from the track'
    ant_ned = ned_R_frd_from_euler(r, p, y) @ lever       # antenna - camera in NED
    return np.array([-ant_ned[1], -ant_ned[0], ant_ned[2]]), how


def _is_at_events(track: AntennaTrack, times: np.ndarray, tol_s: float) -> bool:
    if len(times) == 0 or len(track) == 0:
        return False
    idx = np.clip(np.searchsorted(track.t_gps_s, times), 1, len(track) - 1) if len(track) > 1 else np.zeros(
        len(times), int)
    near = np.minimum(np.abs(track.t_gps_s[idx] - times), np.abs(track.t_gps_s[np.maximum(idx - 1, 0)] - times))
    # A trajectory at 20 Hz has an epoch within 2 ms of an event by chance 8 % of the time, not always;
    # and a solution at the events has about as many epochs as there are events.
    return bool(np.all(near <= tol_s) and len(track) <= 2 * len(times) + 2)


def _quality_text(track: AntennaTrack, k: int) -> str:
    """'Q=2 (float)', with the file's own quality when its format has another scale."""
    q = int(track.q[k])
    text = f'Q={q} ({Q_NAMES.get(q, "?")})'
    if track.q_native is not None and str(track.q_native[k]) != str(q):
        text += f', {track.q_native[k]} in the file'
    return text


def _time_base_hint(track: AntennaTrack, times: np.ndarray) -> str:
    """A note when the events fall outside the track but would fit it 18 s (the leap seconds) off."""
    t0, t1 = track.t_gps_s[0], track.t_gps_s[-1]
    inside = np.mean((times >= t0) & (times <= t1))
    for shift in (18.0, -18.0):
        moved = np.mean((times + shift >= t0) & (times + shift <= t1))
        if moved > max(inside, 0.5) and moved - inside > 0.2:
            return (f'; the events fit the track {abs(shift):.0f} s {"later" if shift > 0 else "earlier"}: the time '
                    'bases do not match (one is UTC, the other GPS time; check the .pos header\'s time system)')
    return ''


def _interpolate(track: AntennaTrack, a: int, b: int, t: float, max_gap: float, cubic: bool = True) -> np.ndarray:
    """The antenna at t between epochs a and b: cubic Hermite with centred-difference velocities when the
    epochs before a and after b are there without a gap (exact under constant acceleration), else linear."""
    ta, tb = track.t_gps_s[a], track.t_gps_s[b]
    pa, pb = track.ecef_m[a], track.ecef_m[b]
    if b == a or tb <= ta:
        return pa.copy()
    s = (t - ta) / (tb - ta)
    if cubic and a >= 1 and b + 1 < len(track) and ta - track.t_gps_s[a - 1] <= max_gap and \
            track.t_gps_s[b + 1] - tb <= max_gap:
        h = tb - ta
        va = (pb - track.ecef_m[a - 1]) / (tb - track.t_gps_s[a - 1])
        vb = (track.ecef_m[b + 1] - pa) / (track.t_gps_s[b + 1] - ta)
        s2, s3 = s * s, s * s * s
        return ((2 * s3 - 3 * s2 + 1) * pa + (s3 - 2 * s2 + s) * h * va + (-2 * s3 + 3 * s2) * pb
                + (s3 - s2) * h * vb)
    return pa + s * (pb - pa)


def place_exposures(track: AntennaTrack, events: list, opt: ExposureOptions | None = None) -> Placement:
    """The camera position at each event (see the module docstring); events it cannot place are problems."""
    opt = opt or ExposureOptions()
    if len(track) == 0:
        raise DataError(f'{track.source}: no solution epochs')
    if np.any(np.diff(track.t_gps_s) <= 0):
        k = int(np.argmax(np.diff(track.t_gps_s) <= 0))
        raise DataError(f'{track.source} line {int(track.line[k + 1])}: epoch time not after the previous one '
                        f'(line {int(track.line[k])})')
    if any(ev.offset_ned_m is not None for ev in events) and np.any(np.asarray(opt.lever_arm_frd_m, float)):
        raise DataError('the events carry their own antenna-camera offsets (a DJI MRK): leave --lever-arm out')
    times = np.array([ev.t_gps_s for ev in events], float)
    at_events = _is_at_events(track, times, opt.at_event_tolerance_s)
    if at_events and opt.event_delay_s != 0.0:
        raise DataError(f'{track.source} is a solution at the events (one epoch per event mark): it cannot be '
                        'moved by an event delay; give the trajectory (the .pos of every epoch) instead')
    max_gap = opt.max_gap_s if opt.max_gap_s > 0 else 2.5 * track.median_interval_s()
    usable = track.q <= opt.accept_q
    out, problems, notes = [], [], []
    hint = _time_base_hint(track, times + opt.event_delay_s)
    t_first, t_last = track.t_gps_s[0], track.t_gps_s[-1]
    for ev in events:
        t = ev.t_gps_s + opt.event_delay_s
        name = f'{ev.where} {ev.unit} {ev.line} (event {ev.seq}' + (f', {ev.photo}' if ev.photo else '') + ')'
        if at_events:
            k = int(np.argmin(np.abs(track.t_gps_s - t)))
            if abs(track.t_gps_s[k] - t) > opt.at_event_tolerance_s:
                problems.append(f'{name}: no solution at its time in {track.source} (nearest epoch line '
                                f'{int(track.line[k])}, {track.t_gps_s[k] - t:+.3f} s)')
                continue
            if not usable[k]:
                problems.append(f'{name}: its solution (line {int(track.line[k])}) is {_quality_text(track, k)}, worse '
                                'than accepted')
                continue
            ant, cov, q, how, kh = track.ecef_m[k], track.cov_enu_m2[k], int(track.q[k]), 'at event', k
        else:
            if t < t_first or t > t_last:
                problems.append(f'{name}: exposure at GPS week/second {gps_s_to_week_tow(t)[0]} '
                                f'{gps_s_to_week_tow(t)[1]:.3f} is outside the track ({track.source} lines '
                                f'{int(track.line[0])}-{int(track.line[-1])}, {t - t_first:+.1f} s from its start, '
                                f'{t - t_last:+.1f} s from its end): not extrapolated' + hint)
                continue
            b = int(np.searchsorted(track.t_gps_s, t))
            a = max(b - 1, 0)
            if b >= len(track):
                b = a
            if track.t_gps_s[a] == t:
                b = a
            if track.t_gps_s[b] == t:
                a = b
            gap = track.t_gps_s[b] - track.t_gps_s[a]
            if gap > max_gap:
                problems.append(f'{name}: the track has a gap of {gap:.2f} s around it (lines {int(track.line[a])}-'
                                f'{int(track.line[b])}; longest bridged {max_gap:.2f} s): not interpolated')
                continue
            if not (usable[a] and usable[b]):
                bad = a if not usable[a] else b
                problems.append(f'{name}: its epoch at line {int(track.line[bad])} is {_quality_text(track, bad)}, worse '
                                'than accepted')
                continue
            ant = _interpolate(track, a, b, t, max_gap, opt.interpolation == 'cubic')
            worse = a if np.trace(track.cov_enu_m2[a]) >= np.trace(track.cov_enu_m2[b]) else b
            cov, q, how, kh = track.cov_enu_m2[worse], int(max(track.q[a], track.q[b])), 'interpolated', a
        a_lat, a_lon, a_h = (float(v) for v in ecef_to_geodetic(*ant))
        heading = None
        if ev.offset_ned_m is None and ev.rpy_deg is None and np.any(opt.lever_arm_frd_m):
            heading = _track_heading_rad(track, kh)
        off_enu, off_how = camera_offset_enu_m(ev, opt.lever_arm_frd_m, heading)
        if off_how not in notes and off_how != 'none':
            notes.append(off_how)
        cam = ant + ecef_R_enu(a_lat, a_lon) @ off_enu
        lat, lon, h = (float(v) for v in ecef_to_geodetic(*cam))
        h_acc, v_acc = accuracy_m(cov, q, opt.sigma_scale)
        out.append(PlacedExposure(ev, lat, lon, h, a_lat, a_lon, a_h, h_acc, v_acc, q, how))
    return Placement(out, problems, 'at events' if at_events else 'trajectory', notes)


def track_from_geodetic(t_gps_s, lat_deg, lon_deg, h_m, cov_enu_m2, q, line, source='') -> AntennaTrack:
    """An AntennaTrack from geodetic positions (arrays), sorted by time."""
    x, y, z = geodetic_to_ecef(np.asarray(lat_deg, float), np.asarray(lon_deg, float), np.asarray(h_m, float))
    order = np.argsort(np.asarray(t_gps_s, float), kind='stable')
    return AntennaTrack(np.asarray(t_gps_s, float)[order], np.stack([x, y, z], axis=1)[order],
                        np.asarray(cov_enu_m2, float)[order], np.asarray(q, int)[order],
                        np.asarray(line, int)[order], source)


# --- photos <-> events ----------------------------------------------------------------------------------

@dataclass
class PhotoMatch:
    pairs: list            # [(photo name, event index)]
    problems: list         # every photo without an event, event without a photo, inconsistent time
    how: str               # 'by number', 'by order', 'by time'
    clock_offset_s: float | None = None   # event time - photo time (GPS), median, when photo times exist


def photo_number(name: str) -> int | None:
    """The sequence number in a camera's file name: DJI_0042.JPG -> 42, DJI_20240501101010_0042_V.JPG -> 42."""
    stem = name.rsplit('.', 1)[0]
    nums = re.findall(r'(?<![0-9])([0-9]{1,6})(?![0-9])', stem)
    return int(nums[-1]) if nums else None


def match_photos(photos: list, events: list, how: str = 'auto', tolerance_s: float = 1.5) -> PhotoMatch:
    """Pair photos with events.

    photos: [(name, t_gps_s or None)] in file-name order; events: [CameraEvent] in time order.
    how: 'number' (the photo's file-name number = the event's seq, as a DJI MRK numbers its photos),
    'order' (n-th photo = n-th event), 'time' (nearest event after removing the median clock offset,
    within `tolerance_s`), or 'auto': number when every photo has one and at least half are event seqs,
    else order when the counts agree, else time. Photo times check any pairing: a pair whose time
    difference strays from the median offset by more than `tolerance_s` is named.
    """
    problems = []
    seqs = {ev.seq: i for i, ev in enumerate(events)}
    numbers = [photo_number(n) for n, _ in photos]
    if how == 'auto':
        if all(n is not None for n in numbers) and len(set(numbers)) == len(numbers) and \
                sum(n in seqs for n in numbers) >= 0.5 * len(numbers):
            how = 'number'
        elif len(photos) == len(events):
            how = 'order'
        elif all(t is not None for _, t in photos):
            how = 'time'
        else:
            how = 'order'
    pairs = []
    if how == 'number':
        for (name, _), num in zip(photos, numbers):
            if num in seqs:
                pairs.append((name, seqs[num]))
            else:
                problems.append(f'photo {name}: no event numbered {num}')
    elif how == 'order':
        if len(photos) != len(events):
            problems.append(f'{len(photos)} photos but {len(events)} events: matched in order, the '
                            f'{abs(len(photos) - len(events))} last {"photos" if len(photos) > len(events) else "events"}'
                            ' left without a partner (give photo times or --match time to find which are missing)')
        pairs = [(name, i) for i, (name, _) in enumerate(photos[:len(events)])]
        for name, _ in photos[len(events):]:
            problems.append(f'photo {name}: no event left (there are fewer events than photos)')
    elif how == 'time':
        ev_t = np.array([ev.t_gps_s for ev in events])
        timed = [(n, t) for n, t in photos if t is not None]
        if not timed or not len(ev_t):
            raise DataError('matching by time needs photo times (EXIF DateTimeOriginal) and events')
        d0 = [ev_t[np.argmin(np.abs(ev_t - t))] - t for _, t in timed]
        offset = float(np.median(d0))
        taken = {}
        for name, t in photos:
            if t is None:
                problems.append(f'photo {name}: no time in its EXIF to match by')
                continue
            i = int(np.argmin(np.abs(ev_t - (t + offset))))
            resid = ev_t[i] - (t + offset)
            if abs(resid) > tolerance_s:
                problems.append(f'photo {name}: no event within {tolerance_s:g} s of its time (nearest: event '
                                f'{events[i].seq}, {events[i].unit} {events[i].line}, {resid:+.2f} s after the clock '
                                'offset)')
                continue
            if i in taken:
                problems.append(f'photos {taken[i]} and {name} both fall on event {events[i].seq} ({events[i].unit} '
                                f'{events[i].line}): {name} left without a position')
                continue
            taken[i] = name
            pairs.append((name, i))
    else:
        raise DataError(f'unknown photo matching {how!r}: number, order, time or auto')
    matched = {i for _, i in pairs}
    for i, ev in enumerate(events):
        if i not in matched:
            problems.append(f'event {ev.seq} ({ev.where} {ev.unit} {ev.line}) has no photo')
    # Times check any pairing: the camera clock is off by a constant, not by a photo here and there.
    t_of = dict(photos)
    diffs = [(name, events[i].t_gps_s - t_of[name]) for name, i in pairs if t_of.get(name) is not None]
    offset = None
    if diffs:
        offset = float(np.median([d for _, d in diffs]))
        if how != 'time':
            for name, d in diffs:
                if abs(d - offset) > tolerance_s:
                    i = dict(pairs)[name]
                    problems.append(f'photo {name} paired by {how} with event {events[i].seq} ({events[i].unit} '
                                    f'{events[i].line}) but its time is {d - offset:+.2f} s off the other pairs\' '
                                    'clock offset: a photo or an event is missing (--match time pairs by time)')
    return PhotoMatch(pairs, problems, f'by {how}', offset)
