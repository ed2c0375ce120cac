"""Writes the trajectory files of this folder in each program's documented export layout (see README.md).

One flight (a drone's antenna at 5 Hz over 48 s: a line north speeding up to 12 m/s, a half turn,
the next line south slowing down, climbing gently) written as each format writes it, plus a DJI Timestamp.MRK of 30 exposures.
Run from the repository root: `python tests/data/trajectories/make_layouts.py`. Deterministic.
"""

from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
from pyproj import Transformer

HERE = Path(__file__).parent
LAT0, LON0, H0 = 46.5190, 6.5668, 455.0      # a field near Lausanne
WEEK, SOW0 = 2304, 378000.2                  # GPS week 2304 (2024-03-03 .. 09), Thursday 09:00 GPST
LEAP = 18
RATE = 5.0
N = 240                                      # 48 s


def enu_at(tt: float) -> tuple[float, float, float]:
    """The antenna's east, north, up (m) at tt seconds from the start."""
    if tt < 18:                       # line 1 north, 10 -> 12 m/s
        n, e = 10 * tt + tt * tt / 18, 0.0
    elif tt < 22:                     # a half turn of radius 15 m at 11.8 m/s
        a = (tt - 18) / 4 * math.pi
        n, e = 198 + 15 * math.sin(a), 15 - 15 * math.cos(a)
    else:                             # line 2 south, 12 m/s slowing
        s = tt - 22
        n, e = 198 - (12 * s - 0.1 * s * s), 30.0
    return e, n, 80 + 0.05 * tt * tt / 10 + 0.3 * math.sin(tt / 5)


def flight():
    """(t_s from the start, east, north, up in metres, sigmas n/e/u, quality 1..6 per epoch)."""
    t = np.arange(N) / RATE
    e, n, u = (np.array(v) for v in zip(*[enu_at(float(tt)) for tt in t]))
    rng = np.random.default_rng(45)
    sd = np.column_stack([0.008 + 0.002 * rng.random(N), 0.007 + 0.002 * rng.random(N), 0.015 + 0.004 * rng.random(N)])
    q = np.ones(N, int)
    q[150:158] = 2                       # a few float epochs in the turn
    return t, e, n, u, sd, q


def geodetic(e, n, u):
    enu2ecef = Transformer.from_crs('EPSG:4979', 'EPSG:4978', always_xy=True)
    ecef2llh = Transformer.from_crs('EPSG:4978', 'EPSG:4979', always_xy=True)
    x0, y0, z0 = enu2ecef.transform(LON0, LAT0, H0)
    la, lo = math.radians(LAT0), math.radians(LON0)
    R = np.array([[-math.sin(lo), -math.sin(la) * math.cos(lo), math.cos(la) * math.cos(lo)],
                  [math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la) * math.sin(lo)],
                  [0, math.cos(la), math.sin(la)]])
    xyz = (R @ np.vstack([e, n, u])).T + [x0, y0, z0]
    lon, lat, h = ecef2llh.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2])
    return np.asarray(lat), np.asarray(lon), np.asarray(h)


def gps_dt(sow):
    return datetime(1980, 1, 6, tzinfo=timezone.utc) + timedelta(weeks=WEEK, seconds=float(sow))


def dms(v, width=3):
    s = '-' if v < 0 else ''
    v = abs(v)
    d = int(v)
    m = int((v - d) * 60)
    sec = (v - d - m / 60) * 3600
    return f'{s}{d:>{width}d} {m:02d} {sec:08.5f}'


def main():
    t, e, n, u, sd, q = flight()
    lat, lon, h = geodetic(e, n, u)
    sow = SOW0 + t
    rtk_q = {1: 1, 2: 2}

    # RTKLIB-demo5 .pos, GPST calendar times
    lines = ['% program   : RTKLIB ver.demo5 b34h', '% inp file  : rover.obs', '% inp file  : base.obs',
             f'% obs start : {gps_dt(sow[0]):%Y/%m/%d %H:%M:%S}.2 GPST (week{WEEK} {sow[0]:.1f}s)',
             '% pos mode  : Kinematic', '% freqs     : L1+L2', '% solution  : Combined',
             '% elev mask : 15.0 deg', '% amb res   : Fix and Hold', '% ref pos   :  46.518000000    6.566000000   '
             '452.1234', '%', '% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,'
             'ns=# of satellites)',
             '%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  '
             'sdne(m)  sdeu(m)  sdun(m) age(s)  ratio']
    for k in range(N):
        dt = gps_dt(sow[k])
        lines.append(f'{dt:%Y/%m/%d %H:%M:%S}.{dt.microsecond // 1000:03d} {lat[k]:14.9f} {lon[k]:14.9f} '
                     f'{h[k]:10.4f} {rtk_q[q[k]]:3d} {21:3d} {sd[k, 0]:8.4f} {sd[k, 1]:8.4f} {sd[k, 2]:8.4f} '
                     f'{0.0021:8.4f} {-0.0032:8.4f} {0.0041:8.4f} {0.2:6.2f} {45.3:6.1f}')
    (HERE / 'rtklib_demo5_5hz.pos').write_text('\n'.join(lines) + '\n')

    # Emlid Studio .pos (RTKLIB layout), UTC week/seconds times
    lines = ['% program   : Emlid Studio v1.8', '% inp file  : rover.24O', '% pos mode  : Kinematic', '%',
             '% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites)',
             '%  UTC                   latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  '
             'sdne(m)  sdeu(m)  sdun(m) age(s)  ratio']
    for k in range(N):
        lines.append(f'{WEEK} {sow[k] - LEAP:11.3f} {lat[k]:14.9f} {lon[k]:14.9f} {h[k]:10.4f} {rtk_q[q[k]]:3d} '
                     f'{19:3d} {sd[k, 0]:8.4f} {sd[k, 1]:8.4f} {sd[k, 2]:8.4f} {0.0:8.4f} {0.0:8.4f} {0.0:8.4f} '
                     f'{0.0:6.2f} {3.1:6.1f}')
    (HERE / 'emlid_studio_5hz.pos').write_text('\n'.join(lines) + '\n')

    # GrafNav ASCII export: free header, column line, units line; GPSTime seconds of week (no week
    # column), latitude/longitude in +/-D M S, H-Ell, SDHoriz, SDHeight, Q, NS, PDOP
    gq = {1: 1, 2: 3}
    lines = ['Project:     M300_PPK', 'Program:     GrafNav Version 8.90.4215', 'Profile:     PPK_5Hz',
             'Source:      GNSS Epochs(Combined)', 'ProcessInfo: Processed on 3/8/2024 at 14:02:11 by surveyor', '',
             'Datum:       WGS84, (processing datum)', 'Master 1:    Name BASE, Status ENABLED',
             '             Antenna height 1.800 m, relative to ARP', '             Position  46 31 04.80000, 6 33 57.60000, '
             '452.123 m (WGS84, Ellipsoidal hgt)', 'Remote:      Antenna height 0.000 m, relative to ARP',
             'UTC Offset:  18 s', '',
             '    GPSTime        Latitude          Longitude         H-Ell  SDHoriz SDHeight  Q  NS   PDOP',
             '      (sec)      (+/-D M S)         (+/-D M S)           (m)      (m)      (m)  (#)    (#)',
             '']
    for k in range(N):
        sh = math.hypot(sd[k, 0], sd[k, 1])
        lines.append(f'{sow[k]:11.2f}  {dms(lat[k])}  {dms(lon[k])}  {h[k]:10.4f}  {sh:7.4f}  {sd[k, 2]:7.4f}  '
                     f'{gq[q[k]]}  {20:2d}  {1.6:5.2f}')
    (HERE / 'grafnav_5hz_dms.txt').write_text('\n'.join(lines) + '\n')

    # Inertial Explorer export, comma-delimited, UTC date and time, decimal degrees, SDNorth/SDEast/SDHeight,
    # Q and the attitude
    lines = ['Project:     M300_PPK', 'Program:     Inertial Explorer Version 8.90.4215',
             'Profile:     IE_UTC_CSV', 'Source:      GNSS/INS Epochs(Combined)', 'UTC Offset:  18 s', '',
             'UTCDate,UTCTime,Latitude,Longitude,H-Ell,SDNorth,SDEast,SDHeight,Q,Roll,Pitch,Heading',
             '(MM/DD/YYYY),(HMS),(Deg),(Deg),(m),(m),(m),(m),(),(deg),(deg),(deg)']
    for k in range(N):
        dt = gps_dt(sow[k] - LEAP)
        lines.append(f'{dt:%m/%d/%Y},{dt:%H:%M:%S}.{dt.microsecond // 10000:02d},{lat[k]:.10f},{lon[k]:.10f},'
                     f'{h[k]:.4f},{sd[k, 0]:.4f},{sd[k, 1]:.4f},{sd[k, 2]:.4f},{gq[q[k]]},0.512,-1.203,{12.5:.3f}')
    (HERE / 'inertial_explorer_5hz_utc.csv').write_text('\n'.join(lines) + '\n')

    # Emlid Studio CSV (the Emlid Flow/Studio point layout), averaging start/end in UTC+01:00
    head = ('Name,Code,Code description,Easting,Northing,Elevation,Description,Longitude,Latitude,Ellipsoidal height,'
            'Origin,Tilt angle,Easting RMS,Northing RMS,Elevation RMS,Lateral RMS,Antenna height,Antenna height units,'
            'Solution status,Correction type,Averaging start,Averaging end,Samples,PDOP,GDOP')
    lines = [head]
    st = {1: 'FIX', 2: 'FLOAT'}
    for k in range(N):
        dt = gps_dt(sow[k] - LEAP) + timedelta(hours=1)
        stamp = f'{dt:%Y-%m-%d %H:%M:%S}.{dt.microsecond // 100000} UTC+01:00'
        lines.append(f'EV{k + 1},,,,,,,{lon[k]:.9f},{lat[k]:.9f},{h[k]:.4f},Global,,{sd[k, 1]:.3f},{sd[k, 0]:.3f},'
                     f'{sd[k, 2]:.3f},{math.hypot(sd[k, 0], sd[k, 1]):.3f},0.000,m,{st[q[k]]},PPK,{stamp},{stamp},1,'
                     '1.4,2.1')
    (HERE / 'emlid_studio_5hz.csv').write_text('\n'.join(lines) + '\n')

    # Trimble Business Center CSV: GPS week and seconds, horizontal/vertical precision, solution type
    lines = ['Point ID,GPS Week,GPS Seconds,Latitude,Longitude,Ellipsoidal Height (m),Horizontal Precision (m),'
             'Vertical Precision (m),Solution Type,Satellites']
    tq = {1: 'Fixed', 2: 'Float'}
    for k in range(N):
        lines.append(f'T{k + 1:04d},{WEEK},{sow[k]:.3f},{lat[k]:.10f},{lon[k]:.10f},{h[k]:.4f},'
                     f'{math.hypot(sd[k, 0], sd[k, 1]):.4f},{sd[k, 2]:.4f},{tq[q[k]]},18')
    (HERE / 'tbc_5hz.csv').write_text('\n'.join(lines) + '\n')

    # Leica Infinity CSV: semicolons, GPS date/time, DMS with hemisphere, Sd Lat/Lon/Hgt, solution type
    lines = ['Point Id;Date/Time (GPS);Latitude;Longitude;Ellip. Hgt.;Sd Lat;Sd Lon;Sd Hgt;Sol. Type']
    lq = {1: 'Phase fixed', 2: 'Phase float'}
    for k in range(N):
        dt = gps_dt(sow[k])
        la = f'{dms(lat[k], 2).strip()}'.replace(' ', '\u00b0', 1).replace(' ', "'", 1) + '" N'
        lo = f'{dms(lon[k], 2).strip()}'.replace(' ', '\u00b0', 1).replace(' ', "'", 1) + '" E'
        lines.append(f'L{k + 1};{dt:%d.%m.%Y %H:%M:%S}.{dt.microsecond // 1000:03d};{la};{lo};{h[k]:.4f};'
                     f'{sd[k, 0]:.4f};{sd[k, 1]:.4f};{sd[k, 2]:.4f};{lq[q[k]]}')
    (HERE / 'leica_infinity_5hz.csv').write_text('\n'.join(lines) + '\n', encoding='utf-8')

    # DJI Timestamp.MRK: 30 exposures between the epochs, offsets 0 (antenna = camera)
    rng = np.random.default_rng(46)
    tev = np.sort(rng.uniform(1.0, t[-1] - 1.0, 30))
    lines = []
    for k, te in enumerate(tev):
        lines.append(f'{k + 1}\t{SOW0 + te:.6f}\t[{WEEK}]\t     0,N\t     0,E\t     0,V\t{LAT0:.8f},Lat\t{LON0:.8f},Lon\t'
                     f'{H0 + 80:.3f},Ellh\t1.500000, 1.500000, 3.000000\t16,Q')
    (HERE / 'Timestamp.MRK').write_text('\n'.join(lines) + '\n')

    # RTKLIB _events.pos: the solution at each exposure (GPST week/seconds times)
    e, n, u = (np.array(v) for v in zip(*[enu_at(float(tt)) for tt in tev]))
    la, lo, hh = geodetic(e, n, u)
    lines = ['% program   : RTKLIB ver.demo5 b34h', '% pos mode  : Kinematic', '%',
             '% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites)',
             '%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  '
             'sdne(m)  sdeu(m)  sdun(m) age(s)  ratio']
    for k, te in enumerate(tev):
        lines.append(f'{WEEK} {SOW0 + te:12.4f} {la[k]:14.9f} {lo[k]:14.9f} {hh[k]:10.4f} {1:3d} {22:3d} {0.009:8.4f} '
                     f'{0.008:8.4f} {0.017:8.4f} {0.0:8.4f} {0.0:8.4f} {0.0:8.4f} {0.0:6.2f} {60.1:6.1f}')
    (HERE / 'rtklib_demo5_events.pos').write_text('\n'.join(lines) + '\n')


if __name__ == '__main__':
    main()
