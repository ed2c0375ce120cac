"""Live ortho tiles (core/ortho_tiles.py), mission files (io/mission.py) and the go / no-go (core/survey_quality.py).

The ortho tiles are checked against the Web Mercator formulas written out here (an oracle independent
of morecantile): a red square fused at a known place must land on the pixels the formulas give.
"""

import json
import math

import numpy as np
import pytest

from photogram_ros.core.fusion import Fusion, FusionConfig, pack_rgb
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.core.ortho_tiles import TILE_PX, OrthoTiler
from photogram_ros.core.survey_quality import (BLOCK_ADJUSTED, BLOCK_IN_FLIGHT, GEOREF_FINAL, GEOREF_PROVISIONAL,
                                               GEOREF_UNKNOWN, GO, NO_GO, PROVISIONAL, WAIT, QualityLimits, fix_class, go_no_go, rmse,
                                               rmse_lower_bound)
from photogram_ros.errors import DataError
from photogram_ros.io.mission import read_survey_area, refly_plan, survey_area_in_map

ORIGIN = LocalFrame(47.3977, 8.5456, 488.0)


def mercator_pixel(lat_deg, lon_deg, z):
    """Global pixel (x from the antimeridian, y from the north) of the XYZ scheme at zoom z."""
    n = TILE_PX * 2 ** z
    x = (lon_deg + 180.0) / 360.0 * n
    y = (1 - math.log(math.tan(math.radians(lat_deg)) + 1 / math.cos(math.radians(lat_deg))) / math.pi) / 2 * n
    return x, y


def fused_field(cell_m=0.1, square=((10.0, 20.0), 3.0)):
    """A grey 60 x 60 m field with a red square (centre, side) fused at cell_m."""
    fus = Fusion(FusionConfig(cell_m=cell_m, tile_cells=128))
    xs = np.arange(-30, 30, cell_m / 2) + cell_m / 4
    X, Y = np.meshgrid(xs, xs)
    (cx, cy), side = square
    red = (np.abs(X - cx) < side / 2) & (np.abs(Y - cy) < side / 2)
    pts = np.zeros(X.size, [('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('rgb', 'u4'), ('confidence', 'f4')])
    pts['x'], pts['y'], pts['z'], pts['confidence'] = X.ravel(), Y.ravel(), 0.0, 1.0
    pts['rgb'] = np.where(red.ravel(), pack_rgb(255, 0, 0), pack_rgb(120, 120, 120))
    fus.add(pts)
    return fus


def test_ortho_tile_puts_the_fused_colours_where_web_mercator_says():
    tiler = OrthoTiler(ORIGIN, 0.1, 128, gsd_m=0.2)
    assert tiler.zoom == 19 and 0.2 <= tiler.pixel_m < 0.4   # 0.2986 m Web Mercator * cos(47.4 deg)
    nw, ne, sw = tiler.tile_corners_enu(tiler.tile_of_enu(10.0, 20.0))
    centre = nw + 0.4 * (ne - nw) + 0.6 * (sw - nw)    # well inside that tile
    fus = fused_field(square=(tuple(centre), 3.0))
    lat, lon, _ = ORIGIN.enu_to_geodetic(np.array([*centre, 0.0]))
    gx, gy = mercator_pixel(float(lat), float(lon), tiler.zoom)
    t = tiler.tile_of_enu(*centre)
    assert (t.x, t.y) == (int(gx // TILE_PX), int(gy // TILE_PX))
    img = tiler.render(t, fus.tile_records)
    red = (img[..., 2] > 200) & (img[..., 1] < 50) & (img[..., 3] == 255)
    rows, cols = np.nonzero(red)
    # The square's centre within a pixel of the formula's; its side 3 m = 3 / pixel_m pixels.
    assert np.mean(cols) + 0.5 == pytest.approx(gx - t.x * TILE_PX, abs=1.0)
    assert np.mean(rows) + 0.5 == pytest.approx(gy - t.y * TILE_PX, abs=1.0)
    assert red.sum() == pytest.approx((3.0 / tiler.pixel_m) ** 2, rel=0.15)
    # Grey field elsewhere; transparent beyond it.
    grey = (np.abs(img[..., :3].astype(int) - 120).max(axis=-1) < 3) & (img[..., 3] == 255)
    assert grey.sum() > 10 * red.sum()
    far = tiler.tile_of_enu(500.0, 500.0)
    assert not tiler.render(far, fus.tile_records)[..., 3].any()


def test_changed_fusion_tile_names_the_xyz_tiles_over_it():
    tiler = OrthoTiler(ORIGIN, 0.1, 128, gsd_m=0.2)
    tiles = tiler.tiles_of_map_tile((0, 1))     # x 0..12.8 m, y 12.8..25.6 m
    assert tiler.tile_of_enu(10.0, 20.0) in tiles
    for x, y in ((0.1, 12.9), (12.7, 25.5)):
        assert tiler.tile_of_enu(x, y) in tiles
    assert len(tiles) <= 4   # a 12.8 m fusion tile in 51 m XYZ tiles


def test_survey_area_from_a_qgc_plan_and_geojson(tmp_path):
    ring = [[47.3970, 8.5450], [47.3970, 8.5470], [47.3985, 8.5470], [47.3985, 8.5450]]
    plan = {'fileType': 'Plan', 'version': 1, 'mission': {'items': [
        {'type': 'SimpleItem', 'command': 22, 'params': [0, 0, 0, None, 47.39, 8.54, 40]},
        {'type': 'ComplexItem', 'complexItemType': 'survey', 'polygon': ring}]},
        'geoFence': {'polygons': []}}
    (tmp_path / 'm.plan').write_text(json.dumps(plan))
    gj = {'type': 'FeatureCollection', 'features': [{'type': 'Feature', 'properties': {}, 'geometry': {
        'type': 'Polygon', 'coordinates': [[[lon, lat] for lat, lon in ring + ring[:1]]]}}]}
    (tmp_path / 'a.geojson').write_text(json.dumps(gj))
    a = read_survey_area(tmp_path / 'm.plan')
    b = read_survey_area(tmp_path / 'a.geojson')
    assert a[0] == [tuple(p) for p in ring]
    assert b[0][:4] == [tuple(p) for p in ring]
    xy = survey_area_in_map(a, ORIGIN)[0]
    # 0.002 deg of longitude at 47.4 deg: 151 m; 0.0015 deg of latitude: 167 m.
    assert np.ptp(xy[:, 0]) == pytest.approx(151.0, abs=1.0) and np.ptp(xy[:, 1]) == pytest.approx(167.0, abs=1.0)
    (tmp_path / 'bad.geojson').write_text('{"type": "Point", "coordinates": [8.5, 47.3]}')
    with pytest.raises(DataError, match='no polygon'):
        read_survey_area(tmp_path / 'bad.geojson')


def test_refly_plan_flies_over_the_gap():
    gap = [(47.39800, 8.54620), (47.39800, 8.54650), (47.39817, 8.54650), (47.39817, 8.54620)]  # 23 x 19 m
    plan = refly_plan([gap], 40.0, 50.0, 37.0, (47.3977, 8.5456))
    items = plan['mission']['items']
    assert plan['fileType'] == 'Plan' and plan['mission']['version'] == 2
    assert items[0]['command'] == 22 and items[-1]['command'] == 20
    wps = [it for it in items if it['command'] == 16]
    assert len(wps) >= 2 and all(it['params'][6] == 40.0 for it in wps)
    # The line passes over the gap's centre and reaches half a footprint beyond its ends.
    lat = np.array([it['params'][4] for it in wps])
    lon = np.array([it['params'][5] for it in wps])
    c = LocalFrame(47.398085, 8.54635, 0.0)
    enu = c.geodetic_to_enu(lat, lon, np.zeros(len(lat)))
    assert np.ptp(enu[:, 0]) + np.ptp(enu[:, 1]) > 23 + 37 - 2
    trig = [it for it in items if it['command'] == 206]
    assert trig[0]['params'][0] == pytest.approx(37.0 * 0.2) and trig[-1]['params'][0] == 0
    assert [it['doJumpId'] for it in items] == list(range(1, len(items) + 1))


def test_fix_classes_and_rmse():
    cov = lambda s: np.diag([s * s, s * s, 4 * s * s])  # noqa: E731
    assert fix_class(GnssFix(0, 0, 0, cov(0.02), status=2)) == 'rtk_fixed'
    assert fix_class(GnssFix(0, 0, 0, cov(0.3), status=2)) == 'rtk_float'
    assert fix_class(GnssFix(0, 0, 0, cov(2.0), status=0)) == '3d'
    assert fix_class(GnssFix(0, 0, 0, cov(0.7), status=1)) == 'dgps'
    assert fix_class(None) == 'none'
    r = rmse([[0.03, 0.04, 0.01], [0.0, 0.0, -0.01]])
    assert r == pytest.approx({'horizontal_m': math.sqrt(0.05 ** 2 / 2), 'vertical_m': 0.01, 'count': 2})
    assert rmse([])['count'] == 0 and math.isnan(rmse([])['horizontal_m'])


def test_go_no_go_waits_for_check_points_then_judges():
    lim = QualityLimits(max_check_rmse_h_m=0.05, min_coverage=0.98, max_gap_m2=25.0)
    wait = go_no_go({'coverage_share': 0.99, 'largest_gap_m2': 0.0}, lim)
    assert wait['verdict'] == WAIT and 'not measured yet' in wait['reasons'][0]
    ok = go_no_go({'check_rmse': {'horizontal_m': 0.03, 'vertical_m': 0.02, 'count': 4}, 'coverage_share': 0.99,
                   'largest_gap_m2': 3.0}, lim)
    assert ok['verdict'] == GO and not ok['reasons']
    bad = go_no_go({'check_rmse': {'horizontal_m': 0.03, 'vertical_m': 0.02, 'count': 4}, 'coverage_share': 0.93,
                    'largest_gap_m2': 448.0}, lim)
    assert bad['verdict'] == NO_GO and len(bad['reasons']) == 2 and '448' in bad['reasons'][1]


def test_go_no_go_judges_only_figures_of_a_block_georeferenced_for_good():
    """The sample flight's live figures (recorded at --rate 1 with its targets): 6.08 m over 2 check points
    while the block was provisional, 5.2-6.6 cm over 2-4 once georeferenced for good, 3.5 cm after the final
    adjustment. None of them is NO-GO; the last is GO. A survey clearly beyond its limit is NO-GO."""
    lim = QualityLimits(max_check_rmse_h_m=0.05, min_coverage=0.98, max_gap_m2=25.0)

    def verdict(h, n, georef, **kw):
        return go_no_go({'check_rmse': {'horizontal_m': h, 'vertical_m': 0.02, 'count': n}, 'georeference': georef,
                         'coverage_share': 1.0, 'gaps': [], **kw}, lim)

    prov = verdict(6.0788, 2, GEOREF_PROVISIONAL)
    assert prov['verdict'] == WAIT and 'provisional' in prov['reasons'][0]
    assert prov['checks'][0]['status'] == PROVISIONAL and prov['checks'][0]['value'] == 6.0788
    assert verdict(6.0788, 2, GEOREF_UNKNOWN)['verdict'] == WAIT
    for h, n in ((0.0638, 2), (0.0658, 3), (0.0563, 3), (0.0517, 4), (0.0537, 4)):
        w = verdict(h, n, GEOREF_FINAL)
        assert w['verdict'] == WAIT and 'cannot tell' in w['reasons'][0], (h, n, w)
    assert verdict(0.0353, 4, GEOREF_FINAL)['verdict'] == GO
    # Clearly beyond: 2.7 m (3D GNSS, no GCPs) over 2 points, 8 cm over 9.
    assert verdict(2.74, 2, GEOREF_FINAL)['verdict'] == NO_GO
    assert verdict(0.08, 9, GEOREF_FINAL)['verdict'] == NO_GO
    # The bound is the chi-square one: 5.37 cm over 4 points (8 degrees of freedom) at 95 % -> 3.86 cm.
    assert rmse_lower_bound(0.0537, 4, 2, 0.95) == pytest.approx(0.0537 * math.sqrt(8 / 15.5073), rel=1e-4)
    strict = QualityLimits(max_check_rmse_h_m=0.05, nogo_confidence=0.0)
    assert go_no_go({'check_rmse': {'horizontal_m': 0.0537, 'vertical_m': 0.0, 'count': 4}, 'coverage_share': 1.0,
                     'gaps': []}, strict)['verdict'] == NO_GO


def test_a_check_point_figure_of_the_in_flight_block_says_so_when_it_is_not_go():
    """The sample flight's one NO-GO poll (7.28 cm over 3 check points, before the final adjustment, which ended
    at 1.42 cm): NO-GO stays NO-GO, and its reason says it comes from the in-flight block; the same figure of
    the adjusted block, or a GO, says nothing more."""
    lim = QualityLimits(max_check_rmse_h_m=0.05, min_coverage=0.98, max_gap_m2=25.0)

    def verdict(h, n, block):
        return go_no_go({'check_rmse': {'horizontal_m': h, 'vertical_m': 0.02, 'count': n}, 'block': block,
                         'georeference': GEOREF_FINAL, 'coverage_share': 1.0, 'gaps': []}, lim)

    flight = verdict(0.0728, 3, BLOCK_IN_FLIGHT)
    assert flight['verdict'] == NO_GO and 'in-flight block, before its final adjustment' in flight['reasons'][0]
    final = verdict(0.0728, 3, BLOCK_ADJUSTED)
    assert final['verdict'] == NO_GO and 'in-flight' not in final['reasons'][0]
    wait = verdict(0.0563, 3, BLOCK_IN_FLIGHT)
    assert wait['verdict'] == WAIT and 'cannot tell' in wait['reasons'][0] and 'in-flight' in wait['reasons'][0]
    good = verdict(0.0142, 4, BLOCK_IN_FLIGHT)
    assert good['verdict'] == GO and good == verdict(0.0142, 4, BLOCK_ADJUSTED)


def test_every_gap_kind_counts():
    """A forward-overlap gap of 1,219 m² that the neighbouring lines see (the camera stopped 10 s) is not GO,
    with its kind and area in the reason; below the limit it passes."""
    lim = QualityLimits(max_check_rmse_h_m=0.05, min_coverage=0.98, max_gap_m2=25.0)
    fig = {'check_rmse': {'horizontal_m': 0.03, 'vertical_m': 0.02, 'count': 4}, 'coverage_share': 1.0,
           'georeference': GEOREF_FINAL}
    r = go_no_go({**fig, 'gaps': [{'kind': 'coverage', 'area_m2': 6.0},
                                  {'kind': 'forward_overlap', 'area_m2': 1219.0, 'min_views': 4}]}, lim)
    assert r['verdict'] == NO_GO and r['reasons'] == [
        'largest gap, any kind (m²): 1219 (<= 25), forward_overlap gap, seen by 4 keyframes of other lines']
    assert go_no_go({**fig, 'gaps': [{'kind': 'not_oriented', 'area_m2': 24.0}]}, lim)['verdict'] == GO
    assert go_no_go({**fig, 'gaps': []}, lim)['checks'][-1]['value'] == 0.0


def test_a_block_the_adjuster_calls_failed_is_no_go_after_its_final_adjustment():
    """Check points GO, coverage full, and a folded block (core/block_check.py FAILED: a strip tilted 31 deg):
    WAIT while in flight (the final adjustment may mend it), NO-GO once the block is adjusted after its last
    keyframe; a block check's warning is a warning; an OK check changes nothing."""
    lim = QualityLimits(max_check_rmse_h_m=0.05, min_coverage=0.98, max_gap_m2=25.0)
    folded = {'status': 'failed', 'summary': 'FAILED (decided by strips): a strip is tilted 31 deg'}

    def verdict(check, block):
        return go_no_go({'check_rmse': {'horizontal_m': 0.03, 'vertical_m': 0.02, 'count': 4}, 'coverage_share': 1.0,
                         'gaps': [], 'georeference': GEOREF_FINAL, 'block': block, 'block_check': check}, lim)

    assert verdict({'status': 'ok', 'summary': 'OK'}, BLOCK_ADJUSTED)['verdict'] == GO
    in_flight = verdict(folded, BLOCK_IN_FLIGHT)
    assert in_flight['verdict'] == WAIT and 'tilted 31 deg' in in_flight['reasons'][-1]
    assert 'before its final adjustment' in in_flight['reasons'][-1]
    final = verdict(folded, BLOCK_ADJUSTED)
    assert final['verdict'] == NO_GO and "the adjuster's check of the block: failed: FAILED" in final['reasons'][-1]
    warned = verdict({'status': 'warning', 'summary': 'WARNING (decided by dome): bent'}, BLOCK_ADJUSTED)
    assert warned['verdict'] == GO and any('bent' in w for w in warned['warnings'])
