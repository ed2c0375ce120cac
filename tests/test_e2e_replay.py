"""End to end: the sample flight replayed through the whole graph, compared with the simulator's truth.

This is the README's main job (photogram-ros replay bags/sample_flight): 78 s, three lines, RTK, no GCPs.
Every figure of docs/measurements.md for it is gated at 1.5x its measured value (MEASURED below, in GSD
unless named); the replay is deterministic to a few micrometres run to run. The dense products are
matched again from the final adjustment (map_final); the DSM is filled inside the camera centres' hull,
its measured and interpolated cells reported apart.
"""

import json
import subprocess
import sys

import laspy
import pytest
import pyproj
import rasterio

from conftest import ROOT
from photogram_ros.sim.truth import GroundTruth

pytestmark = pytest.mark.ros

MEASURED = {
    'check_h': 0.55, 'check_v': 0.33, 'cameras_m': 0.030,
    'dsm_measured_median': 0.64, 'dsm_measured_p90': 1.41, 'dsm_measured_rmse': 1.13, 'dsm_all_median': 0.66,
    'dsm_filled_median': 1.01, 'dtm_rmse': 0.99, 'cloud_median': 0.66, 'cloud_p90': 1.48,
}


def gate(name):
    return 1.5 * MEASURED[name]


@pytest.fixture(scope='module')
def replay(sample_bag, tmp_path_factory):
    out = tmp_path_factory.mktemp('replay') / 'sample'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(sample_bag), '--out', str(out),
                        '--quiet', '--truth', str(sample_bag)], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return out, json.loads((out / 'report.json').read_text()), GroundTruth.load(sample_bag), r.stdout


def test_products_exist_with_crs_and_bounds(replay):
    out, rep, truth, stdout = replay
    for name in ('cloud.las', 'cloud.laz', 'cloud.ply', 'dsm.tif', 'dtm.tif', 'ortho.tif', 'report.html', 'report.md',
                 'trajectory.csv', 'trajectory.geojson'):
        assert (out / name).stat().st_size > 0, name
    las = laspy.read(out / 'cloud.laz')
    las_crs = las.header.parse_crs()
    assert las_crs.to_epsg() == 32632   # a 2D CRS by its EPSG code (ellipsoidal heights)
    with rasterio.open(out / 'dsm.tif') as ds:
        assert pyproj.CRS.from_wkt(ds.crs.to_wkt()).to_2d().to_epsg() == 32632
        b = ds.bounds
    # The sample flies around 47.3977 N, 8.5456 E: UTM 32N easting ~ 465 km, northing ~ 5249 km.
    assert 464_000 < b.left < b.right < 466_500 and 5_248_000 < b.bottom < b.top < 5_250_500
    # Every keyframe taken is oriented. How many the overlap rule takes is not gated exactly: the same code
    # took 53 on earlier machines and takes 52 on this one. Probably a frame near the 0.8 threshold (frame 49
    # measures 0.7992 here, 1.3 cells of the overlap grid below it); whether the CPU or an indirect dependency
    # moved it was not found.
    assert rep['keyframes'] == rep['keyframes_oriented'] and 50 <= rep['keyframes'] <= 56
    assert 'check points' in stdout


def test_check_points_and_cameras_against_truth(replay):
    _, rep, truth, _ = replay
    cp = rep['check_points']['rmse']
    # GCP02, at a corner of the block, is seen in 2 images of one line: intersected too weakly to count (vertical
    # DOP 11.6), it is listed apart.
    assert cp['count'] == 8
    weak = rep['check_points']['weak']
    assert [w['name'] for w in weak] == ['GCP02'] and weak[0]['views'] == 2 and weak[0]['dop_v'] > 5.0
    assert cp['horizontal_m'] <= gate('check_h') * truth.gsd_m
    assert cp['z_m'] <= gate('check_v') * truth.gsd_m
    tr = rep['trajectory_vs_truth']
    assert tr['count'] == rep['keyframes'] and tr['rmse_m'] <= gate('cameras_m')


def test_dense_products_against_true_dem(replay):
    """The DSM's measured cells (band 2 >= 1), its interpolated cells (walls, plain roofs) apart, the
    DTM against the true ground away from buildings and the cloud against the true DEM."""
    _, rep, truth, _ = replay
    dsm = rep['dsm_vs_truth_measured']
    assert dsm['median_abs_gsd'] <= gate('dsm_measured_median') and dsm['p90_abs_gsd'] <= gate('dsm_measured_p90')
    assert dsm['rmse_gsd'] <= gate('dsm_measured_rmse')
    assert rep['dsm_vs_truth']['median_abs_gsd'] <= gate('dsm_all_median')   # the interpolated cells too
    assert rep['dsm_vs_truth_filled']['median_abs_gsd'] <= gate('dsm_filled_median')
    assert rep['dtm_vs_truth_away_from_buildings']['rmse_gsd'] <= gate('dtm_rmse')
    cloud = rep['cloud_vs_truth']
    assert cloud['median_abs_gsd'] <= gate('cloud_median') and cloud['p90_abs_gsd'] <= gate('cloud_p90')
    assert rep['dsm_completeness'] >= 0.98                              # measured 99.5 %
    assert rep['dsm_measured_completeness'] >= 0.90                     # measured 92.9 %
    assert rep['cloud_completeness'] >= 0.90                            # measured 93.4 %
    camera_hull = rep['run']['dsm']['camera_hull']
    assert camera_hull['valid'] >= 0.98 and rep['run']['ortho']['camera_hull']['valid'] >= 0.98


def test_report_lists_nodes_and_run(replay):
    out, rep, _, _ = replay
    assert {'/tracker_node', '/bundle_node', '/stereo_node', '/map_node'} <= set(rep['nodes'])
    assert rep['run']['frames'] == 76 and rep['run']['real_time_factor'] > 0
    html = (out / 'report.html').read_text()
    assert 'Check points' in html and 'data:image/png;base64' in html
    # Overlap map and check-point arrows; the sample's three lines see most cells from 5+ photos (measured
    # median 11, 99.7 % in 5 or more).
    assert (out / 'overlap.png').exists() and (out / 'check_points.png').exists()
    assert rep['overlap']['median_photos'] >= 7 and rep['overlap']['share_5_or_more'] >= 0.66
    assert 'measured by stereo' in (out / 'report.md').read_text() and rep['camera']['fx_px'] > 0
    rows = (out / 'trajectory.csv').read_text().splitlines()
    assert rows[0].startswith('image,stamp_ns,easting_m') and len(rows) == rep['keyframes'] + 1


def test_report_with_a_control_file_lists_gcps_apart(replay, sample_bag, tmp_path):
    """The same map reported with the bag's targets file: only CHK* are check points, the GCPs have their
    own table; the replay without --gcp searched no keyframe for targets (the tracker searches only near
    the surveyed points of a control file): the report finds them in the stored keyframes."""
    from photogram_ros.io.control_file import read_control_file
    from photogram_ros.io.flight_report import build_report
    out, rep, truth, _ = replay
    assert rep['check_points']['rmse']['count'] + len(rep['check_points']['weak']) == len(truth.targets)
    assert 'gcp_residuals' not in rep
    bundle = rep['nodes']['/bundle_node']['values']
    assert bundle.get('target_detections', 0) == 0
    fig = build_report(tmp_path, out / 'map', 'EPSG:32632', {}, control=read_control_file(sample_bag / 'targets.txt'))
    assert sorted(p['name'] for p in fig['check_points']['points']) == ['CHK01', 'CHK02', 'CHK03', 'CHK04']
    assert sorted(p['name'] for p in fig['gcp_residuals']['points']) == ['GCP01', 'GCP03', 'GCP04', 'GCP05']
    assert [w['name'] for w in fig['gcp_residuals']['weak']] == ['GCP02']
    assert fig['gcp_residuals']['rmse']['horizontal_m'] <= 1.5 * truth.gsd_m
    assert 'GCP residuals' in (tmp_path / 'report.md').read_text()
    assert fig['check_points']['ce90_le90']['n'] == 4 and 'CE90' in (tmp_path / 'report.md').read_text()
    # What the bundle node made of the GCPs in flight (core/control_live.py) is in the GCP section: a GCP
    # used horizontally only has no height residual, one left out is not in the RMSE, the faults are listed.
    said = 'GCP GCP01: its surveyed height is 90.00 m below ...; a placeholder?; used horizontally only'
    diag = {'/bundle_node': {'values': {'gcps_used': '4', 'gcps_horizontal_only_names': 'GCP01',
                                        'gcps_rejected_names': 'GCP04'},
                             'problems': [[3.0, f'control: {said}'], [4.0, 'bad keyframe fix: x']]}}
    (tmp_path / 'vetted').mkdir()
    fig = build_report(tmp_path / 'vetted', out / 'map', 'EPSG:32632', {},
                       control=read_control_file(sample_bag / 'targets.txt'), diagnostics=diag)
    g = fig['gcp_residuals']
    use = {p['name']: (p['use'], p['dz_m']) for p in g['points']}
    assert use['GCP01'] == ('horizontal only', None) and use['GCP04'] == ('not used', None)
    assert use['GCP03'][0] == 'full' and use['GCP03'][1] is not None
    # GCP02 is intersected too weakly to count (above), GCP04 was not used, GCP01 has no height.
    assert g['rmse']['count'] == 3 and g['rmse']['count_vertical'] == 2 and g['faults'] == [said]
    assert said in (tmp_path / 'vetted' / 'report.md').read_text()


def test_products_come_from_the_final_adjustment_and_are_reproducible(replay, tmp_path):
    """The products are matched again from the final poses (map_final): the same folder densified again
    gives the same cells, and the in-flight map (pairs matched with the poses they had when they left
    the bundle window) is no better against the truth."""
    from photogram_ros.commands.products import densify_with_params
    from photogram_ros.io.export import export_map
    from photogram_ros.io.flight_report import build_report
    from photogram_ros.io.map_store import MapStore
    out, rep, truth, _ = replay
    assert rep['run']['products_from'].startswith('final adjustment') and rep['run']['densify_pairs'] > 50
    again = densify_with_params(out / 'map', tmp_path / 'again', str(ROOT / 'config/replay.yaml'), progress=False)
    a, b = MapStore(out / 'map_final'), MapStore(again.map_dir)
    assert a.tile_keys() == b.tile_keys() and a.tile_keys()
    for key in a.tile_keys():
        assert (a.load_tile(key) == b.load_tile(key)).all()
    live = tmp_path / 'live'
    ex = export_map(out / 'map', live, 'EPSG:32632', 'ellipsoidal', products=('las', 'dsm'), min_pairs=2)
    fig = build_report(live, out / 'map', 'EPSG:32632', {k: str(v) for k, v in ex.files.items()}, truth=truth)
    print(f"DSM median |dz|: in-flight map {fig['dsm_vs_truth']['median_abs_gsd']:.2f} GSD, "
          f"final {rep['dsm_vs_truth']['median_abs_gsd']:.2f} GSD")
    assert rep['dsm_vs_truth']['median_abs_gsd'] <= fig['dsm_vs_truth']['median_abs_gsd'] + 0.02
