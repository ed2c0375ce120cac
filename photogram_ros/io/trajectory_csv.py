"""Trajectories (or per-photo solutions) in the CSV exports of Emlid Studio, Trimble Business Center and
Leica Infinity.

Each format is one reader (`EmlidCsvReader`, `TbcCsvReader`, `LeicaInfinityCsvReader`) that names its
own columns and quality words; they share the CSV machinery below. A column is found by its name
(case, spaces and a unit in parentheses do not matter), in any order, with `,`, `;` or tab between
values; columns not named here are skipped. The time: a GPS week and seconds of week, or a date and
time whose system is stated, in the value (`UTC+02:00`, `Z`, `GPST`) or in the column's name (`GPS`,
`UTC`); a time that states neither is refused (18 s of leap seconds are 20 cm at 12 m/s). Heights must
be ellipsoidal. A horizontal (2D) sigma becomes per-axis sigma/sqrt(2) north and east.

| format | time | position | sigmas | quality -> common scale |
|---|---|---|---|---|
| Emlid Studio CSV (the Emlid Flow / Studio point layout) | `Averaging start` [+ `Averaging end`, the mean], or `Time`/`GPST` | `Latitude`, `Longitude`, `Ellipsoidal height` | `Northing RMS`, `Easting RMS`, `Elevation RMS` (or `Lateral RMS`, 2D) | `Solution status`: FIX -> fix, FLOAT -> float, DGPS -> dgps, SBAS -> sbas, SINGLE -> single, PPP -> ppp |
| Trimble Business Center CSV | `GPS Week` + `GPS Seconds`, or `Date` + `Time (GPS|UTC)` | `Latitude`, `Longitude`, `Ellipsoidal Height` | `Horizontal Precision` (2D), `Vertical Precision` (or `SD North/East/Height`) | `Solution Type`: Fixed -> fix, Float -> float, DGPS/Code -> dgps, SBAS -> sbas, Autonomous -> single, RTX -> ppp |
| Leica Infinity CSV | `GPS Week` + `GPS Seconds`, or `Date/Time (GPS|UTC)` | `Latitude`, `Longitude`, `Ellip. Hgt.` / `Ellipsoidal Height` | `Sd Lat`, `Sd Lon`, `Sd Hgt` (or `Posn. Qlty`/`2D CQ`, 2D, and `Hgt. Qlty`/`1D CQ`) | `Solution Type`: Phase fixed -> fix, Phase float -> float, Code/DGNSS -> dgps, Navigated/Autonomous -> single |
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from photogram_ros.core.exposure_positions import AntennaTrack, week_tow_to_gps_s
from photogram_ros.errors import DataError
from photogram_ros.io.trajectory_base import (datetime_to_gps_s, per_axis_from_horizontal, read_lines,
                                              track_from_epochs)


def norm(name: str) -> str:
    """A column name without its unit, case or spacing: 'Easting RMS (m)' -> 'easting rms'."""
    n = re.sub(r'[\(\[][^\)\]]*[\)\]]', '', name).strip().strip('"').lower()
    return re.sub(r'\s+', ' ', n)


def _unit(name: str) -> str:
    m = re.search(r'[\(\[]([^\)\]]*)[\)\]]', name)
    return m.group(1).strip().lower() if m else ''


def _delimiter(line: str) -> str:
    return max((',', ';', '\t'), key=line.count)


def _angle(text: str) -> float:
    """Decimal degrees or D M S (any of ° ' " : or spaces), a hemisphere letter or a sign."""
    s = text.strip()
    neg = s.startswith('-') or s[-1:].upper() in ('S', 'W') or s[:1].upper() in ('S', 'W')
    nums = [float(v) for v in re.findall(r'\d+(?:\.\d*)?', s)]
    if not nums or len(nums) > 3:
        raise ValueError(f'{text!r} is not an angle')
    v = nums[0] + (nums[1] / 60 if len(nums) > 1 else 0) + (nums[2] / 3600 if len(nums) > 2 else 0)
    return -v if neg else v


class CsvTrajectoryReader:
    """The shared CSV machinery; a format is a subclass naming its columns (`COLUMNS`: role -> names),
    its quality words (`QUALITY`: lower-case word -> common scale) and the words that sniff it."""

    name = ''
    expects = ''
    COLUMNS: dict = {}
    QUALITY: dict = {}
    OWN_COLUMNS: tuple = ()       # column names only this format writes
    PROGRAM_WORDS: tuple = ()     # words of the program's name in the file

    def _header(self, lines: list[str]) -> tuple[int, list[str], str] | None:
        for i, ln in enumerate(lines):
            if not ln.strip() or ln.lstrip().startswith('#'):
                continue
            d = _delimiter(ln)
            cols = [c.strip().strip('"') for c in ln.split(d)]
            names = {norm(c) for c in cols}
            if any(n in names for n in self.COLUMNS['lat']) and any(n in names for n in self.COLUMNS['lon']):
                return i, cols, d
        return None

    def sniff(self, head_lines: list[str]) -> float | None:
        found = self._header(head_lines)
        if found is None:
            return None
        _, cols, d = found
        if d not in (',', ';', '\t') or len(cols) < 4:
            return None
        names = {norm(c) for c in cols}
        own = sum(n in names for n in self.OWN_COLUMNS)
        text = '\n'.join(head_lines).lower()
        program = any(w in text for w in self.PROGRAM_WORDS)
        if not own and not program:
            return None
        return min(1.0, 0.4 + 0.15 * own + (0.4 if program else 0.0))

    def _find(self, cols: list[str], role: str) -> int | None:
        names = [norm(c) for c in cols]
        for want in self.COLUMNS.get(role, ()):
            if want in names:
                return names.index(want)
        return None

    def _quality(self, word: str, path, n: int) -> int:
        key = word.strip().lower()
        for k, q in self.QUALITY.items():
            if key == k:
                return q
        raise DataError(f'{path} line {n}: quality {word!r} is none of {", ".join(sorted(self.QUALITY))}')

    def _system(self, col_name: str) -> str | None:
        low = col_name.lower()
        if 'local' in low:
            return 'local'
        if 'utc' in low:
            return 'UTC'
        if 'gps' in low:
            return 'GPST'
        return None

    def read(self, path: Path) -> AntennaTrack:
        path = Path(path)
        lines = read_lines(path)
        found = self._header(lines[:400])
        if found is None:
            raise DataError(f'{path}: no column line naming the latitude and longitude ({self.expects})')
        h, cols, d = found
        idx = {role: self._find(cols, role) for role in self.COLUMNS}
        if idx['h'] is None:
            other = [c for c in cols if norm(c) in ('elevation', 'height', 'h-msl', 'orthometric height', 'altitude')]
            raise DataError(f'{path} line {h + 1}: no ellipsoidal height column ({", ".join(self.COLUMNS["h"])})'
                            + (f'; {other[0]!r} is not one (heights above a geoid or a local datum)' if other else ''))
        if idx['week'] is None and idx['datetime'] is None and idx['time'] is None:
            raise DataError(f'{path} line {h + 1}: no time column (GPS week and seconds, or a date and time)')
        t, lat, lon, hgt, sd, q, qn, line = [], [], [], [], [], [], [], []
        systems = set()
        for n in range(h + 1, len(lines)):
            raw = lines[n]
            if not raw.strip() or raw.lstrip().startswith('#'):
                continue
            vals = [v.strip().strip('"') for v in raw.split(d)]
            if len(vals) < len(cols):
                raise DataError(f'{path} line {n + 1}: {len(vals)} values, the column line ({h + 1}) names '
                                f'{len(cols)}: {raw.strip()[:70]!r}')
            try:
                tt, system = self._epoch_time(vals, cols, idx)
                la, lo, hh = _angle(vals[idx['lat']]), _angle(vals[idx['lon']]), float(vals[idx['h']])
                s = self._sigmas(vals, idx)
            except (ValueError, IndexError) as exc:
                raise DataError(f'{path} line {n + 1}: cannot read the epoch ({exc}): {raw.strip()[:70]!r}') from None
            if system == 'local':
                raise DataError(f'{path} line {n + 1}: the time is local time with no zone: export it in GPS time or '
                                'UTC')
            if system is None:
                raise DataError(f'{path} line {n + 1}: the time {vals[idx["datetime"] or idx["time"]]!r} states no time '
                                'system (GPS or UTC) in its value or its column name: export it with one')
            if not (-90 <= la <= 90 and -180 <= lo <= 360 and math.isfinite(hh)):
                raise DataError(f'{path} line {n + 1}: latitude {la} / longitude {lo} is not a position')
            word = vals[idx['q']] if idx['q'] is not None else ''
            q.append(self._quality(word, path, n + 1) if word else 1)
            qn.append(word or 'none')
            t.append(tt)
            lat.append(la)
            lon.append(lo)
            hgt.append(hh)
            sd.append(s)
            line.append(n + 1)
            systems.add(system)
        if not t:
            raise DataError(f'{path} holds no epoch after its column line ({h + 1})')
        track = track_from_epochs(t, lat, lon, hgt, np.array(sd), q, qn, line, str(path), self.name,
                                  '/'.join(sorted(systems)))
        if idx['q'] is None:
            track.notes.append(f'{path.name}: no quality column: every epoch taken as fixed')
        if np.all(np.isnan(np.array(sd, float))):
            track.notes.append(f'{path.name}: no sigma columns: each photo takes its quality\'s smallest sigma')
        used = [cols[i] for i in idx.values() if i is not None]
        track.notes.append(f'{path.name}: columns used {", ".join(used)}')
        return track

    def _epoch_time(self, vals, cols, idx) -> tuple[float, str | None]:
        if idx['week'] is not None and idx['sow'] is not None:
            return week_tow_to_gps_s(int(float(vals[idx['week']])), float(vals[idx['sow']])), \
                self._system(cols[idx['sow']]) or 'GPST'
        k = idx['datetime'] if idx['datetime'] is not None else None
        if k is not None:
            text = vals[k]
            system = self._system(cols[k])
        else:
            k = idx['time']
            text = vals[k] if idx['date'] is None else f'{vals[idx["date"]]} {vals[k]}'
            system = self._system(cols[k]) or (self._system(cols[idx['date']]) if idx['date'] is not None else None)
        stated = re.search(r'(UTC|GMT|GPST?|Z|[+-]\d{1,2}:?\d{2})\s*$', text.strip(), re.I)
        t, sys_used = datetime_to_gps_s(text, system or 'UTC')
        if idx.get('datetime_end') is not None and vals[idx['datetime_end']]:
            t = 0.5 * (t + datetime_to_gps_s(vals[idx['datetime_end']], system or 'UTC')[0])
        return t, (sys_used if stated else system)

    def _sigmas(self, vals, idx) -> list[float]:
        def get(role):
            k = idx.get(role)
            return float(vals[k]) if k is not None and vals[k] not in ('', '-', '*') else math.nan
        sn, se, su, sh = get('sd_n'), get('sd_e'), get('sd_u'), get('sd_h')
        if math.isnan(sn) and math.isnan(se) and not math.isnan(sh):
            sn = se = per_axis_from_horizontal(sh)
        return [sn, se, su]


_TIME_COMMON = {'week': ('gps week', 'week'), 'sow': ('gps seconds', 'gps second', 'gps seconds of week', 'gps sow',
                                                       'tow', 'gps time of week', 'seconds of week'),
                'date': ('date', 'date (gps)', 'date (utc)'),
                'time': ('time', 'time (gps)', 'time (utc)', 'gps time', 'utc time')}


class EmlidCsvReader(CsvTrajectoryReader):
    name = 'Emlid Studio CSV'
    expects = ('a CSV with "Latitude", "Longitude", "Ellipsoidal height", "Easting RMS", "Northing RMS", "Elevation '
               'RMS", "Solution status" and "Averaging start" (or a GPST/UTC time) columns')
    COLUMNS = {'lat': ('latitude',), 'lon': ('longitude',), 'h': ('ellipsoidal height',),
               'sd_n': ('northing rms',), 'sd_e': ('easting rms',), 'sd_u': ('elevation rms',), 'sd_h': ('lateral rms',),
               'q': ('solution status',), 'datetime': ('averaging start', 'gpst', 'timestamp', 'utc', 'datetime'),
               'datetime_end': ('averaging end',), **_TIME_COMMON}
    QUALITY = {'fix': 1, 'fixed': 1, 'float': 2, 'sbas': 3, 'dgps': 4, 'single': 5, 'ppp': 6}
    OWN_COLUMNS = ('solution status', 'lateral rms', 'averaging start', 'easting rms', 'elevation rms')
    PROGRAM_WORDS = ('emlid', 'reach')


class TbcCsvReader(CsvTrajectoryReader):
    name = 'Trimble Business Center CSV'
    expects = ('a CSV with "Latitude", "Longitude", "Ellipsoidal Height", "Horizontal Precision", "Vertical '
               'Precision", "Solution Type" and "GPS Week"/"GPS Seconds" (or a dated GPS/UTC time) columns')
    COLUMNS = {'lat': ('latitude', 'wgs84 latitude', 'wgs 84 latitude', 'lat'),
               'lon': ('longitude', 'wgs84 longitude', 'wgs 84 longitude', 'lon'),
               'h': ('ellipsoidal height', 'ellipsoid height', 'wgs84 ellipsoid height', 'wgs 84 ellipsoidal height',
                     'height (ellipsoidal)', 'ell. height', 'ell height'),
               'sd_n': ('sd north', 'north precision', 'northing precision', 'sigma north'),
               'sd_e': ('sd east', 'east precision', 'easting precision', 'sigma east'),
               'sd_u': ('vertical precision', 'v. prec.', 'v prec', 'sd height', 'height precision'),
               'sd_h': ('horizontal precision', 'h. prec.', 'h prec'),
               'q': ('solution type', 'fix type', 'solution'), 'datetime': ('date time', 'date/time', 'timestamp'),
               'datetime_end': (), **_TIME_COMMON}
    QUALITY = {'fixed': 1, 'fix': 1, 'rtk fixed': 1, 'float': 2, 'rtk float': 2, 'sbas': 3, 'dgps': 4, 'code': 4,
               'differential': 4, 'autonomous': 5, 'single': 5, 'rtx': 6}
    OWN_COLUMNS = ('horizontal precision', 'vertical precision', 'h. prec.', 'v. prec.')
    PROGRAM_WORDS = ('trimble', 'business center', 'tbc')


class LeicaInfinityCsvReader(CsvTrajectoryReader):
    name = 'Leica Infinity CSV'
    expects = ('a CSV with "Latitude", "Longitude", "Ellip. Hgt.", "Sd Lat"/"Sd Lon"/"Sd Hgt" (or "Posn. Qlty"/'
               '"Hgt. Qlty"), "Solution Type" and "GPS Week"/"GPS Seconds" (or a dated GPS/UTC time) columns')
    COLUMNS = {'lat': ('latitude', 'wgs84 latitude'), 'lon': ('longitude', 'wgs84 longitude'),
               'h': ('ellip. hgt.', 'ellip. height', 'ell. height', 'ellipsoidal height', 'ellip. hgt'),
               'sd_n': ('sd lat', 'sd latitude', 'sd lat.'), 'sd_e': ('sd lon', 'sd longitude', 'sd lon.'),
               'sd_u': ('sd hgt', 'sd height', 'sd ellip. hgt.', 'hgt. qlty', 'height quality', '1d cq', 'height cq'),
               'sd_h': ('posn. qlty', 'position quality', '2d cq', 'position cq'),
               'q': ('solution type', 'sol. type', 'position type'),
               'datetime': ('date/time', 'date time', 'time stamp'), 'datetime_end': (), **_TIME_COMMON}
    QUALITY = {'phase fixed': 1, 'fixed': 1, 'gnss phase fixed': 1, 'phase float': 2, 'float': 2,
               'code': 4, 'code only': 4, 'dgnss': 4, 'navigated': 5, 'autonomous': 5, 'single': 5}
    OWN_COLUMNS = ('ellip. hgt.', 'sd lat', 'sd lon', 'sd hgt', 'posn. qlty', 'hgt. qlty', '1d cq', '2d cq', 'sol. type')
    PROGRAM_WORDS = ('leica', 'infinity')


__all__ = ['CsvTrajectoryReader', 'EmlidCsvReader', 'LeicaInfinityCsvReader', 'TbcCsvReader']
