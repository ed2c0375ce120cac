"""Real trajectory layouts (tests/data/trajectories/LAYOUT_SOURCES.md): a real GrafNav 9.00 export copied
verbatim, and an M300 flight written in a real Waypoint export profile's columns with a DJI-layout MRK;
positions at the events against interpolations written here, independently of the product code."""

from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
from pyproj import Transformer
from scipy.interpolate import CubicHermiteSpline

from photogram_ros.core.exposure_positions import CameraEvent, ExposureOptions, place_exposures
from photogram_ros.errors import DataError
from photogram_ros.io.camera_events import read_mrk
from photogram_ros.io.geotag import GeotagInput, geotag
from photogram_ros.io.trajectory_formats import read_trajectory

DATA = Path(__file__).parent / 'data' / 'trajectories'
GPS_EPOCH = datetime(1980, 1, 6, tzinfo=timezone.utc)
TO_ECEF = Transformer.from_crs('EPSG:4979', 'EPSG:4978', always_xy=True)
TO_LLH = Transformer.from_crs('EPSG:4978', 'EPSG:4979', always_xy=True)


def _ecef(lat, lon, h) -> np.ndarray:
    return np.column_stack(TO_ECEF.transform(np.asarray(lon), np.asarray(lat), np.asarray(h)))


def _enu_to_ecef_rot(lat, lon) -> np.ndarray:
    la, lo = np.radians(lat), np.radians(lon)
    return np.array([[-np.sin(lo), -np.sin(la) * np.cos(lo), np.cos(la) * np.cos(lo)],
                     [np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la) * np.sin(lo)],
                     [0.0, np.cos(la), np.sin(la)]])


def test_real_grafnav_9_export_utc_hms_h_ell_and_a_cut_off_last_epoch():
    """luftkode/plotinator3000 test_data/csv/20250909_05_GP1_PPP.txt, verbatim (CRLF, a 36-line header with a
    column description block, UTCDate YMD + UTCTime HMS, H-MSL before H-Ell, Q 3, its last epoch cut off)."""
    path = DATA / 'real_grafnav900_ppp_plotinator.txt'
    assert path.read_bytes().count(b'\r\n') == 45
    track = read_trajectory(path, require_fix=False)
    assert track.format == 'NovAtel GrafNav export (GrafNav Version 9.00.2207)' and track.time_system == 'UTC'
    assert len(track) == 7 and any('line 45: cut off' in n for n in track.notes)
    assert list(track.q_native) == [3] * 7 and list(track.q) == [2] * 7          # Q 3: float
    with pytest.raises(DataError, match='no fixed solution'):
        read_trajectory(path)
    raw = []
    for ln in path.read_text().splitlines()[37:44]:
        v = ln.split()
        utc = datetime.strptime(f'{v[1]} {v[2]}', '%Y/%m/%d %H:%M:%S.%f').replace(tzinfo=timezone.utc)
        raw.append(((utc - GPS_EPOCH).total_seconds() + 18.0, float(v[3]), float(v[4]), float(v[11])))
    t, lat, lon, h = (np.array(c) for c in zip(*raw))
    times = np.array([t[1] + 0.31, t[2] + 0.5, t[4] + 0.93])
    events = [CameraEvent(i + 1, float(x), i + 1, where='test') for i, x in enumerate(times)]
    xyz = _ecef(lat, lon, h)
    refs = {'linear': np.column_stack([np.interp(times, t, xyz[:, k]) for k in range(3)]),
            'cubic': CubicHermiteSpline(t - t[0], xyz, np.gradient(xyz, t - t[0], axis=0))(times - t[0])}
    for how, ref in refs.items():
        placed = place_exposures(track, events, ExposureOptions(interpolation=how))
        assert len(placed.placed) == 3 and not placed.problems
        ours = _ecef([p.antenna_lat_deg for p in placed.placed], [p.antenna_lon_deg for p in placed.placed],
                     [p.antenna_h_m for p in placed.placed])
        d = np.linalg.norm(ours - ref, axis=1)
        print(f'real GrafNav 9.00 export, {how}: max {d.max() * 1e3:.4f} mm from the independent interpolation')
        assert d.max() < 1e-3
    assert np.all(np.abs(np.array([p.antenna_h_m for p in placed.placed]) - 73.39) < 0.01)   # H-Ell, not H-MSL


def _authors_way(traj: Path, mrk: Path) -> tuple[np.ndarray, np.ndarray]:
    """Camera positions as an M300 + Waypoint PPK script computes them: the columns by position (19 lines
    skipped), latitude, longitude and H-Ell interpolated linearly in GPSTime (sec), then the MRK's offset applied
    as east = E, north = N, up = -V (mm) at the interpolated antenna. Returns (GPS seconds of week, camera ECEF)."""
    rows = [ln.split() for ln in traj.read_text().splitlines()[19:] if ln.strip()]
    t = np.array([float(r[5]) for r in rows])
    lat, lon, h = (np.array([float(r[k]) for r in rows]) for k in (6, 7, 8))
    out, tow = [], []
    for ln in mrk.read_text().splitlines():
        f = ln.split('\t')
        x = float(f[1])
        n_mm, e_mm, v_mm = (float(f[k].split(',')[0]) for k in (3, 4, 5))
        a_lat, a_lon, a_h = (np.interp(x, t, c) for c in (lat, lon, h))
        ant = _ecef([a_lat], [a_lon], [a_h])[0]
        out.append(ant + _enu_to_ecef_rot(a_lat, a_lon) @ (np.array([e_mm, n_mm, -v_mm]) / 1000.0))
        tow.append(x)
    return np.array(tow), np.array(out)


@pytest.mark.parametrize('interpolation', ['linear', 'cubic'])
def test_waypoint_m300_profile_with_its_mrk_offsets(interpolation, tmp_path):
    """The real M300 Waypoint export's layout (UTCTime in weeks, HMS and sec; GPSTime in HMS and sec; SDHoriz,
    SDHeight, Q), a trailing blank line, and a DJI MRK with offsets (CRLF): every photo placed; linear
    interpolation (the default) equals the authors' way within 1 mm; on these smooth lines cubic stays within 2 mm median / 5 mm max of it."""
    traj, mrk = DATA / 'waypoint_m300_5hz.txt', DATA / 'm300_Timestamp.MRK'
    res = geotag(GeotagInput(str(traj), str(mrk), None, str(tmp_path / 'geo.txt'),
                             options=ExposureOptions(interpolation=interpolation)))
    assert any('read as NovAtel GrafNav export (GrafNav Version 8.90.6611)' in n and 'times in GPST' in n
               for n in res.notes)
    events = read_mrk(mrk)
    assert len(res.rows) == len(events) == 25
    assert not [p for p in res.problems if 'has no photo' not in p]
    tow, ref = _authors_way(traj, mrk)
    ours = _ecef([pe.lat_deg for _, pe in res.rows], [pe.lon_deg for _, pe in res.rows],
                 [pe.h_m for _, pe in res.rows])
    assert np.allclose([pe.event.t_gps_s % 604800 for _, pe in res.rows], tow, atol=1e-6)
    d = np.linalg.norm(ours - ref, axis=1)
    print(f'Waypoint M300 layout, {interpolation}: median {np.median(d) * 1e3:.3f} mm, max {d.max() * 1e3:.3f} mm '
          'from the authors\' way (linear + MRK offsets)')
    if interpolation == 'linear':
        assert d.max() < 1e-3
    else:
        assert np.median(d) < 2e-3 and d.max() < 5e-3
    # the offsets were applied (camera != antenna by the MRK's 12-21 cm), and SDHoriz became the accuracy
    ant = _ecef([pe.antenna_lat_deg for _, pe in res.rows], [pe.antenna_lon_deg for _, pe in res.rows],
                [pe.antenna_h_m for _, pe in res.rows])
    assert np.all(np.linalg.norm(ours - ant, axis=1) > 0.1)
    h_acc = np.array([pe.h_acc_m for _, pe in res.rows])
    q = np.array([pe.q for _, pe in res.rows])
    print(sorted(set(zip(q.tolist(), h_acc.round(4).tolist()))))
    assert np.all(h_acc[q == 1] < 0.01) and np.all(h_acc[q == 2] >= 0.1)     # SDHoriz 5 mm; a float epoch's floor


def test_mrk_offset_signs_follow_djis_documentation(tmp_path):
    """DJI (Zenmuse P1 / Matrice 4 manuals): N positive north, E positive east, V positive down. A track standing
    still: the camera is the antenna + N north, + E east, - V up."""
    lat0, lon0, h0 = 13.7367, 100.5332, 150.0
    week, sow = 2235, 21198.0
    lines = [f'% program   : RTKLIB ver.demo5 b34f', '%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns']
    for k in range(20):
        lines.append(f'{week} {sow + k * 0.2:10.3f}   {lat0:.9f}  {lon0:.9f}  {h0:10.4f}   1  20')
    pos = tmp_path / 'still.pos'
    pos.write_text('\n'.join(lines) + '\n')
    mrk = tmp_path / 'still_Timestamp.MRK'
    mrk.write_text(f'1\t{sow + 1.1:.6f}\t[{week}]\t   101,N\t   107,E\t   129,V\t{lat0:.8f},Lat\t{lon0:.8f},Lon\t'
                   f'{h0:.3f},Ellh\t0.002967, 0.003104, 0.007622\t50,Q\n'
                   f'2\t{sow + 2.1:.6f}\t[{week}]\t   -40,N\t   -25,E\t   -10,V\t{lat0:.8f},Lat\t{lon0:.8f},Lon\t'
                   f'{h0:.3f},Ellh\t0.002967, 0.003104, 0.007622\t50,Q\n')
    res = geotag(GeotagInput(str(pos), str(mrk), None, str(tmp_path / 'geo.txt')))
    assert len(res.rows) == 2
    x0 = _ecef([lat0], [lon0], [h0])[0]
    R = _enu_to_ecef_rot(lat0, lon0)
    for (_, pe), enu in zip(res.rows, ([0.107, 0.101, -0.129], [-0.025, -0.040, 0.010])):
        cam = _ecef([pe.lat_deg], [pe.lon_deg], [pe.h_m])[0]
        assert np.linalg.norm(R.T @ (cam - x0) - np.array(enu)) < 1e-4


def test_a_real_mrk_line_without_padding(tmp_path):
    """An MRK line as a public DJI-metadata test quotes it (`-40,N\t0,E\t86,V`, no padding; a single-point
    flag 16): the offsets, the GPS time and the onboard position are read."""
    mrk = tmp_path / 'flight_Timestamp.MRK'
    mrk.write_text('1\t400373.488877\t[2264]\t-40,N\t0,E\t86,V\t44.42824637,Lat\t1.26196331,Lon\t359.494,Ellh\t'
                   '0.028, 0.031, 0.055\t16,Q\n')
    (row,) = read_mrk(mrk)
    assert np.allclose(row.event.offset_ned_m, [-0.040, 0.0, 0.086])
    assert row.event.t_gps_s == pytest.approx(2264 * 604800 + 400373.488877)
    assert (row.fix.lat_deg, row.fix.lon_deg, row.fix.h_m, row.flag) == (44.42824637, 1.26196331, 359.494, 16)
    assert row.sd_neu_m == pytest.approx((0.028, 0.031, 0.055), abs=1e-12) and row.fix.quality == 5


def test_inertial_explorer_week_column_and_a_bare_unit_in_the_units_line(tmp_path):
    """`Week GPSTime UTCTime Longitude Latitude H-Ell ...` over `week (sec) (sec) (deg) ...` (the Inertial
    Explorer 8.90 column layout quoted in public code), a text line among the epochs: GPS time, week known."""
    p = tmp_path / 'ie.txt'
    p.write_text('Project:     gici\nProgram:     Inertial Explorer Version 8.90.6611\n\n'
                 'Week     GPSTime     UTCTime       Longitude       Latitude     H-Ell         Heading\n'
                 'week       (sec)       (sec)           (deg)          (deg)       (m)           (deg)\n'
                 '2254  120974.000  120956.000  121.0000000000  31.0000000000    10.000    359.0000000000\n'
                 'a text line\n'
                 '2254  120975.000  120957.000  121.0000100000  31.0000200000    11.000      1.0000000000\n')
    track = read_trajectory(p)
    assert track.format.startswith('NovAtel Inertial Explorer export') and track.time_system == 'GPST'
    assert track.week_known and np.allclose(track.t_gps_s, 2254 * 604800 + np.array([120974.0, 120975.0]))
    assert any('1 text lines between the epochs skipped (first: line 7)' in n for n in track.notes)


def test_the_issue_command_without_photos_or_out_writes_geo_txt_here(tmp_path, monkeypatch, capsys):
    """`photogram-ros geotag --pos PPK_5Hz.txt --events DJI_..._Timestamp.MRK` as issue #45 runs it: no photos beside
    the MRK and no --out: geo.txt and geo.csv in the current folder, every exposure placed, the format said."""
    from photogram_ros.cli import main
    work = tmp_path / 'flight'
    work.mkdir()
    (work / 'PPK_5Hz.txt').write_bytes((DATA / 'waypoint_m300_5hz.txt').read_bytes())
    (work / 'DJI_202211061253_001_Timestamp.MRK').write_bytes((DATA / 'm300_Timestamp.MRK').read_bytes())
    monkeypatch.chdir(tmp_path)
    rc = main(['geotag', '--pos', str(work / 'PPK_5Hz.txt'), '--events', str(work / 'DJI_202211061253_001_Timestamp.MRK')])
    cap = capsys.readouterr()
    assert rc == 0 and 'read as NovAtel GrafNav export' in cap.err and 'geotagged 25 photos' in cap.out
    rows = (tmp_path / 'geo.csv').read_text().splitlines()
    assert len(rows) == 26 and len((tmp_path / 'geo.txt').read_text().splitlines()) == 26


def test_a_cut_off_last_line_of_the_m300_mrk_is_skipped_and_named(tmp_path):
    """The M300 MRK (CRLF) with its last line cut mid-field, as a card pulled while the drone wrote it (#48): the
    whole lines are read, the cut one skipped and named with its line number."""
    text = (DATA / 'm300_Timestamp.MRK').read_bytes()
    assert text.endswith(b'\r\n') and text.count(b'\r\n') == 25
    cut = text + b'26\t21249.037000\t[2235]\t    12,N\t   -3'
    mrk = tmp_path / 'cut_Timestamp.MRK'
    mrk.write_bytes(cut)
    notes: list = []
    rows = read_mrk(mrk, notes)
    assert len(rows) == 25 and len(notes) == 1 and 'line 26: cut off' in notes[0]


def _waypoint_variant(kind: str) -> str:
    text = (DATA / 'waypoint_m300_5hz.txt').read_text()
    lines = text.splitlines()
    hi = next(i for i, ln in enumerate(lines) if 'Latitude' in ln and 'H-Ell' in ln)
    if kind == 'crlf':
        return text.replace('\n', '\r\n')
    if kind == 'bom':
        return '\ufeff' + text
    if kind in ('tabs', 'commas'):
        sep = '\t' if kind == 'tabs' else ','
        return '\n'.join(lines[:hi] + [sep.join(ln.split()) for ln in lines[hi:]]) + '\n'
    if kind == 'no header block':
        return '\n'.join(lines[hi:]) + '\n'
    if kind == 'footer':
        return text + '\n\nEnd of export\n'
    if kind == 'long header':
        block = [f'   Column/Variable Contents {k}: a processing setting' for k in range(600)]
        return '\n'.join(lines[:hi] + block + lines[hi:]) + '\n'
    return text


@pytest.mark.parametrize('kind', ['as exported', 'crlf', 'bom', 'tabs', 'commas', 'no header block', 'footer',
                                  'long header'])
def test_the_waypoint_layout_is_read_as_grafnav_whatever_its_separators_and_header(kind, tmp_path, capsys):
    """Issue #45's M300 export as GrafNav 8.x/9.x write it, with the variants a user's copy may have: it is read
    as a GrafNav export with the same epochs, never sent to the RTKLIB reader ('a solution before the column
    header'), and the issue's command places every event of the MRK."""
    from photogram_ros.cli import main
    from photogram_ros.io.trajectory_formats import read_trajectory, sniff
    base = read_trajectory(DATA / 'waypoint_m300_5hz.txt')
    path = tmp_path / 'PPK_5Hz.txt'
    path.write_bytes(_waypoint_variant(kind).encode())
    reader, scores = sniff(path)
    assert reader.name.startswith('NovAtel GrafNav') and [n for n, _ in scores] == [reader.name], scores
    track = read_trajectory(path)
    assert len(track) == len(base) and np.max(np.abs(track.ecef_m - base.ecef_m)) < 1e-6
    assert np.array_equal(track.t_gps_s, base.t_gps_s) and np.array_equal(track.q, base.q)
    out = tmp_path / 'geo.txt'
    assert main(['geotag', '--pos', str(path), '--events', str(DATA / 'm300_Timestamp.MRK'), '--out', str(out)]) == 0
    said = capsys.readouterr()
    assert 'before the column header' not in said.out + said.err
    n_events = sum(1 for ln in (DATA / 'm300_Timestamp.MRK').read_text().splitlines() if ln.strip())
    assert len(out.read_text().splitlines()) == 1 + n_events
