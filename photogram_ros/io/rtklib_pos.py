"""RTKLIB solution files (.pos, as rnx2rtkp, RTKPOST, Emlid Studio and REDtoolbox write them).

`read_pos(path)` -> core.exposure_positions.AntennaTrack. Layouts read:
- time as `YYYY/MM/DD HH:MM:SS.sss` or `WWWW SSSSSS.sss` (GPS week, seconds), in the time system the
  column header names (`GPST`, `UTC`, `JST` = UTC + 9 h); converted to GPS time;
- position as `latitude(deg) longitude(deg) height(m)`, the same in degrees-minutes-seconds, or
  `x-ecef(m) y-ecef(m) z-ecef(m)`; then `Q ns` and the sigmas sdn sde sdu sdne sdeu sdun (or sdx sdy
  sdz sdxy sdyz sdzx), whose cross terms RTKLIB writes as signed square roots of the covariances.
Refused, naming the line: heights the header calls geodetic (a geoid RTKLIB chose; ask it for
ellipsoidal ones), the Tokyo datum, baseline (e/n/u) solutions, a line that does not parse, Q outside
1..6, and a file with no fixed (Q=1) epoch unless `require_fix=False`.

`RtklibPosReader`: the format in io/trajectory_formats.py's registry (sniffed by its `%` column line;
the flavour, RTKLIB / RTKLIB-demo5 / Emlid Studio, from the `% program` line).

`write_pos(path, ...)`: the same layout (lat/lon, GPST calendar times), for the simulator.
"""

from __future__ import annotations

import math
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from photogram_ros.core.exposure_positions import (GPS_EPOCH_UNIX_S, Q_NAMES, AntennaTrack,
                                                   track_from_geodetic, utc_unix_to_gps_s, week_tow_to_gps_s)
from photogram_ros.core.geodesy import ecef_R_enu, ecef_to_geodetic
from photogram_ros.errors import DataError


def _signed_sq(v: float) -> float:
    return v * abs(v)


def _time_gps_s(tokens: list, system: str) -> tuple[float, int]:
    """(GPS seconds, tokens used) from the start of a solution line."""
    a, b = tokens[0], tokens[1]
    if '/' in a or '-' in a[1:]:
        date = a.replace('-', '/')
        whole, _, frac = b.partition('.')
        dt = datetime.strptime(f'{date} {whole}', '%Y/%m/%d %H:%M:%S').replace(tzinfo=timezone.utc)
        sec = dt.timestamp() + (float('0.' + frac) if frac else 0.0)
        if system == 'GPST':
            return sec - GPS_EPOCH_UNIX_S, 2
        if system == 'JST':
            sec -= 9 * 3600.0
        return utc_unix_to_gps_s(sec), 2
    week, tow = int(a), float(b)
    t = week_tow_to_gps_s(week, tow)
    if system != 'GPST':
        # RTKLIB writes week/second times in the system it was asked for: undo UTC (and JST).
        unix = t + GPS_EPOCH_UNIX_S - (9 * 3600.0 if system == 'JST' else 0.0)
        t = utc_unix_to_gps_s(unix)
    return t, 2


def read_pos(path: str | Path, require_fix: bool = True) -> AntennaTrack:
    """An RTKLIB .pos file -> AntennaTrack (see the module docstring)."""
    path = Path(path)
    try:
        text = path.read_text(errors='replace')
    except OSError as exc:
        raise DataError(f'cannot read {path}: {exc}') from exc
    system, layout, dms, header_line = None, None, False, None
    rows = []
    for n, raw in enumerate(text.splitlines(), 1):
        s = raw.strip()
        if not s:
            continue
        if s.startswith('%'):
            low = s.lower()
            if 'lat/lon/height=' in low:
                if '/geodetic' in low:
                    raise DataError(f'{path} line {n}: heights are geodetic (above RTKLIB\'s geoid); process again '
                                    'with ellipsoidal heights (RTKLIB option out-height=ellipsoidal)')
                if 'tokyo' in low:
                    raise DataError(f'{path} line {n}: the Tokyo datum; process again with WGS84')
            cols = s.lstrip('%').split()
            if cols and cols[0] in ('GPST', 'UTC', 'JST') and len(cols) > 3:
                system, header_line = cols[0], n
                names = ' '.join(cols[1:]).lower()
                if 'x-ecef' in names:
                    layout = 'xyz'
                elif 'latitude' in names:
                    layout, dms = 'llh', "(d'" in names
                elif 'baseline' in names:
                    raise DataError(f'{path} line {n}: e/n/u baseline solutions have no absolute position; process '
                                    'again with lat/lon/height or x/y/z-ecef output')
                else:
                    raise DataError(f'{path} line {n}: unknown solution columns {" ".join(cols[1:5])!r}')
            continue
        if system is None:
            raise DataError(f'{path} line {n}: a solution before the column header ("%  GPST  latitude(deg) ..."): '
                            'not an RTKLIB .pos file, or its header was cut off (its time system is then unknown)')
        tok = s.replace(',', ' ').split()
        try:
            t, used = _time_gps_s(tok, system)
            vals = [float(v) for v in tok[used:]]
        except (ValueError, IndexError):
            raise DataError(f'{path} line {n}: cannot read {raw.strip()[:60]!r} as a {system} solution') from None
        npos = 7 if dms else 3
        if len(vals) < npos + 2:
            raise DataError(f'{path} line {n}: {len(vals)} numbers after the time; a solution needs the position, '
                            'Q and ns')
        if dms:
            lat = math.copysign(abs(vals[0]) + vals[1] / 60 + vals[2] / 3600, vals[0] if vals[0] else 1.0)
            lon = math.copysign(abs(vals[3]) + vals[4] / 60 + vals[5] / 3600, vals[3] if vals[3] else 1.0)
            pos = [lat, lon, vals[6]]
        else:
            pos = vals[:3]
        q = int(vals[npos])
        if q not in Q_NAMES:
            raise DataError(f'{path} line {n}: Q={q} is not a solution quality (1 fix, 2 float, 3 sbas, 4 dgps, '
                            '5 single, 6 ppp)')
        sd = vals[npos + 2:npos + 8]
        rows.append((n, t, pos, q, sd))
    if not rows:
        raise DataError(f'{path} holds no solution line' + ('' if system else ' (and no RTKLIB column header)'))
    qs = np.array([r[3] for r in rows])
    if require_fix and not np.any(qs == 1):
        counts = ', '.join(f'{np.sum(qs == q)} {Q_NAMES[q]}' for q in sorted(set(qs.tolist())))
        raise DataError(f'{path}: no fixed solution (Q=1) in its {len(rows)} epochs ({counts}; first at line '
                        f'{rows[0][0]}): the post-processing did not resolve the ambiguities; check the base '
                        'station data and its position, or pass --accept-no-fix to use it anyway')
    t = np.array([r[1] for r in rows])
    cov = np.zeros((len(rows), 3, 3))
    line = np.array([r[0] for r in rows])
    if layout == 'llh':
        lat = np.array([r[2][0] for r in rows])
        lon = np.array([r[2][1] for r in rows])
        h = np.array([r[2][2] for r in rows])
        for k, (_, _, _, _, sd) in enumerate(rows):
            if len(sd) >= 3:   # sdn sde sdu [sdne sdeu sdun] -> ENU covariance
                sn, se, su = sd[:3]
                ne, eu, un = (_signed_sq(v) for v in sd[3:6]) if len(sd) >= 6 else (0.0, 0.0, 0.0)
                cov[k] = [[se * se, ne, eu], [ne, sn * sn, un], [eu, un, su * su]]
        track = track_from_geodetic(t, lat, lon, h, cov, qs, line, str(path))
    else:
        xyz = np.array([r[2] for r in rows], float)
        for k, (_, _, _, _, sd) in enumerate(rows):
            if len(sd) >= 3:
                sx, sy, sz = sd[:3]
                xy, yz, zx = (_signed_sq(v) for v in sd[3:6]) if len(sd) >= 6 else (0.0, 0.0, 0.0)
                c = np.array([[sx * sx, xy, zx], [xy, sy * sy, yz], [zx, yz, sz * sz]])
                la, lo, _ = ecef_to_geodetic(*xyz[k])
                R = ecef_R_enu(la, lo)
                cov[k] = R.T @ c @ R
        order = np.argsort(t, kind='stable')
        track = AntennaTrack(t[order], xyz[order], cov[order], qs[order], line[order], str(path))
    track.notes.append(f'{path.name}: {len(rows)} epochs, times in {system} (column header line {header_line})')
    track.time_system, track.q_native = system, qs.copy()
    track.format = _flavour(text.splitlines()[:40])
    return track


def _flavour(head: list[str]) -> str:
    """'RTKLIB .pos', 'RTKLIB-demo5 .pos' or 'Emlid Studio .pos' from the `% program` line."""
    for ln in head:
        low = ln.lower()
        if low.startswith('%') and 'program' in low:
            if 'emlid' in low:
                return 'Emlid Studio .pos (RTKLIB layout)'
            if 'demo5' in low:
                return 'RTKLIB-demo5 .pos'
            break
    return 'RTKLIB .pos'


class RtklibPosReader:
    """RTKLIB / RTKLIB-demo5 / Emlid Studio solution files (`.pos`, `_events.pos`): a `%` header whose
    last line names the time system and the columns (`%  GPST  latitude(deg) longitude(deg) height(m)
    Q ns sdn(m) ...`). Quality: RTKLIB's Q as it is (1 fix, 2 float, 3 sbas, 4 dgps, 5 single, 6 ppp)."""

    name = 'RTKLIB .pos'
    expects = ('a "%" header ending in a column line "%  GPST|UTC  latitude(deg) longitude(deg) height(m)  Q  ns  '
               'sdn(m) ..." (or x-ecef(m) ...)')

    def sniff(self, head_lines: list[str]) -> float | None:
        for ln in head_lines:
            s = ln.strip()
            if not s.startswith('%'):
                continue
            cols = s.lstrip('%').split()
            if len(cols) > 3 and cols[0] in ('GPST', 'UTC', 'JST'):
                names = ' '.join(cols[1:]).lower()
                if any(k in names for k in ('latitude(', 'x-ecef(', 'baseline(')):
                    return 1.0
        return None

    def read(self, path: Path) -> AntennaTrack:
        return read_pos(path, require_fix=False)



def write_pos(path: str | Path, t_gps_s, lat_deg, lon_deg, h_m, q, sd_neu_m, ns=20, program='photogram_ros simulator'):
    """An RTKLIB-layout .pos (lat/lon/ellipsoidal height, GPST calendar times); sd_neu_m: (N, 3) sdn, sde, sdu."""
    t_gps_s = np.asarray(t_gps_s, float)

    def cal(t):
        u = t + GPS_EPOCH_UNIX_S
        whole = math.floor(u + 1e-7)
        ms = int(round((u - whole) * 1000))
        if ms == 1000:
            whole, ms = whole + 1, 0
        return datetime.fromtimestamp(whole, tz=timezone.utc).strftime('%Y/%m/%d %H:%M:%S') + f'.{ms:03d}'
    lines = [f'% program   : {program}',
             f'% obs start : {cal(t_gps_s[0])} GPST',
             f'% obs end   : {cal(t_gps_s[-1])} GPST',
             '% pos mode  : Kinematic',
             '%',
             '% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites)',
             '%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  '
             'sdne(m)  sdeu(m)  sdun(m) age(s)  ratio']
    sd = np.asarray(sd_neu_m, float)
    for k in range(len(t_gps_s)):
        lines.append(f'{cal(t_gps_s[k])} {lat_deg[k]:14.9f} {lon_deg[k]:14.9f} {h_m[k]:10.4f} {int(q[k]):3d} '
                     f'{int(ns):3d} {sd[k, 0]:8.4f} {sd[k, 1]:8.4f} {sd[k, 2]:8.4f} {0.0:8.4f} {0.0:8.4f} {0.0:8.4f} '
                     f'{0.0:6.2f} {999.9:6.1f}')
    Path(path).write_text('\n'.join(lines) + '\n')


__all__ = ['RtklibPosReader', 'read_pos', 'write_pos']
