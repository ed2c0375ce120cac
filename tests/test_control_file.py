"""Control-point files for flights (io/control_file.py) and ControlSet lookups (core/control.py)."""

import numpy as np
import pytest

from photogram_ros.core import geoid
from photogram_ros.core.control import TARGET_DTYPE, ControlSet, SurveyedTarget
from photogram_ros.core.geodesy import LocalFrame, geodetic_to_crs
from photogram_ros.errors import DataError
from photogram_ros.io.control_file import read_control_file, write_control_file

LAT, LON, H = 47.3977, 8.5456, 488.0


def _utm(lat, lon):
    x, y, _ = geodetic_to_crs(lat, lon, 0.0, 'EPSG:32632')
    return float(x), float(y)


def _write(tmp_path, text, name='targets.txt'):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_reads_utm_with_commas_comments_sigmas_and_check_names(tmp_path):
    x, y = _utm(LAT, LON)
    p = _write(tmp_path, f"""# site survey, RTK rover on each board
EPSG:32632
# name marker_id x y z [sigma_h_m sigma_v_m]
GCP01 0 {x:.4f} {y:.4f} 490.25
GCP02,3,{x + 30:.4f},{y + 40:.4f},491.50,0.01,0.015   # corner board
CHK01	7	{x + 10:.4f}	{y + 10:.4f}	489.00
P4 9 {x - 20:.4f} {y:.4f} 488.00
""")
    c = read_control_file(p, check_names=['P4'])
    assert c.crs == 'EPSG:32632' and len(c) == 4
    assert c.gcp_names == ['GCP01', 'GCP02'] and c.check_names == ['CHK01', 'P4']
    g1, g2 = c.targets[0], c.targets[1]
    assert abs(g1.lat_deg - LAT) < 1e-8 and abs(g1.lon_deg - LON) < 1e-8 and g1.h_m == pytest.approx(490.25)
    assert g1.sigma_h_m is None and (g2.sigma_h_m, g2.sigma_v_m) == (0.01, 0.015) and g2.marker_id == 3
    # In a map frame: 30 m east, 40 m north of GCP01 (UTM scale and convergence: a few cm over 50 m).
    origin = LocalFrame(LAT, LON, H)
    cps = c.in_map(origin)
    d = cps[1].map_xyz - cps[0].map_xyz
    assert np.linalg.norm(d[:2]) == pytest.approx(50.0, abs=0.05) and d[2] == pytest.approx(1.25, abs=1e-3)
    assert np.allclose(cps[0].map_xyz, [0, 0, 2.25], atol=1e-4)   # 0.1 mm: the file has 4 decimals
    assert np.allclose(cps[0].sigma_m, [0.02, 0.02, 0.03]) and np.allclose(cps[1].sigma_m, [0.01, 0.01, 0.015])
    assert [p.role for p in cps] == ['gcp', 'gcp', 'check', 'check']
    # A sigma override applies to every point.
    assert np.allclose(c.in_map(origin, 0.05, 0.08)[1].sigma_m, [0.05, 0.05, 0.08])


def test_geographic_proj_string_and_odm_utm_header(tmp_path):
    x, y = _utm(LAT, LON)
    a = read_control_file(_write(tmp_path, f'WGS84\nGCP01 0 {LON} {LAT} 500\n', 'a.txt'))
    b = read_control_file(_write(tmp_path, f'+proj=utm +zone=32 +datum=WGS84 +units=m +no_defs\n'
                                           f'GCP01 0 {x} {y} 500\n', 'b.txt'))
    c = read_control_file(_write(tmp_path, f'WGS84 UTM 32N\nGCP01 0 {x} {y} 500\n', 'c.txt'))
    for t in (a, b, c):
        g = t.targets[0]
        assert abs(g.lat_deg - LAT) < 1e-8 and abs(g.lon_deg - LON) < 1e-8 and g.h_m == pytest.approx(500.0)
    assert c.crs == 'EPSG:32632'
    # Latitude first is caught when it cannot be a latitude.
    with pytest.raises(DataError, match='longitude first'):
        read_control_file(_write(tmp_path, 'EPSG:4326\nGCP01 0 -33.9 151.2 20\n', 'd.txt'))


def test_orthometric_heights_through_egm2008(tmp_path):
    x, y = _utm(LAT, LON)
    n = geoid.undulation_m(LAT, LON)
    assert 45 < n < 50   # Zurich: the 20-50 m classic error of mixing the two up
    comp = read_control_file(_write(tmp_path, f'EPSG:32632+3855\nGCP01 0 {x} {y} 440.0\n', 'a.txt'))
    assert comp.targets[0].h_m == pytest.approx(440.0 + n, abs=0.01)
    said = read_control_file(_write(tmp_path, f'EPSG:32632\nGCP01 0 {x} {y} 440.0\n', 'b.txt'), heights='orthometric')
    assert said.targets[0].h_m == pytest.approx(440.0 + n, abs=0.01)
    kept = read_control_file(tmp_path / 'a.txt', heights='ellipsoidal')
    assert kept.targets[0].h_m == pytest.approx(440.0)
    with pytest.raises(DataError, match="LN02 height.*only the EGM2008 geoid"):
        read_control_file(_write(tmp_path, 'EPSG:2056+5728\nGCP01 0 2683000 1248000 440.0\n', 'c.txt'))


@pytest.mark.parametrize('text,match', [
    ('', 'is empty: the first line must be a CRS'),
    ('# only a comment\n', 'is empty'),
    ('EPSG:99999999\nGCP01 0 1 2 3\n', 'line 1: .*not a coordinate reference system'),
    ('EPSG:32632\n', 'lists no targets'),
    ('EPSG:32632\nGCP01 0 465000 5249000\n', r'line 2: expected .*\(5 or 7 values\), got 4'),
    ('EPSG:32632\nGCP01 0 465000 5249000 500 0.02\n', 'line 2: expected .*got 6'),
    ('EPSG:32632\n\n# x\nGCP01 A 465000 5249000 500\n', "line 4: marker id 'A' of 'GCP01' is not a whole number"),
    ('EPSG:32632\nGCP01 -1 465000 5249000 500\n', 'line 2: marker id -1 .* negative'),
    ('EPSG:32632\nGCP01 1 465000 north 500\n', "line 2: y 'north' is not a number"),
    ('EPSG:32632\nGCP01 1 465000 5249000 nan\n', "line 2: z is 'nan'"),
    ('EPSG:32632\nGCP01 1 465000 5249000 500 0.02 0\n', 'line 2: sigmas of .* must be positive'),
    ('EPSG:32632\nGCP01 1 465000 5249000 500\nGCP01 2 465010 5249000 500\n', "name 'GCP01' appears twice"),
    ('EPSG:32632\nGCP01 1 465000 5249000 500\nGCP02 1 465010 5249000 500\n', "marker id 1 is given to 'GCP01' and 'GCP02'"),
    ('EPSG:32632\nGCP01 1 5249000 465000 500\n', 'line 2: .*outside EPSG:32632'),
])
def test_bad_files_name_the_line_and_the_fix(tmp_path, text, match):
    with pytest.raises(DataError, match=match):
        read_control_file(_write(tmp_path, text))


def test_unknown_check_name_and_missing_file(tmp_path):
    p = _write(tmp_path, 'EPSG:32632\nGCP01 1 465000 5249000 500\n')
    with pytest.raises(DataError, match=r"check points \['GCP1'\] are not in .*targets are \['GCP01'\]"):
        read_control_file(p, check_names=['GCP1'])
    with pytest.raises(DataError, match='cannot read the control-point file'):
        read_control_file(tmp_path / 'nope.txt')


def test_write_then_read_gives_the_targets_back(tmp_path):
    ts = [SurveyedTarget('GCP01', 0, LAT, LON, 490.123, 'gcp'),
          SurveyedTarget('CHK01', 4, LAT + 2e-4, LON - 3e-4, 489.5, 'check', 0.01, 0.02)]
    for crs in ('EPSG:32632', 'EPSG:4326'):
        back = read_control_file(write_control_file(tmp_path / f'{crs[5:]}.txt', ts, crs))
        for a, b in zip(ts, back.targets):
            assert (a.name, a.marker_id, a.role, a.sigma_h_m, a.sigma_v_m) == \
                   (b.name, b.marker_id, b.role, b.sigma_h_m, b.sigma_v_m)
            assert abs(a.lat_deg - b.lat_deg) < 1e-8 and abs(a.lon_deg - b.lon_deg) < 1e-8
            assert abs(a.h_m - b.h_m) < 1e-4


def test_detections_become_target_uv_by_marker_id():
    c = ControlSet([SurveyedTarget('GCP01', 0, LAT, LON, H, 'gcp'), SurveyedTarget('CHK01', 5, LAT, LON, H, 'check')])
    det = np.zeros(4, TARGET_DTYPE)
    det['marker_id'] = [5, 0, 17, 17]
    det['u'], det['v'] = [10.5, 20.0, 30.0, 40.0], [1.0, 2.0, 3.0, 4.0]
    uv, unknown = c.target_uv(det)
    assert set(uv) == {'GCP01', 'CHK01'} and np.allclose(uv['CHK01'], [10.5, 1.0]) and unknown == 2
    det['marker_id'] = [0, 0, 5, 17]   # one marker twice in an image: ambiguous, neither is used
    uv, unknown = c.target_uv(det)
    assert set(uv) == {'CHK01'} and unknown == 3


def test_sample_bag_ships_its_targets_file(sample_bag):
    from photogram_ros.sim.truth import GroundTruth
    truth = GroundTruth.load(sample_bag)
    c = read_control_file(sample_bag / 'targets.txt')
    assert c.gcp_names == [t.name for t in truth.targets if t.role == 'gcp']
    assert c.check_names == [t.name for t in truth.targets if t.role == 'check']
    for t, p in zip(truth.targets, c.in_map(truth.origin)):
        assert np.abs(p.map_xyz - t.center_enu).max() < 2e-4 and c.by_marker[t.marker_id].name == t.name


def test_simulate_writes_the_targets_file_beside_the_bag(tiny_flight):
    from photogram_ros.sim.truth import GroundTruth
    truth = GroundTruth.load(tiny_flight)
    c = read_control_file(tiny_flight / 'targets.txt')
    assert c.crs == truth.crs and [t.name for t in c.targets] == [t.name for t in truth.targets]
    for t, p in zip(truth.targets, c.in_map(truth.origin)):
        assert p.role == t.role and np.abs(p.map_xyz - t.center_enu).max() < 2e-4
