"""Antenna trajectories from the post-processing programs surveyors use, recognised by their content.

One reader per format behind one small protocol (`TrajectoryReader`), in a registry (`READERS`; a
new format is one more `register(...)`):
- `sniff(head_lines) -> float | None`: how sure the reader is that the file's first lines are its
  format (0..1; None: not its format), from the header, the column names and the time system;
- `read(path) -> AntennaTrack`: the epochs in the shared typed arrays of
  core.exposure_positions.AntennaTrack: GPS times, WGS84 ECEF positions, per-epoch ENU covariance
  (the file's sigmas), the quality on one ordered scale (`q`: RTKLIB's 1 fix, 2 float, 3 sbas,
  4 dgps, 5 single, 6 ppp) beside the file's own quality (`q_native`), the file's time system and
  the format's name.

`read_trajectory(path)` sniffs the file's first `HEAD_LINES` lines with every reader and reads it
with the one that is surest; it says which format it recognised (the track's first note) and refuses
a file no reader recognises, or two readers recognise equally well, with one line naming what each
format expects. The readers: io/rtklib_pos.py (RTKLIB, RTKLIB-demo5, Emlid Studio `.pos` and
`_events.pos`), io/trajectory_grafnav.py (NovAtel Waypoint GrafNav / Inertial Explorer ASCII
exports), io/trajectory_csv.py (Emlid Studio CSV, Trimble Business Center CSV, Leica Infinity CSV).

Every format's quality maps onto the one scale (`--accept fix|float|all` works on each; the tables
are in each reader and in docs/commands.md).
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
AMBIGUOUS_MARGIN = 0.05    # two readers this close in score: the file is ambiguous

# The shared trajectory type: a post-processed antenna track (core.exposure_positions.AntennaTrack).
Trajectory = AntennaTrack


@runtime_checkable
class TrajectoryReader(Protocol):
    name: str          # the format, as said to the user ('RTKLIB .pos')
    expects: str       # what the reader looks for, for the refusal of an unknown file

    def sniff(self, head_lines: list[str]) -> float | None: ...

    def read(self, path: Path) -> Trajectory: ...


READERS: list[TrajectoryReader] = []


def register(reader: TrajectoryReader) -> TrajectoryReader:
    """Add a reader to the registry (once per name)."""
    if not isinstance(reader, TrajectoryReader):
        raise TypeError(f'{reader!r} is not a TrajectoryReader (name, expects, sniff, read)')
    if all(r.name != reader.name for r in READERS):
        READERS.append(reader)
    return reader


def _load_readers() -> None:
    """Import the reader modules (each registers its readers)."""
    from photogram_ros.io import rtklib_pos, trajectory_csv, trajectory_grafnav  # noqa: F401


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


def sniff(path: str | Path) -> tuple[TrajectoryReader, list[tuple[str, float]]]:
    """The reader surest of the file, and every reader's score (name, score) that recognised it."""
    _load_readers()
    path = Path(path)
    if not path.is_file():
        raise DataError(f'{path} does not exist (give the post-processed trajectory: an RTKLIB/Emlid .pos, a GrafNav/'
                        'Inertial Explorer export, an Emlid, TBC or Leica Infinity CSV)')
    head = head_lines(path)
    scores = []
    for r in READERS:
        s = r.sniff(head)
        if s is not None and s > 0:
            scores.append((r, float(s)))
    scores.sort(key=lambda rs: -rs[1])
    expected = '; '.join(f'{r.name}: {r.expects}' for r in READERS)
    if not scores:
        raise DataError(f'{path}: not a trajectory format read here (expected one of {expected})')
    if len(scores) > 1 and scores[0][1] - scores[1][1] < AMBIGUOUS_MARGIN:
        a, b = scores[0][0], scores[1][0]
        raise DataError(f'{path}: ambiguous, it looks as much like {a.name} ({a.expects}) as like {b.name} '
                        f'({b.expects}); export it again with its program\'s own header')
    return scores[0][0], [(r.name, s) for r, s in scores]


def read_trajectory(path: str | Path, require_fix: bool = True) -> Trajectory:
    """The trajectory of a file of any registered format (see the module docstring); a file with no
    fixed epoch is refused unless `require_fix` is False."""
    path = Path(path)
    reader, _ = sniff(path)
    track = reader.read(path)
    if not track.format:
        track.format = reader.name
    if len(track) == 0:
        raise DataError(f'{path} ({reader.name}) holds no solution epoch')
    if require_fix and not np.any(track.q == 1):
        qs = track.q
        counts = ', '.join(f'{int(np.sum(qs == q))} {Q_NAMES.get(int(q), q)}' for q in sorted(set(qs.tolist())))
        raise DataError(f'{path}: no fixed solution in its {len(track)} epochs ({counts}; first at line '
                        f'{int(track.line[0])}): the post-processing did not resolve the ambiguities; check the base '
                        'station data and its position, or pass --accept-no-fix to use it anyway')
    track.notes.insert(0, f'{path.name}: read as {track.format} ({len(track)} epochs, times in {track.time_system})')
    return track


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


__all__ = ['HEAD_LINES', 'READERS', 'Trajectory', 'TrajectoryReader', 'datetime_to_gps_s', 'head_lines',
           'per_axis_from_horizontal', 'quality_counts', 'read_lines', 'read_trajectory', 'register', 'seconds_of_day', 'sniff',
           'track_from_epochs']
