"""NovAtel Waypoint GrafNav / Inertial Explorer ASCII trajectory exports (the Export Wizard's text files).

The layout, as the Waypoint manuals describe the Export Wizard's output: a free header (`Project:`,
`Program: GrafNav Version ...` or `Inertial Explorer ...`, `Profile:`, `Source:`, `Datum:`, `Master 1:`,
`UTC Offset:` ...), then one line of column names in the profile's order, optionally one line of their
units in parentheses, then one line per epoch (spaces or commas between values). The columns are
mapped by their names, whatever the profile's order and whatever else it exports:

| column (names read)                          | becomes                                              |
|----------------------------------------------|------------------------------------------------------|
| `GPSTime` or `CorrTime` (sec) + `GPSWeek` or a `Date` | GPS time: seconds of week (the week from the `GPSWeek` column, else the date, else the events'), or seconds of the day of the `Date` |
| `GPSTime` as `HH:MM:SS`, or hour / minute / second columns (units `ho mi (sec)`), + `Date` | GPS time |
| `UTCTime` (sec or `HH:MM:SS`, or `ho mi (sec)` columns) + `UTCDate`/`Date` (units `(MDY)` or `(DMY)`); `UTCTime` alone as UTC seconds of week | UTC -> GPS time (leap seconds: the header's `UTC Offset`, else 18 s) |
| `Latitude`, `Longitude` (deg, or `+/-D M S` as three numbers) | WGS84 latitude, longitude         |
| `H-Ell`                                      | ellipsoidal height (an `H-MSL` alone is refused)     |
| `X-ECEF`, `Y-ECEF`, `Z-ECEF`                  | the position, instead of latitude/longitude/height   |
| `SDNorth`, `SDEast` (or `SDLat`, `SDLon`), `SDHeight` | per-axis 1-sigma north, east, up            |
| `SDHoriz`                                    | horizontal 1-sigma sqrt(sdn^2+sde^2): sdn = sde = SDHoriz/sqrt(2) |
| `SDX-ECEF`, `SDY-ECEF`, `SDZ-ECEF`            | ECEF sigmas, turned into north, east, up             |
| `Q`                                          | quality, 1..6: 1 fixed integer -> fix; 2 stable float, 3 converging float -> float; 4, 5 DGPS -> dgps; 6 single point -> single |

A profile may export one time in several units (a real M300 Waypoint export: `UTCTime` in weeks, HMS and
seconds, `GPSTime` in HMS and seconds): the column in seconds is read, the GPS one before the UTC one. A units
line may hold a bare unit (`week`). Anything else (`NS`, `PDOP`, velocities, attitude of an Inertial Explorer
export, a `Column/Variable Contents` block in the header) is skipped, and so are text lines among or after the
epochs (a footer); a last epoch cut off mid-line (the file truncated) is skipped and named in the notes. Column names cut to their column's width, as
Inertial Explorer writes them (`UTCTim`, `GPSTim`), are read as the whole name.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from photogram_ros.core.exposure_positions import SECONDS_PER_WEEK, AntennaTrack, week_tow_to_gps_s
from photogram_ros.core.geodesy import ecef_to_geodetic
from photogram_ros.errors import DataError
from photogram_ros.io.trajectory_base import (datetime_to_gps_s, per_axis_from_horizontal, read_lines,
                                              seconds_of_day, track_from_epochs)

PROGRAM_WORDS = ('grafnav', 'grafnet', 'inertial explorer', 'waypoint', 'novatel')
# GrafNav / Inertial Explorer quality number -> the common scale (RTKLIB Q).
GRAFNAV_Q = {1: 1, 2: 2, 3: 2, 4: 4, 5: 4, 6: 5}
_TIME = ('gpstime', 'utctime', 'gpsweek', 'gpssow', 'gpsseconds')
_POS = ('latitude', 'longitude', 'x-ecef')
_GRAFNAV_ONLY = ('h-ell', 'h-msl', 'sdhoriz', 'sdheight', 'sdnorth', 'sdeast', 'q')
_ALIASES = {'corrtime': 'gpstime', 'gpstim': 'gpstime', 'utctim': 'utctime', 'lat': 'latitude', 'lon': 'longitude', 'long': 'longitude', 'week': 'gpsweek', 'gpsdate': 'date',
            'utcdate': 'utcdate', 'sdht': 'sdheight', 'sd-height': 'sdheight', 'sd-north': 'sdnorth',
            'sd-east': 'sdeast', 'sd-horiz': 'sdhoriz', 'quality': 'q', 'hell': 'h-ell', 'ellhgt': 'h-ell',
            'sdlat': 'sdnorth', 'sdlon': 'sdeast', 'sdlong': 'sdeast', 'x': 'x-ecef', 'y': 'y-ecef', 'z': 'z-ecef'}


def _split(line: str) -> list[str]:
    s = line.strip()
    return [t.strip() for t in s.split(',')] if ',' in s else s.split()


def _names(line: str) -> list[str]:
    return [_ALIASES.get(t.lower(), t.lower()) for t in _split(line)]


def _is_header(names: list[str]) -> bool:
    return (('latitude' in names and 'longitude' in names) or 'x-ecef' in names) and any(t in names for t in _TIME)


def _header_index(lines: list[str]) -> int | None:
    for i, ln in enumerate(lines):
        if _is_header(_names(ln)):
            return i
    return None


def _is_units_line(line: str) -> bool:
    """The line of units under the column names: '(sec) (deg) ...' (a bare unit such as `week` among them)."""
    toks = re.findall(r'\([^)]*\)|\S+', line.strip())
    return bool(toks) and not any(_num(t) for t in toks) and sum(t.startswith('(') for t in toks) * 2 >= len(toks)


def _one_of_each(names: list[str], units: list[str]) -> list[str]:
    """A profile that exports one variable in several units (Waypoint: `UTCTime` in weeks, HMS and seconds;
    `GPSTime` in HMS and seconds) keeps, per name, its column in seconds (else the first); a time column in
    weeks becomes the week (`gpsweek` / `utcweek`); the others are renamed out of the way."""
    out = list(names)
    for k, (nm, u) in enumerate(zip(names, units)):
        if nm in ('gpstime', 'utctime') and u.startswith('week'):
            out[k] = 'gpsweek' if nm == 'gpstime' else 'utcweek'
    for nm in set(out):
        ks = [k for k, n in enumerate(out) if n == nm]
        if len(ks) > 1:
            keep = next((k for k in ks if units[k] in ('sec', 's')), ks[0])
            for k in ks:
                if k != keep:
                    out[k] = f'{nm}[{units[k] or k}]'
    return out


def _num(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return False


def _dms(toks: list[str]) -> float:
    d, m, s = toks
    v = abs(float(d)) + float(m) / 60.0 + float(s) / 3600.0
    return -v if d.strip().startswith('-') else v


class GrafNavReader:
    """NovAtel Waypoint GrafNav / Inertial Explorer ASCII export (see the module docstring)."""

    name = 'NovAtel GrafNav/Inertial Explorer export'
    expects = ('a GrafNav/Inertial Explorer header then a column line such as "GPSTime Latitude Longitude H-Ell '
               'SDHoriz SDHeight Q" (units line optional)')

    def sniff(self, head_lines: list[str]) -> float | None:
        text = '\n'.join(head_lines).lower()
        program = any(w in text for w in PROGRAM_WORDS)
        i = _header_index(head_lines)
        if i is None:
            return 0.3 if program else None
        names = _names(head_lines[i])
        if head_lines[i].lstrip().startswith('%'):
            return None                                  # an RTKLIB column line
        own = sum(n in names for n in _GRAFNAV_ONLY)
        if not own and not program:
            return None
        return min(1.0, 0.5 + 0.1 * own + (0.4 if program else 0.0))

    def read(self, path: Path) -> AntennaTrack:
        path = Path(path)
        lines = read_lines(path)
        h = _header_index(lines)          # however long the header (a multi-base project's runs to hundreds)
        if h is None:
            raise DataError(f'{path}: no column line naming the time ({", ".join(_TIME)}) and Latitude/Longitude (or '
                            'X-ECEF): export it again with a time and the position in the profile')
        names = _names(lines[h])
        program = next((ln.split(':', 1)[1].strip() for ln in lines[:h] if ln.lower().startswith('program')), '')
        widths = [1] * len(names)
        units = [''] * len(names)
        first = h + 1
        if first < len(lines) and _is_units_line(lines[first]):
            ul = lines[first].strip()
            units = [u.strip().strip('()').lower() for u in (ul.split(',') if ',' in ul else
                                                               re.findall(r'\([^)]*\)|\S+', ul))]
            units = (units + [''] * len(names))[:len(names)]
            first += 1
            for k, u in enumerate(units):
                if names[k] in ('latitude', 'longitude') and re.search(r'd\s*m\s*s', u):
                    widths[k] = 3
                elif u == 'ho':            # UTC or GPS time split into hour, minute, second columns
                    names[k] = 'hour'
                elif u == 'mi':
                    names[k] = 'minute'
            names = _one_of_each(names, units)
        if 'h-ell' not in names and 'x-ecef' not in names:
            got = 'H-MSL (above the geoid)' if 'h-msl' in names else 'no height'
            raise DataError(f'{path} line {h + 1}: {got}: export H-Ell (ellipsoidal height) in the profile')
        utc_offset = None
        for ln in lines[:h]:
            m = re.match(r'\s*(?:utc\s*offset|leap\s*seconds?)\s*:\s*(-?\d+)', ln, re.I)
            if m:
                utc_offset = abs(int(m.group(1)))
        col = {n: k for k, n in enumerate(names)}
        rows, skipped, widths_set, cut = [], [], False, None
        last = max((k for k, ln in enumerate(lines) if ln.strip()), default=-1)
        for n in range(first, len(lines)):
            toks = _split(lines[n])
            if not toks or not toks[0]:
                continue
            if not (_num(toks[0]) or re.match(r'^\d{1,4}[/.-]\d', toks[0]) or ':' in toks[0]):
                skipped.append(n + 1)
                continue
            if not widths_set:
                extra = len(toks) - sum(widths)
                if extra == 4 and widths[col.get('latitude', 0)] == 1 and 'latitude' in col:
                    widths[col['latitude']] = widths[col['longitude']] = 3   # DMS without a units line
                widths_set = True
            if len(toks) < sum(widths) and n == last and rows:
                cut = f'{path.name} line {n + 1}: cut off ({len(toks)} of {sum(widths)} values): skipped'
                continue
            if len(toks) < sum(widths):
                raise DataError(f'{path} line {n + 1}: {len(toks)} values, the column line ({h + 1}) names '
                                f'{sum(widths)}: {lines[n].strip()[:70]!r}')
            start = np.cumsum([0] + widths[:-1])
            val = {nm: toks[start[k]:start[k] + widths[k]] for k, nm in enumerate(names)}
            rows.append((n + 1, val))
        if not rows:
            raise DataError(f'{path} holds no epoch after its column line ({h + 1})')
        track = self._track(path, rows, names, units, col, utc_offset, program, skipped)
        if cut:
            track.notes.append(cut + ' (the file ends in the middle of an epoch)')
        return track

    def _track(self, path, rows, names, units, col, utc_offset, program, skipped) -> AntennaTrack:
        n_ep = len(rows)
        t = np.zeros(n_ep)
        lat, lon, hgt = np.zeros(n_ep), np.zeros(n_ep), np.zeros(n_ep)
        sd = np.full((n_ep, 3), np.nan)
        q, qn, line = np.zeros(n_ep, int), [], np.zeros(n_ep, int)
        week_known, system = True, 'GPST'
        time_unit = units[col['gpstime']].lower() if 'gpstime' in col else ''
        date_unit = next((units[col[d]] for d in ('date', 'utcdate') if d in col), '')
        order = 'dmy' if date_unit.startswith('d') else 'mdy'
        notes = []
        for i, (n, v) in enumerate(rows):
            try:
                t[i], system, wk = self._time(v, time_unit, utc_offset, order)
                week_known &= wk
                if 'x-ecef' in v:
                    la, lo, hh = ecef_to_geodetic(float(v['x-ecef'][0]), float(v['y-ecef'][0]), float(v['z-ecef'][0]))
                    lat[i], lon[i], hgt[i] = float(la), float(lo), float(hh)
                else:
                    lat[i] = _dms(v['latitude']) if len(v['latitude']) == 3 else float(v['latitude'][0])
                    lon[i] = _dms(v['longitude']) if len(v['longitude']) == 3 else float(v['longitude'][0])
                    hgt[i] = float(v['h-ell'][0])
                if 'sdnorth' in v:
                    sd[i, 0] = float(v['sdnorth'][0])
                if 'sdeast' in v:
                    sd[i, 1] = float(v['sdeast'][0])
                if 'sdhoriz' in v and not ('sdnorth' in v and 'sdeast' in v):
                    sd[i, 0] = sd[i, 1] = per_axis_from_horizontal(float(v['sdhoriz'][0]))
                if 'sdx-ecef' in v and 'sdnorth' not in v and 'sdhoriz' not in v:
                    sd[i] = _ecef_sd_to_neu(lat[i], lon[i], [float(v[f'sd{a}-ecef'][0]) for a in 'xyz'])
                if 'sdheight' in v:
                    sd[i, 2] = float(v['sdheight'][0])
                raw_q = int(float(v['q'][0])) if 'q' in v else 1
            except (ValueError, KeyError, IndexError) as exc:
                raise DataError(f'{path} line {n}: cannot read the epoch ({exc}): {" ".join(sum(v.values(), []))[:70]!r}'
                                ) from None
            if not (-90.0 <= lat[i] <= 90.0 and -180.0 <= lon[i] <= 360.0 and math.isfinite(hgt[i])):
                raise DataError(f'{path} line {n}: latitude {lat[i]} / longitude {lon[i]} is not a position')
            if raw_q not in GRAFNAV_Q:
                raise DataError(f'{path} line {n}: Q={raw_q} is not a GrafNav quality (1 fixed, 2-3 float, 4-5 DGPS, '
                                '6 single)')
            q[i], line[i] = GRAFNAV_Q[raw_q], n
            qn.append(raw_q)
        if 'q' not in col:
            notes.append(f'{path.name}: no Q column: every epoch taken as fixed')
        if np.all(np.isnan(sd)):
            notes.append(f'{path.name}: no SD columns: each photo takes its quality\'s smallest sigma')
        if skipped:
            notes.append(f'{path.name}: {len(skipped)} text lines between the epochs skipped (first: line {skipped[0]})')
        if not week_known:
            notes.append(f'{path.name}: times are seconds of week with no week or date column')
        fmt = ('NovAtel Inertial Explorer export' if 'inertial explorer' in program.lower() else
               'NovAtel GrafNav export') + (f' ({program})' if program else '')
        track = track_from_epochs(t, lat, lon, hgt, sd, q, qn, line, str(path), fmt, system, week_known)
        track.notes += notes + [f'{path.name}: columns {" ".join(names)}']
        return track

    @staticmethod
    def _time(v: dict, time_unit: str, utc_offset: int | None, order: str = 'mdy') -> tuple[float, str, bool]:
        """(GPS seconds (or seconds of week when no week is known), the file's time system, week known)."""
        date = (v.get('date') or v.get('utcdate') or [None])[0]
        system = 'GPST' if 'gpstime' in v else 'UTC'
        key = 'gpstime' if 'gpstime' in v else 'utctime' if 'utctime' in v else None
        if key is None:
            raise ValueError('no GPSTime, CorrTime or UTCTime column')
        tok = v[key][0]
        if 'hour' in v and 'minute' in v:            # hour, minute and second columns
            sod = int(float(v['hour'][0])) * 3600 + int(float(v['minute'][0])) * 60 + float(tok)
        elif ':' in tok or (time_unit in ('hms', 'h:m:s', 'hh:mm:ss')):
            sod = seconds_of_day(tok)
        else:
            sod = None
        if sod is not None:
            if date is None:
                raise ValueError(f'a time of day ({key}) needs a Date column')
            midnight = datetime_to_gps_s(f'{date} 00:00:00', system, order)[0]
            return midnight + sod, system, True
        sec = float(tok)
        leap = utc_offset if utc_offset is not None else 18
        if 'gpsweek' in v:
            t = week_tow_to_gps_s(int(float(v['gpsweek'][0])), sec)
            return (t + leap if system == 'UTC' else t), system, True
        if date is not None:
            midnight = datetime_to_gps_s(f'{date} 00:00:00', system, order)[0]
            sow_midnight = midnight % SECONDS_PER_WEEK
            if abs(sec - (sow_midnight + 43200.0)) <= 86400.0 or abs(sec + SECONDS_PER_WEEK - sow_midnight) < 86400.0:
                week = round((midnight - sec) / SECONDS_PER_WEEK)      # seconds of week, its week from the date
                return week_tow_to_gps_s(week, sec), system, True
            if 0.0 <= sec < 86401.0:                                  # seconds of the day
                return midnight + sec, system, True
            raise ValueError(f'{key} {sec} is neither a second of the week nor of the day of {date}')
        return (sec + leap if system == 'UTC' else sec), system, False


def _ecef_sd_to_neu(lat_deg: float, lon_deg: float, sd_xyz) -> list[float]:
    """ECEF per-axis sigmas (uncorrelated) -> sigmas north, east, up."""
    from photogram_ros.core.geodesy import ecef_R_enu
    R = ecef_R_enu(lat_deg, lon_deg)                       # columns: east, north, up in ECEF
    c = R.T @ np.diag(np.square(sd_xyz)) @ R
    return [float(np.sqrt(c[1, 1])), float(np.sqrt(c[0, 0])), float(np.sqrt(c[2, 2]))]


__all__ = ['GRAFNAV_Q', 'GrafNavReader']
