"""`photogram-ros fixes` on every kind of input, and dataflash logs."""

from __future__ import annotations

import csv
import io
import json
import math
from contextlib import redirect_stdout

import numpy as np
import pytest

from conftest import shared_data
from photogram_ros.cli import main
from photogram_ros.core import gnss_fix as gf
from photogram_ros.io.dataflash import gps_to_unix_s, read_dataflash_fixes
from test_mavlink_parse import sample_dir  # noqa: F401  (fixture)

BIN = ('mavlink', 'flightdata_center_0003.bin')


def _run(*args) -> str:
    buf = io.StringIO()
    with redirect_stdout(buf):
        assert main(['fixes', *map(str, args)]) == 0
    return buf.getvalue()


def test_dataflash_gps_gpa():
    from pymavlink import DFReader
    path = shared_data(*BIN)
    fixes, counts = read_dataflash_fixes(path)
    assert counts['GPS'] == 209 and counts['GPA'] == 209 and len(fixes) == 209
    log = DFReader.DFReader_binary(str(path))
    ref = []
    while (m := log.recv_match(type=['GPS', 'GPA'])) is not None:
        ref.append(m)
    gps = [m for m in ref if m.get_type() == 'GPS']
    gpa = [m for m in ref if m.get_type() == 'GPA']
    for f, g, a in zip(fixes, gps, gpa):
        assert f.lat_deg == pytest.approx(g.Lat, abs=1e-9) and f.lon_deg == pytest.approx(g.Lng, abs=1e-9)
        assert f.cov_type == gf.COV_DIAGONAL_KNOWN and f.var_enu_m2[0] == pytest.approx(a.HAcc ** 2, rel=1e-3)
        # The receiver's own ellipsoidal height: GPA.Und is the ellipsoid's height above MSL.
        assert f.h_m == pytest.approx(g.Alt - a.Und, abs=0.002) and f.height_source == 'alt_ellipsoid'
        if g.GWk > 0:
            assert f.t_s == pytest.approx(gps_to_unix_s(g.GWk, g.GMS), abs=1e-6)
    # The receiver's geoid and EGM2008 agree to a couple of metres (a sign error would be ~100 m).
    n = gf.undulation_m(fixes[0].lat_deg, fixes[0].lon_deg)
    assert abs(-gpa[0].Und - n) < 3.0
    t = np.array([f.t_s for f in fixes])
    assert np.all(np.diff(t) > 0) and 40 < t[-1] - t[0] < 50
    assert gps_to_unix_s(2347, 481578000) == pytest.approx(1735911960.0)   # pymavlink's own timestamp


def test_fixes_csv_from_tlog_matches_truth(sample_dir):  # noqa: F811
    from photogram_ros.sim.truth import GroundTruth
    gt = GroundTruth.load(sample_dir)
    rows = list(csv.DictReader(io.StringIO(_run(sample_dir / 'flight.tlog'))))
    assert len(rows) == len(gt.fixes)
    for r, tr in zip(rows, gt.fixes):
        assert abs(float(r['t_unix_s']) - tr['t_fix_unix_s']) < 0.001
        assert abs(float(r['lat_deg']) - tr['lat_deg']) < 1e-7 and abs(float(r['h_m']) - tr['h_m']) < 0.002
        assert r['fix_name'] == 'RTK_FIXED' and r['status'] == '2' and r['cov_type'] == '2'


def test_fixes_same_from_bag_and_tlog(sample_dir):  # noqa: F811
    a = [json.loads(line) for line in _run(sample_dir / 'flight.tlog', '--format', 'jsonl').splitlines()]
    b = [json.loads(line) for line in _run(sample_dir, '--format', 'jsonl').splitlines()]
    assert len(a) == len(b) > 300
    assert all(x['t_unix_s'] == pytest.approx(y['t_unix_s'], abs=1e-6) and x['lat_deg'] == y['lat_deg']
               for x, y in zip(a, b))


def test_fixes_geojson_and_no_fix_rows():
    path = shared_data('mavlink', 'phoenix_mission1_2018-09-17_16-44-06.tlog')
    doc = json.loads(_run(path, '--format', 'geojson', '--with-no-fix'))
    feats = doc['features']
    assert len(feats) == 786
    assert sum(f['geometry'] is None for f in feats) == 5
    lon, lat, h = feats[-1]['geometry']['coordinates']
    assert 49 < lat < 50 and -124 < lon < -123 and math.isfinite(h)
    assert feats[-1]['properties']['height_source'] == 'msl+EGM2008'
    rows = list(csv.DictReader(io.StringIO(_run(shared_data(*BIN)))))
    assert len(rows) == 209 and rows[0]['source'] == 'dataflash GPS[0]'


def test_fixes_bad_input_is_an_error(tmp_path, capsys):
    assert main(['fixes', str(tmp_path / 'missing.tlog')]) == 2
    junk = tmp_path / 'junk.tlog'
    junk.write_bytes(np.random.default_rng(0).integers(0, 256, 20000, dtype=np.uint8).tobytes())
    assert main(['fixes', str(junk)]) == 2
    assert 'holds no MAVLink' in capsys.readouterr().err
