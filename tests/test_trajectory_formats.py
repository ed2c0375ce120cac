"""`geotag --pos` on every trajectory format it reads, recognised by content.

The files in tests/data/trajectories/ are one flight written in each program's documented export layout
(tests/data/trajectories/README.md says how and why). Each is read through the registry and placed at
the 30 exposures of the folder's Timestamp.MRK; the antenna at each exposure must equal an independent
interpolation within 1 mm: the file's raw columns parsed here with the standard library, turned into
ECEF with pyproj, and interpolated with scipy's cubic Hermite spline on numpy's centred differences.
"""

from __future__ import annotations

import csv
import math
import re
import shutil
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
from pyproj import Transformer
from scipy.interpolate import CubicHermiteSpline

from photogram_ros.core.exposure_positions import ExposureOptions
from photogram_ros.errors import DataError
from photogram_ros.io.geotag import GeotagInput, geotag
from photogram_ros.io.trajectory_formats import READERS, read_trajectory, sniff

DATA = Path(__file__).parent / 'data' / 'trajectories'
MRK = DATA / 'Timestamp.MRK'
GPS0 = datetime(1980, 1, 6, tzinfo=timezone.utc).timestamp()
WEEK_S = 604800.0
TO_ECEF = Transformer.from_crs('EPSG:4979', 'EPSG:4978', always_xy=True)


def _gps_of(dt: datetime, leap: float) -> float:
    return dt.timestamp() - GPS0 + leap


def _dms(text: str) -> float:
    nums = [float(v) for v in re.findall(r'\d+(?:\.\d+)?', text)]
    v = nums[0] + nums[1] / 60 + nums[2] / 3600
    return -v if text.strip().startswith('-') or text.strip()[-1] in 'SW' else v


# Raw columns of each file -> (t_gps_s, lat_deg, lon_deg, h_m), parsed here independently of the readers.
def raw_rtklib_demo5(p):
    out = []
    for ln in p.read_text().splitlines():
        if ln.startswith('%'):
            continue
        f = ln.split()
        dt = datetime.strptime(f[0] + ' ' + f[1], '%Y/%m/%d %H:%M:%S.%f').replace(tzinfo=timezone.utc)
        out.append((_gps_of(dt, 0), float(f[2]), float(f[3]), float(f[4])))
    return out


def raw_emlid_pos(p):       # UTC week / seconds
    return [(int(f[0]) * WEEK_S + float(f[1]) + 18, float(f[2]), float(f[3]), float(f[4]))
            for f in (ln.split() for ln in p.read_text().splitlines() if not ln.startswith('%'))]


def raw_grafnav(p):         # GPS seconds of week; the week is the MRK's
    week = int(re.search(r'\[(\d+)\]', MRK.read_text()).group(1))
    out = []
    for ln in p.read_text().splitlines():
        f = ln.split()
        if len(f) == 13 and re.match(r'^\d+\.\d+$', f[0]):
            out.append((week * WEEK_S + float(f[0]), _dms(' '.join(f[1:4])), _dms(' '.join(f[4:7])), float(f[7])))
    return out


def raw_inertial_explorer(p):   # UTC date and time
    rows = [r for r in csv.reader(p.read_text().splitlines()) if r and re.match(r'^\d\d/', r[0])]
    return [(_gps_of(datetime.strptime(f'{r[0]} {r[1]}', '%m/%d/%Y %H:%M:%S.%f').replace(tzinfo=timezone.utc), 18),
             float(r[2]), float(r[3]), float(r[4])) for r in rows]


def raw_emlid_csv(p):
    out = []
    for r in csv.DictReader(p.read_text().splitlines()):
        dt = datetime.strptime(r['Averaging start'].replace(' UTC', ''), '%Y-%m-%d %H:%M:%S.%f%z')
        out.append((_gps_of(dt, 18), float(r['Latitude']), float(r['Longitude']), float(r['Ellipsoidal height'])))
    return out


def raw_tbc(p):
    return [(int(r['GPS Week']) * WEEK_S + float(r['GPS Seconds']), float(r['Latitude']), float(r['Longitude']),
             float(r['Ellipsoidal Height (m)'])) for r in csv.DictReader(p.read_text().splitlines())]


def raw_leica(p):
    out = []
    for r in csv.DictReader(p.read_text(encoding='utf-8').splitlines(), delimiter=';'):
        dt = datetime.strptime(r['Date/Time (GPS)'], '%d.%m.%Y %H:%M:%S.%f').replace(tzinfo=timezone.utc)
        out.append((_gps_of(dt, 0), _dms(r['Latitude']), _dms(r['Longitude']), float(r['Ellip. Hgt.'])))
    return out


FILES = {  # file: (raw parser, format said, time system)
    'rtklib_demo5_5hz.pos': (raw_rtklib_demo5, 'RTKLIB-demo5 .pos', 'GPST'),
    'emlid_studio_5hz.pos': (raw_emlid_pos, 'Emlid Studio .pos', 'UTC'),
    'grafnav_5hz_dms.txt': (raw_grafnav, 'NovAtel GrafNav export', 'GPST'),
    'inertial_explorer_5hz_utc.csv': (raw_inertial_explorer, 'NovAtel Inertial Explorer export', 'UTC'),
    'emlid_studio_5hz.csv': (raw_emlid_csv, 'Emlid Studio CSV', 'UTC'),
    'tbc_5hz.csv': (raw_tbc, 'Trimble Business Center CSV', 'GPST'),
    'leica_infinity_5hz.csv': (raw_leica, 'Leica Infinity CSV', 'GPST'),
}


def _mrk_times() -> np.ndarray:
    return np.array([int(m.group(2)) * WEEK_S + float(m.group(1))
                     for m in re.finditer(r'^\d+\t([\d.]+)\t\[(\d+)\]', MRK.read_text(), re.M)])


def _ecef(lat, lon, h) -> np.ndarray:
    x, y, z = TO_ECEF.transform(np.asarray(lon), np.asarray(lat), np.asarray(h))
    return np.column_stack([x, y, z])


def independent_antenna(raw, times, cubic: bool = False) -> np.ndarray:
    """The antenna at `times` from the raw columns: linear in ECEF between epochs (geotag's default), or scipy's
    cubic Hermite spline on centred-difference velocities."""
    t, lat, lon, h = (np.array(v) for v in zip(*raw))
    xyz = _ecef(lat, lon, h)
    if not cubic:
        return np.column_stack([np.interp(times, t, xyz[:, k]) for k in range(3)])
    spline = CubicHermiteSpline(t - t[0], xyz, np.gradient(xyz, t - t[0], axis=0))
    return spline(times - t[0])


@pytest.mark.parametrize('name', sorted(FILES))
def test_each_format_is_recognised_and_placed_as_an_independent_interpolation(name, tmp_path):
    raw_of, fmt, system = FILES[name]
    res = geotag(GeotagInput(str(DATA / name), str(MRK), None, str(tmp_path / 'geo.txt')))
    assert res.notes[1].startswith(f'{name}: read as {fmt}') or any(n.startswith(f'{name}: read as {fmt}')
                                                                     for n in res.notes)
    assert any(f'times in {system}' in n for n in res.notes)
    assert len(res.rows) == 30 and not [p for p in res.problems if 'has no photo' not in p]
    times = _mrk_times()
    ours = _ecef([pe.antenna_lat_deg for _, pe in res.rows], [pe.antenna_lon_deg for _, pe in res.rows],
                 [pe.antenna_h_m for _, pe in res.rows])
    ref = independent_antenna(raw_of(DATA / name), times)
    d = np.linalg.norm(ours - ref, axis=1)
    print(f'{name}: {fmt}, 30 exposures, max {d.max() * 1000:.3f} mm from the independent interpolation')
    assert d.max() < 1e-3
    # the per-epoch sigmas became the photos' accuracies (1-3 cm here; the float epochs' floor 10 cm)
    h_acc = np.array([pe.h_acc_m for _, pe in res.rows])
    assert np.all((h_acc > 0.004) & (h_acc < 0.2)) and np.median(h_acc) < 0.015


def test_events_pos_is_read_at_the_events(tmp_path):
    res = geotag(GeotagInput(str(DATA / 'rtklib_demo5_events.pos'), str(MRK), None, str(tmp_path / 'geo.txt')))
    assert res.placement.mode == 'at events' and len(res.rows) == 30
    raw = [(int(f[0]) * WEEK_S + float(f[1]), float(f[2]), float(f[3]), float(f[4]))
           for f in (ln.split() for ln in (DATA / 'rtklib_demo5_events.pos').read_text().splitlines()
                     if not ln.startswith('%'))]
    ref = _ecef(*[np.array(v) for v in list(zip(*raw))[1:]])
    ours = _ecef([pe.antenna_lat_deg for _, pe in res.rows], [pe.antenna_lon_deg for _, pe in res.rows],
                 [pe.antenna_h_m for _, pe in res.rows])
    assert np.linalg.norm(ours - ref, axis=1).max() < 1e-3


def test_accept_works_on_every_quality_scale(tmp_path):
    """The epochs 150-157 are float in every file (RTKLIB Q 2, GrafNav Q 3, FLOAT, Float, Phase float): --accept fix
    leaves out the same exposures whatever the format."""
    left_out = {}
    for name in FILES:
        res = geotag(GeotagInput(str(DATA / name), str(MRK), None, str(tmp_path / f'{name}.txt'), skip_unplaced=True,
                                 options=ExposureOptions(accept_q=1)))
        left_out[name] = sorted(p.split('(event ')[1].split(')')[0] for p in res.problems if 'worse than' in p)
    first = next(iter(left_out.values()))
    assert first and all(v == first for v in left_out.values()), left_out


def test_unknown_and_ambiguous_files_are_refused_naming_what_was_expected(tmp_path):
    junk = tmp_path / 'notes.txt'
    junk.write_text('flight notes\nwind 5 m/s\n')
    with pytest.raises(DataError) as e:
        read_trajectory(junk)
    msg = str(e.value)
    assert '\n' not in msg and all(r.name in msg for r in READERS) and 'GPSTime Latitude Longitude H-Ell' in msg
    both = tmp_path / 'both.csv'
    both.write_text('Latitude,Longitude,Ellipsoidal Height,Horizontal Precision,Sd Lat,GPS Week,GPS Seconds\n'
                    '46.5,6.5,500,0.01,0.01,2304,378000\n')
    with pytest.raises(DataError, match='ambiguous.*Trimble Business Center CSV|ambiguous.*Leica Infinity CSV'):
        read_trajectory(both)
    # the case: a GrafNav export is no longer refused as "not an RTKLIB .pos file"
    reader, scores = sniff(DATA / 'grafnav_5hz_dms.txt')
    assert reader.name.startswith('NovAtel') and len(scores) == 1


def test_grafnav_columns_are_mapped_by_their_names(tmp_path):
    """The same epochs with the profile's columns in another order, GPSWeek and SDNorth/SDEast present, commas."""
    src = read_trajectory(DATA / 'grafnav_5hz_dms.txt', require_fix=False).in_week_of(_mrk_times()[0])
    lines = ['Program:     Waypoint GrafNav 8.90', 'Q,NS,SDEast,SDNorth,SDHeight,H-Ell,Longitude,Latitude,GPSWeek,GPSTime']
    from photogram_ros.core.geodesy import ecef_to_geodetic
    for k in range(len(src)):
        la, lo, h = (float(v) for v in ecef_to_geodetic(*src.ecef_m[k]))
        week, sow = divmod(src.t_gps_s[k], WEEK_S)
        sd = src.sigma_enu_m()[k]
        lines.append(f'{src.q_native[k]},20,{sd[0]:.4f},{sd[1]:.4f},{sd[2]:.4f},{h:.4f},{lo:.10f},{la:.10f},'
                     f'{int(week)},{sow:.2f}')
    p = tmp_path / 'reordered.txt'
    p.write_text('\n'.join(lines) + '\n')
    t = read_trajectory(p)
    assert t.week_known and t.format.startswith('NovAtel GrafNav') and len(t) == len(src)
    assert np.abs(t.t_gps_s - src.t_gps_s).max() < 1e-6
    assert np.linalg.norm(t.ecef_m - src.ecef_m, axis=1).max() < 1e-3
    assert np.array_equal(t.q, src.q)
    # heights above the geoid only: refused, saying what to export
    p.write_text('\n'.join(lines).replace('H-Ell', 'H-MSL') + '\n')
    with pytest.raises(DataError, match='H-Ell'):
        read_trajectory(p)


def test_event_delay_moves_each_exposure_along_the_track(tmp_path):
    """Exposures 30 ms after marks at 10-12 m/s: 30 cm off without --event-delay-ms, on the truth with it."""
    sys.path.insert(0, str(DATA))
    try:
        import make_layouts as ml
    finally:
        sys.path.pop(0)
    marks = tmp_path / 'Timestamp.MRK'
    marks.write_text(re.sub(r'^(\d+\t)([\d.]+)', lambda m: f'{m.group(1)}{float(m.group(2)) - 0.030:.6f}',
                            MRK.read_text(), flags=re.M))
    truth = []
    for te in _mrk_times():
        e, n, u = ml.enu_at(te - ml.WEEK * WEEK_S - ml.SOW0)
        truth.append((e, n, u))
    lat, lon, h = ml.geodetic(*[np.array(v) for v in zip(*truth)])
    ref = _ecef(lat, lon, h)
    err = {}
    for delay in (0.0, 0.030):
        res = geotag(GeotagInput(str(DATA / 'rtklib_demo5_5hz.pos'), str(marks), None, str(tmp_path / 'g.txt'),
                                 options=ExposureOptions(event_delay_s=delay, interpolation='cubic')))
        ours = _ecef([pe.lat_deg for _, pe in res.rows], [pe.lon_deg for _, pe in res.rows],
                     [pe.h_m for _, pe in res.rows])
        err[delay] = np.linalg.norm(ours - ref, axis=1)
    print(f'without the delay: median {np.median(err[0.0]) * 100:.1f} cm; with --event-delay-ms 30: max '
          f'{err[0.030].max() * 1000:.2f} mm')
    assert np.median(err[0.0]) > 0.28 and err[0.030].max() < 0.01


def test_a_cut_off_last_mrk_line_is_skipped_and_named(tmp_path):
    from photogram_ros.io.camera_events import read_mrk
    text = MRK.read_text().rstrip('\n')
    cut = tmp_path / 'Timestamp.MRK'
    cut.write_text(text[:-40])
    notes = []
    rows = read_mrk(cut, notes)
    assert len(rows) == 29 and len(notes) == 1 and 'line 30' in notes[0] and 'cut off' in notes[0]
    res = geotag(GeotagInput(str(DATA / 'tbc_5hz.csv'), str(cut), None, str(tmp_path / 'geo.txt')))
    assert len(res.rows) == 29 and any('cut off' in n for n in res.notes)
    # a bad line elsewhere is still an error naming it
    lines = text.splitlines()
    lines[5] = lines[5][:20]
    cut.write_text('\n'.join(lines) + '\n')
    with pytest.raises(DataError, match='line 6'):
        read_mrk(cut)


def test_geotag_command_says_the_format(tmp_path, capsys):
    from photogram_ros.cli import main
    shutil.copy(DATA / 'leica_infinity_5hz.csv', tmp_path / 'traj.csv')
    rc = main(['geotag', '--pos', str(tmp_path / 'traj.csv'), '--events', str(MRK), '--out', str(tmp_path / 'g.txt'),
               '--accept', 'float', '--event-delay-ms', '-5'])
    err = capsys.readouterr().err
    assert rc == 0 and 'read as Leica Infinity CSV' in err and '-5.0 ms' in err
    assert math.isfinite(float((tmp_path / 'g.txt').read_text().splitlines()[1].split()[1]))


REAL = {  # excerpts of real public RTKLIB solutions (tests/data/trajectories/README.md: source and licence)
    'real_rtklib_demo5_ublox_excerpt.pos': 'RTKLIB-demo5 .pos',
    'real_matrtklib_kinematic_excerpt.pos': 'RTKLIB .pos',
}


@pytest.mark.parametrize('name', sorted(REAL))
def test_real_rtklib_excerpts_placed_as_an_independent_interpolation(name):
    """Exposures inside every 1 s interval whose neighbours are 1 s away too (where the track is interpolated
    cubically) equal scipy's cubic Hermite spline on the raw columns; an exposure in a 4 s hole is refused."""
    from photogram_ros.core.exposure_positions import CameraEvent, place_exposures
    track = read_trajectory(DATA / name, require_fix=False)
    assert track.format == REAL[name] and track.time_system == 'GPST'
    raw = raw_rtklib_demo5(DATA / name)
    t = np.array([r[0] for r in raw])
    d = np.diff(t)
    ks = [k for k in range(1, len(t) - 2) if d[k - 1] == d[k] == d[k + 1] == 1.0]
    times = np.array([t[k] + 0.137 + 0.7 * (i % 2) for i, k in enumerate(ks)])
    events = [CameraEvent(i + 1, float(tt), i + 1, where='test') for i, tt in enumerate(times)]
    holes = [t[k] + 1.9 for k in range(len(d)) if d[k] >= 4.0]
    events += [CameraEvent(900 + i, float(tt), 900 + i, where='test') for i, tt in enumerate(holes)]
    placed = place_exposures(track, events, ExposureOptions(interpolation='cubic'))
    assert len(placed.placed) == len(times) and len(placed.problems) == len(holes)
    assert all('gap' in p for p in placed.problems)
    ours = _ecef([pe.antenna_lat_deg for pe in placed.placed], [pe.antenna_lon_deg for pe in placed.placed],
                 [pe.antenna_h_m for pe in placed.placed])
    ref = independent_antenna(raw, times, cubic=True)
    dist = np.linalg.norm(ours - ref, axis=1)
    print(f'{name}: {len(times)} exposures, max {dist.max() * 1000:.3f} mm from the independent interpolation; '
          f'{len(holes)} in holes refused')
    assert len(times) >= 10 and dist.max() < 1e-3
    # the file's sigmas became the accuracies: the float epochs' decimetres, the fixed ones' millimetres
    acc = np.array([pe.h_acc_m for pe in placed.placed])
    q = np.array([pe.q for pe in placed.placed])
    assert np.all(acc[q == 1] < 0.01) and (not np.any(q == 2) or np.all(acc[q == 2] >= 0.10))


# The header of a real Inertial Explorer 8.30 export and its first epoch, as the CReSIS toolbox's
# read_gps_novatel.m quotes them (a comment of that file in the CReSIS toolbox, e.g. CReSIS/OLD_cresis-toolbox): CorrTime
# (GPS seconds of week), Date (MDY), latitude/longitude in +/-D M S, H-Ell, the attitude.
CRESIS_IE = """
Project:     rover_diff_antarctica_01022010
Program:     Inertial Explorer Version 8.30.0623
Profile:     CReSIS
Source:      GPS Epochs(Smoothed TC Combined)

Datum:       WGS84, (processing datum)
Master 1:    Name base_antarctica, Status ENABLED
             Antenna height 0.054 m, to L1-PC (JPSLEGANT_E, MeasDist 0.000 m to mark/ARP)
             Position -80 00 42.83213, -119 33 24.98087, 1496.009 m (WGS84, Ellipsoidal hgt)
Remote:      Antenna height 0.000 m, to L1-PC (Generic)
SD/Covariance Scaling Settings:
  Position: No scaling (1-sigma)
  Velocity: No scaling (1-sigma)
  Attitude: No scaling (1-sigma)
  Increase SD on kinematic float: Yes

 CorrTime       Date         Latitude        Longitude        H-Ell        Heading        HdngSep         HdngSD          Pitch        PtchSep        PitchSD           Roll        RollSep         RollSD
    (sec)      (MDY)       (+/-D M S)       (+/-D M S)          (m)          (Deg)          (Deg)          (Deg)          (Deg)          (Deg)          (Deg)          (Deg)          (Deg)          (Deg)
598861.01  1/02/2010  -79 28 10.85149 -112 03 17.05073     1765.359  51.2305580000 359.9682999998   0.0198516510  -1.2856740000 359.9926000000   0.0049116057   0.0289810000 359.9872000003   0.0048216125
"""


def test_a_real_inertial_explorer_header_and_epoch(tmp_path):
    p = tmp_path / 'rover_diff.txt'
    p.write_text(CRESIS_IE + '598862.01  1/02/2010  -79 28 10.80000 -112 03 17.00000     1765.400' + ' 0' * 9
                 + '\n\nFooter lines\n   - not an epoch\n')
    t = read_trajectory(p)
    assert t.format.startswith('NovAtel Inertial Explorer export') and t.time_system == 'GPST' and len(t) == 2
    from photogram_ros.core.geodesy import ecef_to_geodetic
    lat, lon, h = (float(v) for v in ecef_to_geodetic(*t.ecef_m[0]))
    assert lat == pytest.approx(-(79 + 28 / 60 + 10.85149 / 3600), abs=1e-9)
    assert lon == pytest.approx(-(112 + 3 / 60 + 17.05073 / 3600), abs=1e-9) and h == pytest.approx(1765.359, abs=1e-4)
    # 2010-01-02 is the Saturday of GPS week 1564: 598861.01 s into it
    assert t.t_gps_s[0] == pytest.approx(1564 * WEEK_S + 598861.01, abs=1e-6)
    assert any('no Q column' in n for n in t.notes)


def test_inertial_explorer_hour_minute_second_columns_and_ecef_sigmas(tmp_path):
    """The layout of an IE export with `UTCDate UT UT UTCTim` (units `(MDY) ho mi (sec)`), DMS, X/Y/Z-ECEF with
    their SDs, attitude, Q (as a public writer of the IE 8.60 layout, IEWriter.cpp, writes it)."""
    src = read_trajectory(DATA / 'inertial_explorer_5hz_utc.csv')
    from photogram_ros.core.geodesy import ecef_to_geodetic
    lines = ['Program:     Inertial Explorer Version 8.60.4609', 'UTC Offset:  18s', '', '',
             'UTCDate     UT UT UTCTim       Latitude        Longitude         H-Ell         X-ECEF        SDX-ECEF'
             '       Y-ECEF       SDY-ECEF       Z-ECEF       SDZ-ECEF       Roll       RollSD      Q        Heave',
             '(MDY)       ho mi  (sec)      (+/-D M S)       (+/-D M S)         (m)           (m)             (m)'
             '           (m)          (m)            (m)          (m)          (deg)       (deg)                (m)']
    for k in range(len(src)):
        dt = datetime.fromtimestamp(src.t_gps_s[k] + GPS0 - 18, tz=timezone.utc)
        la, lo, h = (float(v) for v in ecef_to_geodetic(*src.ecef_m[k]))
        x, y, z = src.ecef_m[k]

        def dms(v):
            d = int(v)
            m = int((v - d) * 60)
            return f'{d} {m} {((v - d) * 60 - m) * 60:.6f}'
        lines.append(f'{dt:%m/%d/%Y}  {dt:%H} {dt:%M} {dt.second + dt.microsecond / 1e6:06.3f}     {dms(la)} {dms(lo)}'
                     f'     {h:.6f}      {x:.3f}      0.010      {y:.3f}      0.010      {z:.3f}      0.010      0.5'
                     f'      0.01      1      0.0')
    p = tmp_path / 'ie.txt'
    p.write_text('\n'.join(lines) + '\n')
    t = read_trajectory(p)
    assert t.time_system == 'UTC' and len(t) == len(src)
    assert np.abs(t.t_gps_s - src.t_gps_s).max() < 2e-3
    assert np.linalg.norm(t.ecef_m - src.ecef_m, axis=1).max() < 1e-3
    assert np.allclose(t.sigma_enu_m(), 0.010, atol=1e-6)         # isotropic ECEF sigmas stay 1 cm on each axis


def test_cubic_interpolation_on_request(tmp_path):
    res = geotag(GeotagInput(str(DATA / 'tbc_5hz.csv'), str(MRK), None, str(tmp_path / 'g.txt'),
                             options=ExposureOptions(interpolation='cubic')))
    ref = independent_antenna(raw_tbc(DATA / 'tbc_5hz.csv'), _mrk_times(), cubic=True)
    ours = _ecef([pe.antenna_lat_deg for _, pe in res.rows], [pe.antenna_lon_deg for _, pe in res.rows],
                 [pe.antenna_h_m for _, pe in res.rows])
    assert np.linalg.norm(ours - ref, axis=1).max() < 1e-3


@pytest.mark.slow
def test_simulated_shutter_delay_is_taken_back_by_event_delay_ms(tmp_path):
    """`simulate --ppk` flown at 12 m/s with the shutter 30 ms after the MRK's marks and the .pos the true antenna
    track: without --event-delay-ms the cameras are 36 cm back along the track, with 30 ms every photo where the
    true track is smooth (lines, turns) within 1 cm. The photos at the simulator's instant speed changes (parked
    to 12 m/s at take-off; 12 to 2.5 m/s into a turn) are where the product equals an independent linear
    interpolation of the .pos epochs (to 1 mm): the 5 Hz track's own limit, not the delay."""
    from photogram_ros.core.exposure_positions import gps_s_to_utc_unix
    from photogram_ros.core.geodesy import ecef_to_geodetic
    from photogram_ros.io.trajectory_formats import read_trajectory
    from photogram_ros.sim.scenario import START_UNIX_S, preset, simulate
    from photogram_ros.sim.truth import GroundTruth
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / 'bench'))
    try:
        import ppk_formats
    finally:
        sys.path.pop(0)
    root = tmp_path / 'flight'
    simulate(preset('tiny', fps=2.5, ppk=True, speed_mps=12.0, ppk_shutter_delay_ms=30.0, ppk_sigma_scale=0.0), root)
    truth = GroundTruth.load(root)
    ppk = root / 'ppk'
    frame = {f'IMG_{f.index:04d}.JPG': f for f in truth.frames}
    t_truth = np.array([f['t_fix_unix_s'] for f in truth.fixes]) - START_UNIX_S
    ant_truth = np.array([f['antenna_enu'] for f in truth.fixes])
    track = read_trajectory(ppk / 'flight.pos')
    t_pos = np.array([gps_s_to_utc_unix(t) for t in track.t_gps_s]) - START_UNIX_S
    pos_enu = np.array([truth.origin.geodetic_to_enu(*ecef_to_geodetic(*x)) for x in track.ecef_m])
    err, names = {}, []
    for delay_ms in (0.0, 30.0):
        res = geotag(GeotagInput(str(ppk / 'flight.pos'), str(ppk / 'Timestamp.MRK'), str(ppk), str(tmp_path / 'g.txt'),
                                 options=ExposureOptions(event_delay_s=delay_ms * 1e-3)))
        names = [n for n, _ in res.rows]
        err[delay_ms] = np.array([truth.origin.geodetic_to_enu(pe.lat_deg, pe.lon_deg, pe.h_m)
                                  - frame[n].map_T_cam[:3, 3] for n, pe in res.rows])
    t_exp = np.array([frame[n].stamp_ns * 1e-9 - START_UNIX_S for n in names])
    acc = ppk_formats.truth_acceleration_mps2(t_exp, t_truth, ant_truth)
    e0, e30 = np.linalg.norm(err[0.0], axis=1), np.linalg.norm(err[30.0], axis=1)
    row = ppk_formats.split_by_motion(e30, acc)
    print(f'{len(e0)} photos: without the delay median {np.median(e0) * 100:.1f} cm; with --event-delay-ms 30: '
          f'{row["smooth_photos"]} on a smooth track max {row["smooth_max_m"] * 1000:.2f} mm, '
          f'{row["speed_step_photos"]} at a speed step max {row["speed_step_max_m"] * 100:.1f} cm')
    assert 0.35 < np.median(e0) < 0.37
    assert row['smooth_photos'] >= 0.6 * len(e30) and row['smooth_max_m'] < 0.01
    # at the steps: the product's antenna is the linear interpolation of the epochs (the camera's offset is exact)
    step = acc > ppk_formats.SPEED_STEP_MPS2
    lin = np.array([[np.interp(t, t_pos, pos_enu[:, k]) for k in range(3)] for t in t_exp[step]])
    miss = lin - np.array([frame[n].antenna_enu for n, s in zip(names, step) if s])
    assert np.linalg.norm(err[30.0][step] - miss, axis=1).max() < 1e-3
