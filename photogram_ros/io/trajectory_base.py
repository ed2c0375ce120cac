"""The shared part of the trajectory readers: the reader protocol and the helpers every format's reader uses.

`TrajectoryReader` is the small protocol each format's reader implements (io/rtklib_pos.py,
io/trajectory_csv.py, io/trajectory_grafnav.py); io/trajectory_formats.py holds the registry of them and
reads a file with the one that recognises it. The readers import this module only, never the registry:
- `sniff(head_lines) -> float | None`: how sure the reader is that the file's first lines are its
  format (0..1; None: not its format), from the header, the column names and the time system;
- `read(path) -> Trajectory`: the epochs in the shared typed arrays of
  core.exposure_positions.AntennaTrack: GPS times, WGS84 ECEF positions, per-epoch ENU covariance
  (the file's sigmas), the quality on one ordered scale (`q`: RTKLIB's 1 fix, 2 float, 3 sbas,
  4 dgps, 5 single, 6 ppp) beside the file's own quality (`q_native`), the file's time system and
  the format's name.
"""

from __future__ import annotations

import calendar
import math
import re
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from photogram_ros.core.exposure_positions import (GPS_EPOCH_UNIX_S, Q_NAMES, AntennaTrack, track_from_geodetic,
                                                   utc_unix_to_gps_s)
from photogram_ros.errors import DataError

HEAD_LINES = 80            # lines a reader sniffs

# The shared trajectory type: a post-processed antenna track (core.exposure_positions.AntennaTrack).
Trajectory = AntennaTrack


@runtime_checkable
class TrajectoryReader(Protocol):
    name: str          # the format, as said to the user ('RTKLIB .pos')
    expects: str       # what the reader looks for, for the refusal of an unknown file

    def sniff(self, head_lines: list[str]) -> float | None: ...

    def read(self, path: Path) -> Trajectory: ...


def head_lines(path: Path, n: int = HEAD_LINES) -> list[str]:
    """The first n lines of a text file (a binary file reads as no lines)."""
    try:
        with open(path, 'rb') as fh:
            raw = fh.read(256 * 1024)
    except OSError as exc:
        raise DataError(f'cannot read {path}: {exc}') from exc
    if b'\x00' in raw[:4096]:
        return []
    return raw.decode('utf-8', errors='replace').lstrip('\ufeff').splitlines()[:n]


def read_lines(path: Path) -> list[str]:
    """A text file's lines (a leading byte-order mark dropped); DataError when it cannot be read."""
    try:
        return Path(path).read_text(errors='replace').lstrip('\ufeff').splitlines()
    except OSError as exc:
        raise DataError(f'cannot read {path}: {exc}') from exc


_DT = re.compile(r'^\s*(\d{1,4})([-/.])(\d{1,2})[-/.](\d{1,4})[ T]+(\d{1,2}):(\d{2}):(\d{2}(?:\.\d*)?)\s*(.*)$')
_ZONE = re.compile(r'^(?:UTC|GMT)?\s*([+-])(\d{1,2}):?(\d{2})?$')


def datetime_to_gps_s(text: str, system: str = 'UTC', order: str = 'auto') -> tuple[float, str]:
    """A calendar date and time -> (seconds since the GPS epoch on the GPS scale, the time system used).

    Dates `YYYY-MM-DD`, `YYYY/MM/DD`, `MM/DD/YYYY` (order 'mdy', the default for '/' unless the first
    number is above 12) or `DD.MM.YYYY` ('dmy'); times `HH:MM:SS[.sss]`; a suffix `UTC+hh:mm`, `+hh:mm`,
    `Z`, `UTC`, `GPST` or `GPS` states the system (else `system`: 'UTC' or 'GPST')."""
    m = _DT.match(text)
    if m is None:
        raise ValueError(f'{text!r} is not a date and time')
    a, sep, b, c, hh, mm, ss, rest = m.groups()
    if len(a) == 4:
        y, mo, d = int(a), int(b), int(c)
    elif order == 'dmy' or (order == 'auto' and (sep == '.' or int(a) > 12)):
        d, mo, y = int(a), int(b), int(c)
    else:
        mo, d, y = int(a), int(b), int(c)
    if y < 100:
        y += 2000
    rest = rest.strip().upper()
    offset_s = 0.0
    if rest in ('GPST', 'GPS', 'GPS TIME'):
        system = 'GPST'
    elif rest in ('Z', 'UTC', 'GMT'):
        system = 'UTC'
    elif rest:
        z = _ZONE.match(rest)
        if z is None:
            raise ValueError(f'{text!r}: unknown time zone {rest!r}')
        offset_s = (1 if z.group(1) == '+' else -1) * (int(z.group(2)) * 3600 + int(z.group(3) or 0) * 60)
        system = 'UTC'
    whole = calendar.timegm((y, mo, d, int(hh), int(mm), 0, 0, 0, 0)) + float(ss) - offset_s
    if system == 'GPST':
        return whole - GPS_EPOCH_UNIX_S, 'GPST'
    return utc_unix_to_gps_s(whole), 'UTC'


def seconds_of_day(text: str) -> float:
    """`HH:MM:SS[.sss]` or plain seconds -> seconds of the day."""
    if ':' in text:
        parts = text.split(':')
        return int(parts[0]) * 3600 + int(parts[1]) * 60 + (float(parts[2]) if len(parts) > 2 else 0.0)
    return float(text)


def track_from_epochs(t_gps_s, lat_deg, lon_deg, h_m, sd_neu_m, q, q_native, line, source: str, fmt: str,
                      system: str, week_known: bool = True) -> Trajectory:
    """A trajectory from per-epoch columns: sd_neu_m (N, 3) per-axis 1-sigma north, east, up (NaN: not
    given, 0 in the covariance)."""
    sd = np.nan_to_num(np.asarray(sd_neu_m, float).reshape(-1, 3), nan=0.0)
    cov = np.zeros((len(sd), 3, 3))
    cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2] = sd[:, 1] ** 2, sd[:, 0] ** 2, sd[:, 2] ** 2
    order = np.argsort(np.asarray(t_gps_s, float), kind='stable')
    track = track_from_geodetic(t_gps_s, lat_deg, lon_deg, h_m, cov, q, line, source)
    track.format, track.time_system, track.week_known = fmt, system, week_known
    track.q_native = np.asarray(q_native, dtype=object)[order]
    return track


def per_axis_from_horizontal(sd_h_m: float) -> float:
    """A horizontal (2D, sqrt(sdn^2 + sde^2)) sigma as the per-axis sigma of each of north and east."""
    return sd_h_m / math.sqrt(2.0)


def quality_counts(track: Trajectory) -> str:
    """'250 fix, 3 float' on the common scale, with the format's own values when it has its own."""
    parts = []
    for q in sorted(set(track.q.tolist())):
        sel = track.q == q
        native = ''
        if track.q_native is not None:
            vals = sorted({str(v) for v in np.asarray(track.q_native)[sel]})
            native = f' (file: {", ".join(vals[:4])})'
        parts.append(f'{int(np.sum(sel))} {Q_NAMES.get(int(q), q)}{native}')
    return ', '.join(parts)


__all__ = ['HEAD_LINES', 'Trajectory', 'TrajectoryReader', 'datetime_to_gps_s', 'head_lines', 'per_axis_from_horizontal',
           'quality_counts', 'read_lines', 'seconds_of_day', 'track_from_epochs']
