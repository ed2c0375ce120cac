"""`triangulate --heights` means what `run`/`replay`/`export --heights` mean (issue 47): one option definition
(commands/common_args.add_heights) and the heights of what triangulate writes (poses.csv's z, sparse.ply,
sparse.las and the report) written once in the datum asked (TriangulateOptions.heights)."""

from __future__ import annotations

import csv
import json

import numpy as np

from photogram_ros.cli import main
from test_cli_heights import _option_help
from test_triangulate_command import exif_survey  # noqa: F401  (the fixture: a small EXIF-only photo survey)


def test_triangulate_shows_the_heights_option_of_run_replay_and_export(capsys):
    assert _option_help(capsys, 'triangulate') == _option_help(capsys, 'replay') == _option_help(capsys, 'export')


def _outputs(out):
    import laspy
    rows = list(csv.DictReader(open(out / 'poses.csv')))
    las = laspy.read(str(out / 'sparse.las'))
    ply = (out / 'sparse.ply').read_bytes()[:400].decode('ascii', 'replace')
    return rows, las, ply, json.loads((out / 'report.json').read_text()), (out / 'report.md').read_text()


def test_triangulate_writes_orthometric_heights_one_geoid_undulation_below_the_ellipsoidal_ones(exif_survey,  # noqa: F811
                                                                                                 tmp_path):
    from photogram_ros.core import geoid
    flight, _, _ = exif_survey
    for heights in ('ellipsoidal', 'orthometric'):
        assert main(['triangulate', str(flight / 'msl'), '--out', str(tmp_path / heights), '--heights', heights,
                     '--quiet']) == 0
    e_rows, e_las, e_ply, e_rep, e_md = _outputs(tmp_path / 'ellipsoidal')
    o_rows, o_las, o_ply, o_rep, o_md = _outputs(tmp_path / 'orthometric')
    assert [r['image'] for r in e_rows] == [r['image'] for r in o_rows] and len(e_rows) >= 5
    lat = np.array([float(r['lat_deg']) for r in o_rows])
    lon = np.array([float(r['lon_deg']) for r in o_rows])
    n_m = geoid.undulation_m(lat, lon)
    assert 45.0 < float(np.median(n_m)) < 51.0          # EGM2008 near Zurich (the simulator's site): about 48 m
    dz = np.array([float(e['z']) - float(o['z']) for e, o in zip(e_rows, o_rows)])
    # The same block adjusted twice: the same poses to a millimetre, the heights one undulation apart.
    assert np.max(np.abs(dz - n_m)) < 0.002, (dz, n_m)
    assert all(e['h_m'] == o['h_m'] and e['z'] == e['h_m'] for e, o in zip(e_rows, o_rows))   # h_m: ellipsoidal
    epsg = o_rows[0]['crs'].split(':')[1].split('+')[0]
    assert o_rows[0]['crs'] == f'EPSG:{epsg}+3855' and e_rows[0]['crs'] == f'EPSG:{epsg}'
    # The sparse cloud: the same points, heights one undulation below; LAS CRS compound with EGM2008 height.
    assert len(e_las.x) == len(o_las.x) > 100
    assert np.allclose(e_las.x, o_las.x, atol=0.002) and np.allclose(e_las.y, o_las.y, atol=0.002)
    dz_cloud = np.asarray(e_las.z) - np.asarray(o_las.z)
    assert abs(np.median(dz_cloud) - np.median(n_m)) < 0.05 and np.ptp(dz_cloud) < 0.1
    crs = o_las.header.parse_crs()
    assert crs.is_compound and crs.sub_crs_list[1].to_epsg() == 3855 and crs.sub_crs_list[0].to_epsg() == int(epsg)
    assert e_las.header.parse_crs().to_epsg() == int(epsg)
    assert 'comment heights orthometric' in o_ply and 'comment heights ellipsoidal' in e_ply
    assert (o_rep['heights'], e_rep['heights']) == ('orthometric', 'ellipsoidal')
    assert o_rep['crs_with_heights'] == f'EPSG:{epsg}+3855'
    assert 'orthometric, above the EGM2008 geoid' in o_md and 'WGS84 ellipsoidal' in e_md


def test_options_refuse_an_unknown_datum():
    import pytest

    from photogram_ros.errors import ConfigError
    from photogram_ros.io.aerial_triangulation import TriangulateOptions
    assert TriangulateOptions(heights='orthometric').heights == 'orthometric'
    with pytest.raises(ConfigError, match='--heights'):
        TriangulateOptions(heights='msl')


def test_poses_and_cloud_are_written_once_in_the_datum_asked(tmp_path):
    """write_poses_and_cloud (what adjust_block and split-merge write through) in each datum: poses.csv's z and
    the cloud one undulation apart, h_m ellipsoidal in both; an empty cloud is written too."""
    import laspy

    from photogram_ros.core import geoid
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.io.aerial_triangulation import heights_keys, write_poses_and_cloud
    origin = LocalFrame(47.3977, 8.5456, 450.0)
    Ts = []
    for k in range(4):
        T = np.diag([1.0, -1.0, -1.0, 1.0])
        T[:3, 3] = (20.0 * k, 5.0 * k, 80.0)
        Ts.append(T)
    P = np.array([[5.0, 2.0, 0.5], [30.0, 10.0, -1.0], [50.0, 12.0, 2.0]])
    for heights in ('ellipsoidal', 'orthometric'):
        write_poses_and_cloud(tmp_path / heights, [f'IMG_{k}.JPG' for k in range(4)], Ts, P, origin, 'EPSG:32632',
                              [], heights)
        write_poses_and_cloud(tmp_path / f'{heights}_empty', ['IMG_0.JPG'], Ts[:1], np.zeros((0, 3)), origin,
                              'EPSG:32632', [], heights)
        assert len(laspy.read(str(tmp_path / f'{heights}_empty' / 'sparse.las')).x) == 0
    e_rows = list(csv.DictReader(open(tmp_path / 'ellipsoidal' / 'poses.csv')))
    o_rows = list(csv.DictReader(open(tmp_path / 'orthometric' / 'poses.csv')))
    n_m = geoid.undulation_m([float(r['lat_deg']) for r in o_rows], [float(r['lon_deg']) for r in o_rows])
    dz = np.array([float(e['z']) - float(o['z']) for e, o in zip(e_rows, o_rows)])
    assert np.allclose(dz, n_m, atol=2e-4) and 45.0 < float(np.median(n_m)) < 51.0
    assert all(e['h_m'] == o['h_m'] == e['z'] for e, o in zip(e_rows, o_rows))
    assert {r['crs'] for r in o_rows} == {'EPSG:32632+3855'} and {r['crs'] for r in e_rows} == {'EPSG:32632'}
    e_las, o_las = (laspy.read(str(tmp_path / h / 'sparse.las')) for h in ('ellipsoidal', 'orthometric'))
    assert np.allclose(np.asarray(e_las.z) - np.asarray(o_las.z), np.median(n_m), atol=0.05)
    assert o_las.header.parse_crs().is_compound and e_las.header.parse_crs().to_epsg() == 32632
    assert heights_keys('EPSG:32632', 'orthometric') == {'heights': 'orthometric', 'crs_with_heights': 'EPSG:32632+3855'}
