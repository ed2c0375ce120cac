"""PPK geotagging (`photogram-ros geotag`): RTKLIB .pos and DJI MRK readers, interpolation, lever arm,
photo <-> event matching and the errors a user can act on.

Oracles: positions are made and checked through pyproj (EPSG:4979 <-> EPSG:4978), not through the
project's geodesy; the trajectory is analytic (constant acceleration, which cubic Hermite interpolation
with centred-difference velocities reproduces exactly); the MRK convention is the one DJI states
(camera = antenna + N north, + E east, height - V).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pyproj import Transformer

from photogram_ros.core.exposure_positions import (CameraEvent, ExposureOptions, match_photos, photo_number,
                                                   place_exposures, utc_unix_to_gps_s, week_tow_to_gps_s)
from photogram_ros.errors import DataError
from photogram_ros.io.camera_events import mrk_track, read_mrk, write_mrk
from photogram_ros.io.geotag import write_geo_txt
from photogram_ros.io.photo_block import read_geo_txt
from photogram_ros.io.rtklib_pos import read_pos, write_pos

TO_ECEF = Transformer.from_crs('EPSG:4979', 'EPSG:4978', always_xy=True)
TO_LLH = Transformer.from_crs('EPSG:4978', 'EPSG:4979', always_xy=True)
LAT0, LON0, H0 = 47.3977, 8.5456, 528.0
WEEK = 2420
TOW0 = 419200.0


def _enu_axes(lat, lon):
    la, lo = math.radians(lat), math.radians(lon)
    e = np.array([-math.sin(lo), math.cos(lo), 0.0])
    n = np.array([-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)])
    u = np.array([math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)])
    return e, n, u


def _enu_to_llh(enu):
    """Local ENU about (LAT0, LON0, H0) -> lat, lon, h through pyproj."""
    x0 = np.array(TO_ECEF.transform(LON0, LAT0, H0))
    e, n, u = _enu_axes(LAT0, LON0)
    x = x0 + enu[0] * e + enu[1] * n + enu[2] * u
    lon, lat, h = TO_LLH.transform(*x)
    return lat, lon, h


def _llh_to_enu(lat, lon, h, lat0=LAT0, lon0=LON0, h0=H0):
    x0 = np.array(TO_ECEF.transform(lon0, lat0, h0))
    x = np.array(TO_ECEF.transform(lon, lat, h))
    e, n, u = _enu_axes(lat0, lon0)
    d = x - x0
    return np.array([d @ e, d @ n, d @ u])


def _path_enu(t):
    """A drone accelerating in a turn: constant acceleration (1.5, -2.0, 0.3) m/s^2."""
    return np.array([3.0 * t + 0.75 * t * t, 5.0 * t - 1.0 * t * t, 40.0 + 0.15 * t * t])


def _write_track(path, rate_hz=5.0, n=60, phase=0.0, header_system='GPST', shift_s=0.0):
    t = TOW0 + phase + np.arange(n) / rate_hz
    llh = np.array([_enu_to_llh(_path_enu(tt - TOW0)) for tt in t])
    gps = np.array([week_tow_to_gps_s(WEEK, tt) for tt in t]) + shift_s
    sd = np.tile([0.011, 0.012, 0.025], (n, 1))
    write_pos(path, gps, llh[:, 0], llh[:, 1], llh[:, 2], np.ones(n, int), sd)
    if header_system != 'GPST':
        text = path.read_text().replace('%  GPST  ', f'%  {header_system}  ')
        path.write_text(text)
    return t


def test_pos_reader_layouts_and_time_systems(tmp_path):
    body = ('% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites)\n'
            '%  {sys}                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  '
            'sdne(m)  sdeu(m)  sdun(m) age(s)  ratio\n'
            '{time}   47.397700000    8.545600000   528.0000   1  20   0.0100   0.0200   0.0300   0.0050  -0.0040'
            '   0.0030   0.00  999.9\n')
    cases = {'GPST': '2026/05/28 20:27:00.000', 'UTC': '2026/05/28 20:26:42.000'}
    t = {}
    for sys_, tm in cases.items():
        p = tmp_path / f'{sys_}.pos'
        p.write_text(body.format(sys=sys_, time=tm))
        tr = read_pos(p)
        t[sys_] = tr.t_gps_s[0]
        cov = tr.cov_enu_m2[0]
        assert cov[1, 1] == pytest.approx(1e-4) and cov[0, 0] == pytest.approx(4e-4) and cov[2, 2] == pytest.approx(9e-4)
        # sdne, sdeu, sdun are signed square roots of the covariances
        assert cov[0, 1] == pytest.approx(2.5e-5) and cov[0, 2] == pytest.approx(-1.6e-5)
        assert cov[1, 2] == pytest.approx(9e-6)
    # 20:26:42 UTC is 20:27:00 GPST (18 leap seconds)
    assert t['UTC'] == pytest.approx(t['GPST'], abs=1e-6)
    # week / seconds and the ECEF layout give the same epoch and position
    week, tow = divmod(t['GPST'], 604800)
    x, y, z = TO_ECEF.transform(8.5456, 47.3977, 528.0)
    (tmp_path / 'xyz.pos').write_text(
        '%  GPST                      x-ecef(m)      y-ecef(m)      z-ecef(m)   Q  ns   sdx(m)   sdy(m)   sdz(m)  '
        'sdxy(m)  sdyz(m)  sdzx(m) age(s)  ratio\n'
        f'{int(week)} {tow:.3f} {x:.4f} {y:.4f} {z:.4f} 1 20 0.01 0.01 0.01 0 0 0 0 999\n')
    tr2 = read_pos(tmp_path / 'xyz.pos')
    assert tr2.t_gps_s[0] == pytest.approx(t['GPST'], abs=1e-6)
    assert np.allclose(tr2.ecef_m[0], read_pos(tmp_path / 'GPST.pos').ecef_m[0], atol=1e-3)


@pytest.mark.parametrize('text, words', [
    ('% (lat/lon/height=WGS84/geodetic,Q=1:fix)\n', 'geodetic'),
    ('2026/05/28 20:27:00.000 47.3977 8.5456 528.0 1 20 0.01 0.01 0.02\n', 'header'),
    ('%  GPST  latitude(deg) longitude(deg) height(m) Q ns\n2026/05/28 20:27:00.000 47.3977 8.5456 528.0 9 20\n',
     'Q=9'),
    ('%  GPST  latitude(deg) longitude(deg) height(m) Q ns\n2026/05/28 20:27:00.000 47.3977 8.5456 528.0 5 9\n'
     '2026/05/28 20:27:00.200 47.3977 8.5456 528.0 2 9\n', 'no fixed solution'),
    ('%  GPST  e-baseline(m) n-baseline(m) u-baseline(m) Q ns\n', 'baseline'),
    ('%  GPST  latitude(deg) longitude(deg) height(m) Q ns\n2026/05/28 20:27:00.000 47.3977 eight 528.0 1 9\n',
     'cannot read'),
])
def test_pos_reader_names_the_bad_line(tmp_path, text, words):
    p = tmp_path / 'bad.pos'
    p.write_text(text)
    with pytest.raises(DataError) as e:
        read_pos(p)
    assert words in str(e.value)
    if words not in ('no fixed solution',):
        assert 'line' in str(e.value)


def test_interpolation_is_exact_under_constant_acceleration_and_refuses_to_extrapolate(tmp_path):
    _write_track(tmp_path / 't.pos')
    track = read_pos(tmp_path / 't.pos')
    rng = np.random.default_rng(3)
    rel = np.sort(rng.uniform(0.3, 11.5, 40))
    events = [CameraEvent(k + 1, week_tow_to_gps_s(WEEK, TOW0 + r), k + 1) for k, r in enumerate(rel)]
    res = place_exposures(track, events, ExposureOptions(interpolation='cubic'))
    assert res.mode == 'trajectory' and not res.problems and len(res.placed) == 40
    err = [np.linalg.norm(_llh_to_enu(pe.lat_deg, pe.lon_deg, pe.h_m) - _path_enu(r)) for pe, r in zip(res.placed, rel)]
    print(f'cubic interpolation error max {max(err) * 1000:.3f} mm')
    # .pos coordinates carry 1e-9 deg (0.1 mm); the path is a parabola, so the cubic is exact to that
    assert max(err) < 5e-4
    # linear interpolation of the same track would be off by up to a*dt^2/8 = 1.3 cm
    assert all(pe.how == 'interpolated' and pe.h_acc_m == pytest.approx(math.sqrt((0.011 ** 2 + 0.012 ** 2) / 2))
               and pe.v_acc_m == pytest.approx(0.025) for pe in res.placed)
    late = [CameraEvent(99, week_tow_to_gps_s(WEEK, TOW0 + 12.5), 7)]
    res = place_exposures(track, late)
    assert not res.placed and 'outside the track' in res.problems[0] and 'line 7' in res.problems[0]


def test_gap_is_not_bridged_and_time_base_mismatch_is_named(tmp_path):
    _write_track(tmp_path / 't.pos')
    lines = (tmp_path / 't.pos').read_text().splitlines()
    head = [ln for ln in lines if ln.startswith('%')]
    rows = [ln for ln in lines if not ln.startswith('%')]
    (tmp_path / 'gap.pos').write_text('\n'.join(head + rows[:20] + rows[26:]) + '\n')    # 1.2 s without epochs
    track = read_pos(tmp_path / 'gap.pos')
    res = place_exposures(track, [CameraEvent(5, week_tow_to_gps_s(WEEK, TOW0 + 4.5), 12)])
    assert not res.placed and 'gap of 1.40 s' in res.problems[0] and 'line 12' in res.problems[0]
    # a .pos whose header says UTC while its times are GPS time: every event 18 s off
    _write_track(tmp_path / 'utc.pos', n=300, header_system='UTC')
    track = read_pos(tmp_path / 'utc.pos')
    events = [CameraEvent(k, week_tow_to_gps_s(WEEK, TOW0 + 1 + 2 * k), k) for k in range(20)]
    res = place_exposures(track, events)
    assert len(res.placed) < 20 and 'time bases do not match' in res.problems[0]


def _mrk_line(idx, tow, n, e, v, lat, lon, h, flag=50):
    return (f'{idx}\t{tow:.6f}\t[{WEEK}]\t{n:6d},N\t{e:6d},E\t{v:6d},V\t{lat:.8f},Lat\t{lon:.8f},Lon\t{h:.3f},Ellh\t'
            f'0.012319, 0.011541, 0.025683\t{flag},Q')


def test_mrk_offsets_at_an_events_solution_within_2_mm(tmp_path):
    """A solution at the events (*_events.pos) and an MRK: camera = antenna + N, + E, height - V."""
    rng = np.random.default_rng(5)
    tows = TOW0 + np.cumsum(rng.uniform(1.8, 2.2, 15))
    ant = np.array([_enu_to_llh(_path_enu(t - TOW0) + rng.normal(0, 0.01, 3)) for t in tows])
    nev = rng.integers(-150, 150, (15, 3))
    nev[:, 2] = rng.integers(50, 250, 15)                      # the camera hangs below the antenna
    (tmp_path / 'Timestamp.MRK').write_text('\n'.join(
        _mrk_line(k + 1, tows[k], *nev[k], *ant[k]) for k in range(15)) + '\n')
    # RTKLIB writes event times to 1 ms
    write_pos(tmp_path / 'flight_events.pos', [week_tow_to_gps_s(WEEK, round(t, 3)) for t in tows],
              ant[:, 0], ant[:, 1], ant[:, 2], np.ones(15, int), np.tile([0.008, 0.009, 0.02], (15, 1)))
    rows = read_mrk(tmp_path / 'Timestamp.MRK')
    assert [r.flag for r in rows] == [50] * 15 and rows[0].sd_neu_m == pytest.approx((0.012319, 0.011541, 0.025683), abs=1e-12)
    assert rows[0].fix.quality == 1 and rows[0].fix.native_scale == 'DJI RtkFlag'
    res = place_exposures(read_pos(tmp_path / 'flight_events.pos'), [r.event for r in rows])
    assert res.mode == 'at events' and len(res.placed) == 15
    worst = 0.0
    for k, pe in enumerate(res.placed):
        d = _llh_to_enu(pe.lat_deg, pe.lon_deg, pe.h_m, *ant[k])
        want = np.array([nev[k, 1], nev[k, 0], -nev[k, 2]]) * 1e-3        # E, N, U
        worst = max(worst, float(np.max(np.abs(d - want))))
        assert pe.h_acc_m == pytest.approx(math.sqrt((0.008 ** 2 + 0.009 ** 2) / 2), abs=1e-4)
        assert pe.v_acc_m == pytest.approx(0.02, abs=1e-4)
    print(f'camera - (antenna + MRK offset): worst axis {worst * 1000:.3f} mm')
    assert worst < 0.002
    # no --pos: the MRK's own onboard RTK positions, at the events
    res2 = place_exposures(mrk_track(rows, 'Timestamp.MRK'), [r.event for r in rows])
    assert res2.mode == 'at events' and res2.placed[0].v_acc_m == pytest.approx(0.025683)
    # --lever-arm on top of MRK offsets is a mistake
    with pytest.raises(DataError, match='leave --lever-arm out'):
        place_exposures(mrk_track(rows), [r.event for r in rows], ExposureOptions(lever_arm_frd_m=(0.1, 0, 0)))


def test_body_lever_arm_turns_with_the_attitude(tmp_path):
    _write_track(tmp_path / 't.pos')
    track = read_pos(tmp_path / 't.pos')
    t = week_tow_to_gps_s(WEEK, TOW0 + 5.0)
    base = place_exposures(track, [CameraEvent(1, t, 1)]).placed[0]
    opt = ExposureOptions(lever_arm_frd_m=(0.30, 0.0, -0.20))     # antenna 30 cm ahead of and 20 cm above the camera
    east = place_exposures(track, [CameraEvent(1, t, 1, rpy_deg=(0.0, 0.0, 90.0))], opt).placed[0]
    d = _llh_to_enu(east.lat_deg, east.lon_deg, east.h_m, base.lat_deg, base.lon_deg, base.h_m)
    assert np.allclose(d, [-0.30, 0.0, -0.20], atol=2e-4)      # heading east: the camera is 30 cm west, 20 cm below
    tilted = place_exposures(track, [CameraEvent(1, t, 1, rpy_deg=(0.0, 10.0, 0.0))], opt).placed[0]
    d = _llh_to_enu(tilted.lat_deg, tilted.lon_deg, tilted.h_m, base.lat_deg, base.lon_deg, base.h_m)
    p = math.radians(10.0)   # nose up 10 deg: FRD forward = (cos p) north + (sin p) up, down = (sin p) north - (cos p) up
    ant_ned = 0.30 * np.array([math.cos(p), 0, -math.sin(p)]) - 0.20 * np.array([math.sin(p), 0, math.cos(p)])
    assert np.allclose(d, [-ant_ned[1], -ant_ned[0], ant_ned[2]], atol=2e-4)


def test_photo_matching_names_every_mismatch():
    events = [CameraEvent(k + 1, 1000.0 + 2.0 * k, k + 1) for k in range(6)]
    photos = [(f'DJI_{k + 1:04d}.JPG', 1000.0 + 2.0 * k - 18.0) for k in range(6)]
    m = match_photos(photos, events)
    assert m.how == 'by number' and not m.problems and m.clock_offset_s == pytest.approx(18.0)
    assert [photo_number(n) for n in ('DJI_0042.JPG', 'DJI_20240501101010_0042_V.JPG', 'IMG_0042.jpg', 'a.jpg')] == [
        42, 42, 42, None]
    # the camera skipped the 3rd event, the photos are numbered on their own: by time finds which
    photos = [(f'IMG_{k:03d}.JPG', 1000.0 + 2.0 * k + 0.3) for k in (0, 1, 3, 4, 5)]
    m = match_photos(photos, events, 'time', 1.0)
    assert dict(m.pairs) == {'IMG_000.JPG': 0, 'IMG_001.JPG': 1, 'IMG_003.JPG': 3, 'IMG_004.JPG': 4, 'IMG_005.JPG': 5}
    assert m.problems == ['event 3 ( line 3) has no photo']
    # by order the same gap shows as photos off the others' clock offset
    m = match_photos(photos, events, 'order', 1.0)
    off = [p for p in m.problems if 'paired by order' in p and 'a photo or an event is missing' in p]
    assert len(off) == 2 and 'IMG_000.JPG' in off[0] and 'IMG_001.JPG' in off[1]


def test_mrk_with_fewer_rows_than_photos_is_an_error(tmp_path):
    from PIL import Image

    from photogram_ros.io.geotag import GeotagInput, geotag
    _write_track(tmp_path / 't.pos')
    for k in range(1, 5):
        Image.new('RGB', (32, 24)).save(tmp_path / f'DJI_{k:04d}.JPG')
    (tmp_path / 'Timestamp.MRK').write_text('\n'.join(
        _mrk_line(k, TOW0 + 2 * k, 10, 5, 150, LAT0, LON0, H0) for k in (1, 2, 3)) + '\n')
    with pytest.raises(DataError) as e:
        geotag(GeotagInput(str(tmp_path / 't.pos'), str(tmp_path / 'Timestamp.MRK'), str(tmp_path),
                           str(tmp_path / 'geo.txt')))
    assert 'DJI_0004.JPG' in str(e.value) and 'no event numbered 4' in str(e.value)
    res = geotag(GeotagInput(str(tmp_path / 't.pos'), str(tmp_path / 'Timestamp.MRK'), str(tmp_path),
                             str(tmp_path / 'geo.txt'), skip_unplaced=True))
    assert [n for n, _ in res.rows] == ['DJI_0001.JPG', 'DJI_0002.JPG', 'DJI_0003.JPG']


def test_geo_txt_reads_back_as_written(tmp_path):
    _write_track(tmp_path / 't.pos')
    track = read_pos(tmp_path / 't.pos')
    res = place_exposures(track, [CameraEvent(k, week_tow_to_gps_s(WEEK, TOW0 + 1 + k), k) for k in range(5)])
    rows = [(f'P{k}.JPG', pe) for k, pe in enumerate(res.placed)]
    write_geo_txt(tmp_path / 'geo.txt', rows, {})
    back = read_geo_txt(tmp_path / 'geo.txt')
    for name, pe in rows:
        lat, lon, h, ha, va = back[name]
        assert (lat, lon) == pytest.approx((pe.lat_deg, pe.lon_deg), abs=1e-10)
        assert h == pytest.approx(pe.h_m, abs=1e-4) and ha == pytest.approx(pe.h_acc_m, abs=1e-4)
        assert va == pytest.approx(pe.v_acc_m, abs=1e-4)


def test_mrk_written_by_the_simulator_reads_back(tmp_path):
    t = [week_tow_to_gps_s(WEEK, TOW0 + 2 * k + 0.123456) for k in range(3)]
    write_mrk(tmp_path / 'x.MRK', t, np.array([[0.012, -0.004, 0.167]] * 3), [LAT0] * 3, [LON0] * 3, [H0] * 3,
              [(0.01, 0.01, 0.02)] * 3, flag=34, seqs=[7, 8, 9])
    rows = read_mrk(tmp_path / 'x.MRK')
    assert [r.event.seq for r in rows] == [7, 8, 9] and rows[1].event.t_gps_s == pytest.approx(t[1], abs=1e-6)
    assert np.allclose(rows[0].event.offset_ned_m, [0.012, -0.004, 0.167]) and rows[2].flag == 34
    assert utc_unix_to_gps_s(1483228800.0) - utc_unix_to_gps_s(1483228799.0) == 2.0     # the leap second of 2017


def test_dataflash_cam_messages_read_back(tmp_path):
    from photogram_ros.io.camera_events import read_dataflash_events, read_events
    from photogram_ros.sim.dataflash import write_cam_log
    cams = [{'boot_us': 95_000_000 + k * 2_000_000, 'img': k + 1, 'gps_week': WEEK, 'gps_ms': 419218000 + 2000 * k + 7,
             'lat_deg': LAT0 + 1e-5 * k, 'lon_deg': LON0, 'alt_msl_m': 480.25, 'rel_alt_m': 40.0,
             'roll_deg': 1.5, 'pitch_deg': -4.25, 'yaw_deg': -90.0} for k in range(3)]
    write_cam_log(tmp_path / 'f.bin', cams)
    evs = read_dataflash_events(tmp_path / 'f.bin')
    assert [e.seq for e in evs] == [1, 2, 3] and [e.unit for e in evs] == ['message'] * 3
    assert evs[2].t_gps_s == pytest.approx(week_tow_to_gps_s(WEEK, 419222.007), abs=1e-6)
    assert evs[0].rpy_deg == pytest.approx((1.5, -4.25, 270.0))
    assert evs[1].logged_llh == pytest.approx((LAT0 + 1e-5, LON0, 480.25))
    assert [e.seq for e in read_events(tmp_path / 'f.bin')] == [1, 2, 3]
    with pytest.raises(DataError, match='holds no TRIG'):
        read_dataflash_events(tmp_path / 'f.bin', 'TRIG')


def _command(module, argv):
    import argparse
    p = argparse.ArgumentParser()
    module.add_arguments(p)
    return module.run(p.parse_args(argv))


def test_fixes_events_lists_exposures_and_names_logs_without_any(tmp_path, capsys):
    from conftest import shared_data

    from photogram_ros.cli import main
    from photogram_ros.sim.dataflash import write_cam_log
    real = shared_data('mavlink', 'flightdata_center_0003.bin')
    if real is not None:
        assert main(['fixes', str(real), '--events']) == 2     # a real ArduPilot log: no CAM/TRIG in it
        assert 'holds no CAM or TRIG message' in capsys.readouterr().err
    write_cam_log(tmp_path / 'f.bin', [{'boot_us': 1, 'img': 4, 'gps_week': WEEK, 'gps_ms': 419218500, 'lat_deg': LAT0,
                                        'lon_deg': LON0, 'alt_msl_m': 480.0, 'rel_alt_m': 40.0, 'roll_deg': 0.0,
                                        'pitch_deg': 0.0, 'yaw_deg': 0.0}])
    assert main(['fixes', str(tmp_path / 'f.bin'), '--events']) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith('seq,source,gps_week,gps_seconds') and out[1].startswith(f'4,{tmp_path / "f.bin"} CAM,'
                                                                                     f'{WEEK},419218.5,')


def test_geotag_command_on_a_mrk_without_pos(tmp_path, capsys):
    from photogram_ros.commands import geotag as cmd
    (tmp_path / 'Timestamp.MRK').write_text('\n'.join(
        _mrk_line(k, TOW0 + 2 * k, 10, 5, 150, LAT0 + 1e-5 * k, LON0, H0, flag=(50, 50, 34)[k - 1])
        for k in (1, 2, 3)) + '\n')
    assert _command(cmd, ['--events', str(tmp_path / 'Timestamp.MRK'), '--out', str(tmp_path / 'geo.txt')]) == 0
    out = capsys.readouterr()
    assert 'geotagged 3 photos (2 fix, 1 float' in out.out and "MRK's own onboard RTK" in out.err
    geo = read_geo_txt(tmp_path / 'geo.txt')
    assert sorted(geo) == ['event_0001', 'event_0002', 'event_0003']
    assert geo['event_0003'][3] == pytest.approx(0.10) and geo['event_0001'][3] == pytest.approx(
        math.sqrt((0.012319 ** 2 + 0.011541 ** 2) / 2), abs=1e-4)     # float: at least its class's floor
    h_cam = geo['event_0001'][2]
    assert h_cam == pytest.approx(H0 - 0.150, abs=2e-4)
    assert (tmp_path / 'geo.csv').read_text().splitlines()[0].startswith('image,latitude,longitude,altitude')
