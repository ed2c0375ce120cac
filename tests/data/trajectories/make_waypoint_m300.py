"""Writes `waypoint_m300_5hz.txt` and `m300_Timestamp.MRK` (see LAYOUT_SOURCES.md): a simulated DJI M300 mapping
flight's 5 Hz antenna trajectory with exactly the header, column and units lines of a real M300 NovAtel
Waypoint GrafNav 8.90 export (UTCDate YMD; UTCTime in fractional weeks, H:MM:SS.ss and seconds; GPSTime in
H:MM:SS.sss and seconds; Latitude, Longitude in degrees; H-Ell; SDHoriz; SDHeight; Q 1/2; 19 lines before the
first epoch; a trailing blank line), and its Timestamp.MRK in DJI's layout with per-photo antenna -> camera
offsets (mm, N/E/V; Windows line ends).
Run from the repository root: `python tests/data/trajectories/make_waypoint_m300.py`. Deterministic.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
LAT0, LON0, H0 = 13.7367, 100.5332, 40.0     # a field near Bangkok
WEEK, SOW0, LEAP = 2235, 21198.0, 18         # 2022-11-06 05:53:00 UTC = GPS week 2235, 21198 s
RATE, N = 5.0, 300                           # 60 s at 5 Hz


def enu_at(tt: float) -> tuple[float, float, float]:
    """east, north, up (m) of the antenna tt s after the first epoch: a line north at 8 m/s (from 6 m/s), a
    half turn of radius 20 m, the next line south at 8 m/s; a gentle heave."""
    if tt < 25:
        n, e = 6 * tt + 0.04 * tt * tt, 0.0
    elif tt < 25 + 20 * math.pi / 8:
        a = (tt - 25) * 8 / 20
        n, e = 175 + 20 * math.sin(a), 20 - 20 * math.cos(a)
    else:
        n, e = 175 - 8 * (tt - 25 - 20 * math.pi / 8), 40.0
    return e, n, 120 + 0.15 * math.sin(tt / 3)


def geodetic(e, n, u):
    from pyproj import Transformer
    to_ecef = Transformer.from_crs('EPSG:4979', 'EPSG:4978', always_xy=True)
    to_llh = Transformer.from_crs('EPSG:4978', 'EPSG:4979', always_xy=True)
    x0 = np.array(to_ecef.transform(LON0, LAT0, H0))
    la, lo = math.radians(LAT0), math.radians(LON0)
    R = np.array([[-math.sin(lo), -math.sin(la) * math.cos(lo), math.cos(la) * math.cos(lo)],
                  [math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la) * math.sin(lo)],
                  [0, math.cos(la), math.sin(la)]])
    xyz = (R @ np.vstack([e, n, u])).T + x0
    lon, lat, h = to_llh.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2])
    return np.asarray(lat), np.asarray(lon), np.asarray(h)


def hms(sow: float, decimals: int) -> str:
    """H:MM:SS.ss as the export writes it (no leading zero on the hour)."""
    s = sow % 86400
    return f'{int(s // 3600)}:{int(s % 3600 // 60):02d}:{s % 60:0{3 + decimals}.{decimals}f}'


def main():
    rng = np.random.default_rng(300)
    t = np.arange(N) / RATE
    e, n, u = (np.array(v) for v in zip(*[enu_at(float(x)) for x in t]))
    noise = rng.normal(0, 0.004, (N, 3)).cumsum(axis=0) * 0.3          # correlated PPK noise, mm level
    noise[:, 2] += rng.normal(0, 0.006, N)                              # and the real export's cm height noise
    lat, lon, h = geodetic(e + noise[:, 0], n + noise[:, 1], u + noise[:, 2])
    # the header, column and units lines exactly as the real export's (a leading blank line, 19 lines before the
    # first epoch); the base station's name and position are this file's own
    head = ['', 'Project:     PPK', 'Program:     GrafNav Version 8.90.6611', 'Profile:     Research',
            'Source:      GNSS Epochs(GNSS Combined)', 'ProcessInfo: PPK by Unknown on 11/15/2022 at 20:51:00', '',
            'Datum:       WGS84', 'Master 1:    Name BASE, Status ENABLED',
            '             Antenna height 1.871 m, to L1PC [Generic(NONE)]',
            '             Lat, Lon, El Hgt 13 44 12.12000, 100 32 00.00000, 38.412 m [WGS84, N/A]',
            'Remote:      Antenna height 0.000 m, to L1PC [Generic(NONE)]', 'UTC Offset:  18 s',
            'SD Scaling Settings:', '  Position: 1.0000', '  Velocity: 1.0000', '',
            '   UTCDate    UTCTime     UTCTime   UTCTime     GPSTime   GPSTime       Latitude      Longitude        '
            'H-Ell      SDHoriz     SDHeight Q',
            '     (YMD)    (weeks)       (HMS)     (sec)       (HMS)     (sec)          (deg)          (deg)          '
            '(m)          (m)          (m)  ']
    rows = []
    q = np.where(rng.random(N) < 0.06, 2, 1)                   # a few float epochs among the fixed, as the real
    for k in range(N):
        g = SOW0 + t[k]
        c = g - LEAP
        sdh, sdv = 0.005 + 0.002 * (q[k] - 1), 0.009 + 0.002 * (q[k] - 1)
        rows.append(f'2022/11/06 {WEEK + c / 604800:.5f} {hms(c, 2):>11s} {c:9.2f} {hms(g, 3):>11s} {g:9.3f}  '
                    f'{lat[k]:13.10f} {lon[k]:14.10f} {h[k]:12.3f} {sdh:12.3f} {sdv:12.3f} {q[k]}')
    (HERE / 'waypoint_m300_5hz.txt').write_text('\n'.join(head + rows) + '\n\n')
    # photos every 2 s on the lines (not in the turn), 0.037 s after an arbitrary epoch phase
    mrk = []
    times = [x for x in np.arange(1.037, t[-1] - 1, 2.0) if not 25 <= x <= 25 + 20 * math.pi / 8]
    for i, x in enumerate(times):
        off = rng.integers(-60, 60, 2).tolist() + [int(rng.integers(120, 200))]
        e1, n1, u1 = enu_at(float(x))
        la, lo, hh = geodetic(np.array([e1 + off[1] / 1000]), np.array([n1 + off[0] / 1000]),
                              np.array([u1 - off[2] / 1000]))
        mrk.append(f'{i + 1}\t{SOW0 + x:.6f}\t[{WEEK}]\t{off[0]:6d},N\t{off[1]:6d},E\t{off[2]:6d},V\t'
                   f'{la[0]:.8f},Lat\t{lo[0]:.8f},Lon\t{hh[0]:.3f},Ellh\t0.011219, 0.010187, 0.021876\t50,Q')
    (HERE / 'm300_Timestamp.MRK').write_bytes(('\r\n'.join(mrk) + '\r\n').encode())


if __name__ == '__main__':
    main()
