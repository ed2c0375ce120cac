"""Camera exposure events from the files drones leave, as core.exposure_positions.CameraEvent (GPS time).

- DJI `Timestamp.MRK` (`read_mrk`): one line per photo, `index  seconds-of-week  [week]  N,N  E,E  V,V
  lat,Lat  lon,Lon  h,Ellh  sdN, sdE, sdV  flag,Q`: the exposure in GPS time, the antenna -> camera
  offset in mm (north, east, and V positive down: camera = antenna + N, + E, height - V), and the
  onboard RTK antenna position with its sigmas (m) and flag (50 fixed, 34 float, 16 single).
- ArduPilot dataflash `.bin` (`read_dataflash_events`): CAM (camera feedback) or TRIG (trigger)
  messages with GPS week and milliseconds of week, and the body attitude (R, P, Y).
- MAVLink `.tlog` (`read_tlog_events`): CAMERA_FEEDBACK (ArduPilot, with attitude), CAMERA_TRIGGER
  and CAMERA_IMAGE_CAPTURED (PX4), on the UNIX (UTC) clock (boot times through SYSTEM_TIME).
- The photos' EXIF DateTimeOriginal + SubSecTimeOriginal (+ OffsetTimeOriginal), `read_exif_events`.

`read_events(path)` picks the reader from the file. `write_mrk` writes an MRK (the simulator).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from photogram_ros.core.exposure_positions import (DJI_RTK_FLAG_Q, GPS_EPOCH_UNIX_S, AntennaTrack, CameraEvent,
                                                   gps_s_to_utc_unix, gps_s_to_week_tow, track_from_geodetic, utc_unix_to_gps_s,
                                                   week_tow_to_gps_s)
from photogram_ros.core.gnss_fix import COV_DIAGONAL_KNOWN, COV_UNKNOWN, Q_NONE, GnssFix, stamp_ns_of
from photogram_ros.errors import DataError

MRK_FLAG_Q = DJI_RTK_FLAG_Q   # the MRK's `flag,Q` is DJI's RTK position flag (core/exposure_positions)
_MRK_HEAD = re.compile(r'^\s*(\d+)\s+(\d+(?:\.\d*)?)\s+\[\s*(\d+)\s*\]')


def _mrk_field(line: str, tag: str) -> float | None:
    m = re.search(r'(-?\d+(?:\.\d*)?)\s*,\s*' + tag + r'\b', line)
    return float(m.group(1)) if m else None


@dataclass
class MrkRow:
    """One MRK line: the exposure event and the onboard RTK antenna fix the line carries (NaN position without
    Lat/Lon/Ellh; covariance unknown without its sigmas; quality from DJI's flag, the flag its native number)."""

    event: CameraEvent
    fix: GnssFix

    @property
    def flag(self) -> int:
        return int(self.fix.quality_native)

    @property
    def sd_neu_m(self) -> tuple:
        """1-sigma north, east, up as the line gives them (NaN without)."""
        if self.fix.cov_type == COV_UNKNOWN:
            return (math.nan,) * 3
        e, n, u = (float(v) for v in self.fix.sigma_enu_m)
        return n, e, u


def _cut_last(lines: list[str]) -> int | None:
    """The index of the last non-empty line when it is cut off (the card pulled or the battery gone while
    the drone wrote it): it does not parse, or lacks fields the line before it has. None otherwise."""
    filled = [k for k, ln in enumerate(lines) if ln.strip()]
    if len(filled) < 2:
        return None
    k, prev = filled[-1], lines[filled[-2]]
    line = lines[k]
    if _MRK_HEAD.match(line) is None:
        return k
    for tag in ('N', 'E', 'V', 'Lat', 'Lon', 'Ellh', 'Q'):
        if _mrk_field(prev, tag) is not None and _mrk_field(line, tag) is None:
            return k
    return None


def mrk_cut_line(path: str | Path) -> tuple[int, int | None] | None:
    """(line number, the photo number it begins with or None) of an MRK's cut-off last line; None when whole."""
    try:
        lines = Path(path).read_text(errors='replace').splitlines()
    except OSError:
        return None
    k = _cut_last(lines)
    if k is None:
        return None
    m = re.match(r'^\s*(\d+)\s', lines[k])
    return k + 1, int(m.group(1)) if m else None


def read_mrk(path: str | Path, notes: list | None = None) -> list[MrkRow]:
    """A DJI Timestamp.MRK -> rows in file order (see the module docstring). A cut-off last line is
    skipped and named in `notes` (a list to append to); any other line that does not parse is an error."""
    path = Path(path)
    try:
        lines = path.read_text(errors='replace').splitlines()
    except OSError as exc:
        raise DataError(f'cannot read {path}: {exc}') from exc
    cut = _cut_last(lines)
    if cut is not None:
        msg = (f'{path} line {cut + 1}: cut off ({lines[cut].strip()[:50]!r}): skipped, its photo has no event '
               '(the file ends in the middle of a line)')
        if notes is not None:
            notes.append(msg)
        lines = lines[:cut]
    rows = []
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        head = _MRK_HEAD.match(line)
        vals = {t: _mrk_field(line, t) for t in ('N', 'E', 'V', 'Lat', 'Lon', 'Ellh', 'Q')}
        if head is None or any(vals[t] is None for t in ('N', 'E', 'V')):
            raise DataError(f'{path} line {n}: not a DJI MRK line ("index  seconds  [week]  N,N  E,E  V,V  lat,Lat '
                            f'lon,Lon  h,Ellh  sdN, sdE, sdV  flag,Q"): {line.strip()[:70]!r}')
        idx, tow, week = int(head.group(1)), float(head.group(2)), int(head.group(3))
        if not 0 <= tow < 604800 or week < 1000:
            raise DataError(f'{path} line {n}: GPS week {week} second {tow} is not a GPS time')
        sd = re.search(r'(\d+(?:\.\d*)?)\s*,\s*(\d+(?:\.\d*)?)\s*,\s*(\d+(?:\.\d*)?)\s+\d+\s*,\s*Q', line)
        ev = CameraEvent(idx, week_tow_to_gps_s(week, tow), n,
                         np.array([vals['N'], vals['E'], vals['V']]) * 1e-3, None, str(path))
        rows.append(MrkRow(ev, _mrk_fix(ev, vals, [float(v) for v in sd.groups()] if sd else None, str(path))))
    if not rows:
        raise DataError(f'{path} holds no MRK line')
    t = [r.event.t_gps_s for r in rows]
    for k in range(1, len(rows)):
        if t[k] <= t[k - 1]:
            raise DataError(f'{path} line {rows[k].event.line}: exposure time not after the previous line\'s')
    return rows


def _mrk_fix(ev: CameraEvent, vals: dict, sd_nev_m: list | None, where: str) -> GnssFix:
    """The antenna fix of an MRK line (read_mrk's fields `vals`, its sdN, sdE, sdV or None)."""
    nan = math.nan
    flag = int(vals['Q']) if vals['Q'] is not None else 0
    sd = sd_nev_m if sd_nev_m is not None and all(math.isfinite(v) for v in sd_nev_m) else None
    cov = np.diag([sd[1] ** 2, sd[0] ** 2, sd[2] ** 2]) if sd is not None else np.zeros((3, 3))
    return GnssFix(vals['Lat'] if vals['Lat'] is not None else nan, vals['Lon'] if vals['Lon'] is not None else nan,
                   vals['Ellh'] if vals['Ellh'] is not None else nan, cov,
                   stamp_ns_of(gps_s_to_utc_unix(ev.t_gps_s)), cov_type=COV_DIAGONAL_KNOWN if sd else COV_UNKNOWN,
                   quality=MRK_FLAG_Q.get(flag, Q_NONE), source=f'{where} MRK', quality_native=flag,
                   native_scale='DJI RtkFlag')


def mrk_track(rows: list[MrkRow], path='') -> AntennaTrack:
    """The MRK's own onboard RTK antenna positions as a solution at the events (no post-processing)."""
    ok = [r for r in rows if np.isfinite(r.fix.lat_deg) and np.isfinite(r.fix.h_m)]
    if not ok:
        raise DataError(f'{path}: its lines carry no position (Lat/Lon/Ellh): give the PPK track with --pos')
    bad = [r for r in ok if r.flag not in MRK_FLAG_Q]
    if bad:
        raise DataError(f'{path} line {bad[0].event.line}: RTK flag {bad[0].flag} is none of DJI\'s position flags '
                        f'({", ".join(str(k) for k in sorted(MRK_FLAG_Q))}: 50 fixed, 34 float, 16 single ...)')
    cov = np.array([r.fix.cov_enu_m2 for r in ok])
    t = [r.event.t_gps_s for r in ok]
    track = track_from_geodetic(t, [r.fix.lat_deg for r in ok], [r.fix.lon_deg for r in ok], [r.fix.h_m for r in ok], cov,
                                [MRK_FLAG_Q[r.flag] for r in ok], [r.event.line for r in ok], str(path))
    track.format = 'DJI Timestamp.MRK'
    track.q_native = np.array([r.flag for r in ok])[np.argsort(np.asarray(t, float), kind='stable')]
    return track


def write_mrk(path: str | Path, t_gps_s, offset_ned_m, lat_deg, lon_deg, h_m, sd_neu_m, flag=50,
              seqs=None) -> None:
    """A DJI-layout Timestamp.MRK: one line per exposure, numbered `seqs` (the photos' numbers; default 1..N)."""
    out = []
    for k, t in enumerate(t_gps_s):
        seq = int(seqs[k]) if seqs is not None else k + 1
        week, tow = gps_s_to_week_tow(t)
        n, e, v = (int(round(x * 1000)) for x in offset_ned_m[k])
        out.append(f'{seq}\t{tow:.6f}\t[{week}]\t{n:6d},N\t{e:6d},E\t{v:6d},V\t{lat_deg[k]:.8f},Lat\t'
                   f'{lon_deg[k]:.8f},Lon\t{h_m[k]:.3f},Ellh\t{sd_neu_m[k][0]:.6f}, {sd_neu_m[k][1]:.6f}, '
                   f'{sd_neu_m[k][2]:.6f}\t{flag},Q')
    Path(path).write_text('\n'.join(out) + '\n')


def _get(m, *names, default=None):
    for n in names:
        v = getattr(m, n, None)
        if v is not None:
            return v
    return default


def read_dataflash_events(path: str | Path, kind: str = 'auto') -> list[CameraEvent]:
    """CAM (or TRIG) messages of an ArduPilot .bin. kind: 'CAM', 'TRIG' or 'auto' (CAM when present)."""
    from pymavlink import DFReader
    try:
        log = DFReader.DFReader_binary(str(path))
    except Exception as exc:     # DFReader raises assorted errors on foreign files
        raise DataError(f'{path} is not a readable ArduPilot dataflash log: {exc}') from exc
    found = {'CAM': [], 'TRIG': []}
    n = 0
    while True:
        try:
            m = log.recv_match(type=['CAM', 'TRIG'])
        except Exception:
            break
        if m is None:
            break
        n += 1
        t = m.get_type()
        week, ms = int(_get(m, 'GPSWeek', default=0)), float(_get(m, 'GPSTime', default=0))
        seq = int(_get(m, 'Img', 'I', default=len(found[t]) + 1))
        if week <= 0:
            raise DataError(f'{path}: {t} message {n} (image {seq}) has no GPS time (GPSWeek 0): the autopilot had '
                            'no GPS time when it fired')
        rpy = tuple(float(_get(m, a, b, default=0.0)) for a, b in (('R', 'Roll'), ('P', 'Pitch'), ('Y', 'Yaw')))
        llh = tuple(float(_get(m, k, default=math.nan)) for k in ('Lat', 'Lng', 'Alt'))
        found[t].append(CameraEvent(seq, week_tow_to_gps_s(week, ms * 1e-3), n, None, rpy, f'{path} {t}',
                                    unit='message', logged_llh=llh))
    use = kind if kind in found else ('CAM' if found['CAM'] else 'TRIG')
    if not found[use]:
        raise DataError(f'{path} holds no {"CAM or TRIG" if kind == "auto" else kind} message: the log has no '
                        'camera events (set LOG_BITMASK to log camera messages, or use the photos\' EXIF times)')
    return found[use]


def read_tlog_events(path: str | Path, kind: str = 'auto') -> list[CameraEvent]:
    """CAMERA_FEEDBACK / CAMERA_TRIGGER / CAMERA_IMAGE_CAPTURED of a .tlog, in GPS time.

    kind: one of those names, or 'auto' (feedback, else image captured, else trigger)."""
    from photogram_ros.io import mavlink as ml
    messages, _ = ml.read_tlog(str(path))
    if not messages:
        raise DataError(f'{path} holds no MAVLink')
    ing = ml.Ingest()
    cams = []
    for k, (m, t) in enumerate(messages):
        typ = m.get_type()
        if typ == 'SYSTEM_TIME':
            ing.handle(m, t)
        elif typ in ('CAMERA_FEEDBACK', 'CAMERA_TRIGGER', 'CAMERA_IMAGE_CAPTURED'):
            cams.append((k + 1, typ, m))
    names = ('CAMERA_FEEDBACK', 'CAMERA_IMAGE_CAPTURED', 'CAMERA_TRIGGER')
    have = [nm for nm in names if any(c[1] == nm for c in cams)]
    if not have:
        raise DataError(f'{path} holds no CAMERA_FEEDBACK, CAMERA_TRIGGER or CAMERA_IMAGE_CAPTURED message')
    use = kind if kind in have else have[0]
    if kind != 'auto' and kind not in have:
        raise DataError(f'{path} holds no {kind} (it has {", ".join(have)})')
    out = []
    for k, typ, m in cams:
        if typ != use:
            continue
        if typ == 'CAMERA_IMAGE_CAPTURED':
            us = int(m.time_utc)
            unix = us * 1e-6 if us > 0 else ing.clock.to_time(m.time_boot_ms * 1e-3)
            seq, rpy = int(m.image_index), _rpy_from_quat(m.q)
        else:
            us = int(m.time_usec)
            unix = us * 1e-6 if us > 10 ** 15 else ing.clock.to_time(us * 1e-6)
            seq = int(m.img_idx) if typ == 'CAMERA_FEEDBACK' else int(m.seq)
            rpy = (float(m.roll), float(m.pitch), float(m.yaw)) if typ == 'CAMERA_FEEDBACK' else None
        llh = None
        if typ == 'CAMERA_FEEDBACK':
            llh = (m.lat * 1e-7, m.lng * 1e-7, float(m.alt_msl))
        elif typ == 'CAMERA_IMAGE_CAPTURED':
            llh = (m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3)
        if unix is None:
            raise DataError(f'{path}: {typ} {seq} (message {k}) is stamped in boot time and the log has no '
                            'SYSTEM_TIME to map it to UTC')
        out.append(CameraEvent(seq, utc_unix_to_gps_s(unix), k, None, rpy, f'{path} {typ}', unit='message',
                               logged_llh=llh))
    out.sort(key=lambda e: e.t_gps_s)
    return out


def _rpy_from_quat(q) -> tuple | None:
    w, x, y, z = (float(v) for v in q)
    if not all(map(math.isfinite, (w, x, y, z))) or abs(w * w + x * x + y * y + z * z - 1) > 0.1:
        return None
    roll = math.degrees(math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))
    pitch = math.degrees(math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x)))))
    yaw = math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
    return roll, pitch, yaw


def photo_times_gps_s(photos: list[Path], utc_offset_s: float = 0.0) -> list[float | None]:
    """Each photo's EXIF exposure time in GPS seconds (None without one)."""
    from photogram_ros.io.image_source import read_exif_time_ns
    out = []
    for p in photos:
        ns, _, _ = read_exif_time_ns(p, utc_offset_s)
        out.append(None if ns is None else utc_unix_to_gps_s(ns * 1e-9))
    return out


def read_exif_events(photos: list[Path], utc_offset_s: float = 0.0) -> list[CameraEvent]:
    """The photos' own EXIF times as events, one per photo (numbered in file-name order)."""
    out = []
    for k, (p, t) in enumerate(zip(photos, photo_times_gps_s(photos, utc_offset_s))):
        if t is None:
            raise DataError(f'{p}: no EXIF DateTimeOriginal to take its exposure time from')
        out.append(CameraEvent(k + 1, t, k + 1, None, None, 'EXIF of', p.name, unit='photo'))
    return out


def read_events(path: str | Path, kind: str = 'auto', notes: list | None = None) -> list[CameraEvent]:
    """The camera events of a Timestamp.MRK, an ArduPilot .bin or a .tlog (kind: the message type or auto); an
    MRK's cut-off last line is skipped and named in `notes` (a list to append to)."""
    which = event_kind(path)
    if which == 'mrk':
        return [r.event for r in read_mrk(path, notes)]
    if which == 'dataflash':
        return read_dataflash_events(path, kind)
    return read_tlog_events(path, kind)


def event_kind(path: str | Path) -> str:
    """'mrk', 'dataflash' or 'tlog' from the file's name and first bytes."""
    p = Path(path)
    if not p.is_file():
        raise DataError(f'{p} does not exist (give a Timestamp.MRK, an ArduPilot .bin, a .tlog, or "exif")')
    with open(p, 'rb') as f:
        head = f.read(4)
    if head[:2] == b'\xa3\x95':
        return 'dataflash'
    if p.suffix.lower() == '.mrk':
        return 'mrk'
    if p.suffix.lower() == '.tlog':
        return 'tlog'
    try:
        first = p.read_text(errors='strict').splitlines()[0]
    except (UnicodeDecodeError, IndexError):
        return 'tlog'
    return 'mrk' if _MRK_HEAD.match(first) else 'tlog'


__all__ = ['GPS_EPOCH_UNIX_S', 'MrkRow', 'mrk_cut_line', 'read_events', 'read_mrk', 'mrk_track', 'write_mrk', 'read_dataflash_events',
           'read_tlog_events', 'read_exif_events', 'photo_times_gps_s', 'event_kind']
