"""The DSM covers what the photos saw: cells stereo did not measure, inside the camera centres' hull, are
interpolated (core/raster.fill_surface) and band 2 of dsm.tif says which cells were measured (the stereo
pairs that measured them) and which interpolated (0), so nothing filled passes for measured."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from helpers.clouds import fused_map, pair_cloud

LAT, LON, H = 47.3977, 8.5456, 488.0


def plane(x, y):
    return 3.0 + 0.05 * x - 0.02 * y


def test_push_pull_reproduces_a_plane_inside_holes_and_keeps_measured_cells():
    from photogram_ros.core.raster import push_pull_fill
    Y, X = np.mgrid[0:200, 0:240].astype(float)
    z = plane(X, Y)
    valid = np.ones(z.shape, bool)
    cv2.circle(valid.view(np.uint8), (120, 100), 30, 0, -1)      # a pond 60 cells across
    valid[20:30, 10:200] = False                                  # a textureless track
    out = push_pull_fill(np.where(valid, z, -9999.0), valid)
    assert np.array_equal(out[valid], z[valid])
    err = np.abs(out - z)[~valid]
    # A plane's slope is 0.05 per cell: push-pull blends the rim, so it bends in the middle of a hole.
    assert np.median(err) < 0.3 and err.max() < 1.0


def test_fill_surface_keeps_steps_fills_only_the_region_and_leaves_the_rest():
    from photogram_ros.core.raster import NODATA, fill_surface
    d = np.full((60, 60), 10.0, np.float32)
    d[:, 30:] = 16.0                      # a roof 6 m above the ground, wall at column 30
    d[:, 29:31] = NODATA                  # the wall's two cells: no-data
    d[40:50, 5:15] = NODATA               # a hole in the ground
    region = np.zeros(d.shape, bool)
    region[:, :55] = True
    d[:, 56:] = NODATA                    # outside the region
    out = fill_surface(d, region)
    assert out[0, 29] == 10.0 and out[0, 30] == 16.0          # the nearest side: a step, not a ramp
    assert np.allclose(out[40:50, 5:15], 10.0)
    assert (out[:, 56:] == NODATA).all()


@pytest.fixture(scope='module')
def holed_map(tmp_path_factory):
    """A map of a plane with a 12 m disk no pair measured (water, a crown), keyframes over all of it."""
    d = tmp_path_factory.mktemp('fill') / 'map'
    rng = np.random.default_rng(3)

    def clouds():
        for k in range(4):
            for _ in range(2):              # two pairs over each strip: every cell confirmed (min_pairs 2)
                c = pair_cloud(rng, plane, -12.0 + 8 * k, 0.0, 10.0, 20.0, 60.0, 0.01)
                yield c[np.hypot(c['x'] - 0.0, c['y'] - 2.0) > 6.0]

    store = fused_map(d, 0.2, clouds(), (LAT, LON, H))
    jpg = cv2.imencode('.jpg', np.zeros((8, 8, 3), np.uint8))[1].tobytes()
    for k, (x, y) in enumerate([(-16, -16), (16, -16), (16, 16), (-16, 16), (0, 0)]):
        T = np.eye(4)
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])     # looking down
        T[:3, 3] = (x, y, 40.0)
        store.save_keyframe_image(k, jpg)
        store.save_keyframe_pose(k, T)
    return d


def test_dsm_is_filled_inside_the_camera_hull_and_band_2_says_what_was_measured(holed_map, tmp_path):
    import rasterio
    from photogram_ros.io.export import DsmParams, crs_to_enu, export_map
    from photogram_ros.core.geodesy import LocalFrame
    res = export_map(holed_map, tmp_path / 'filled', 'EPSG:32632', products=('dsm',), min_pairs=2)
    raw = export_map(holed_map, tmp_path / 'raw', 'EPSG:32632', products=('dsm',), min_pairs=2,
                     dsm=DsmParams(fill=False))
    hull, raw_hull = res.dsm['camera_hull'], raw.dsm['camera_hull']
    assert hull['valid'] >= 0.98 and raw_hull['valid'] < 0.9
    assert hull['measured'] == pytest.approx(raw_hull['measured'], abs=1e-9)   # filling measures nothing
    assert hull['valid'] == pytest.approx(hull['measured'] + hull['filled'])
    with rasterio.open(res.files['dsm']) as ds:
        assert ds.count == 2 and ds.descriptions == ('height_m', 'pairs')
        z, pairs = ds.read(1), ds.read(2)
        rows, cols = np.nonzero(z != ds.nodata)
        xs, ys = rasterio.transform.xy(ds.transform, rows, cols)
    enu = crs_to_enu(LocalFrame(LAT, LON, H), np.asarray(xs), np.asarray(ys), z[rows, cols], 'EPSG:32632')
    in_disk = np.hypot(enu[:, 0], enu[:, 1] - 2.0) < 5.0
    p = pairs[rows, cols]
    assert in_disk.sum() > 400 and (p[in_disk] == 0).all()          # the disk: interpolated, and said so
    # The rest of what the pairs covered (x within 22 m, y within 20 m): measured by 2+ pairs; the raster reaches
    # on to the cameras' footprint (a quarter of the 40 m flying height beyond the camera centres), interpolated.
    covered = (np.abs(enu[:, 0]) < 21.5) & (np.abs(enu[:, 1]) < 19.5)
    assert (p[~in_disk & covered] >= 2).mean() > 0.9
    beyond = (np.abs(enu[:, 0]) > 22.5) | (np.abs(enu[:, 1]) > 20.5)
    assert (p[beyond] == 0).all() and np.abs(enu[beyond, 0]).max() > 25.0
    err = np.abs(enu[:, 2] - plane(enu[:, 0], enu[:, 1]))
    print(f'filled disk |dz| median {np.median(err[in_disk]):.3f} m, max {err[in_disk].max():.3f} m')
    assert np.median(err[in_disk]) < 0.033 and err[in_disk].max() < 0.08     # measured 0.022 / 0.052 m


def _strips_map(folder, one_pair_offset_m: float):
    """A plane in four strips: two pairs over the outer ones, one pair over the inner two (60 % forward overlap
    leaves one pair per spot), that one pair's heights `one_pair_offset_m` off the plane."""
    rng = np.random.default_rng(5)

    def clouds():
        for k in range(4):
            inner = k in (1, 2)
            for _ in range(1 if inner else 2):
                shift = one_pair_offset_m if inner else 0.0
                yield pair_cloud(rng, lambda x, y: plane(x, y) + shift, -12.0 + 8 * k, 0.0, 4.0, 20.0, 60.0, 0.01)

    store = fused_map(folder, 0.2, clouds(), (LAT, LON, H))
    _nadir_keyframes(store, [(-16, -20), (16, -20), (16, 20), (-16, 20)])
    return folder


def _nadir_keyframes(store, corners_m) -> None:
    """Keyframes looking straight down from 40 m at each (east, north) of `corners_m` (black images)."""
    jpg = cv2.imencode('.jpg', np.zeros((8, 8, 3), np.uint8))[1].tobytes()
    for k, (x, y) in enumerate(corners_m):
        T = np.eye(4)
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])
        T[:3, 3] = (x, y, 40.0)
        store.save_keyframe_image(k, jpg)
        store.save_keyframe_pose(k, T)


def _dsm_cells(path):
    """(east, north ENU, m; height, m; band 2) of the cells of dsm.tif holding a height."""
    import rasterio

    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.io.export import crs_to_enu
    with rasterio.open(path) as ds:
        z, pairs = ds.read(1), ds.read(2)
        rows, cols = np.nonzero(z != ds.nodata)
        xs, ys = rasterio.transform.xy(ds.transform, rows, cols)
    enu = crs_to_enu(LocalFrame(LAT, LON, H), np.asarray(xs), np.asarray(ys), z[rows, cols], 'EPSG:32632')
    return enu[:, 0], enu[:, 1], enu[:, 2], pairs[rows, cols]


@pytest.mark.parametrize('offset_m', [0.0, 1.5])
def test_one_pair_cells_far_from_confirmed_ones_hold_the_dsm_and_the_near_ones_check_it(tmp_path, offset_m):
    """With min_pairs 2 a cell one pair measured holds the DSM's height (band 2: 1) where no confirmed cell is
    within DsmParams.one_pair_beyond_m (4.24 m at 0.2 m cells: the middle 7.5 m of the 16 m one-pair band); nearer,
    the confirmed cells win (interpolated from them, band 2: 0) and the one-pair heights only check the
    interpolation (export.json's dsm.one_pair_check): a plane agrees, a band one pair put 1.5 m off is named."""
    from photogram_ros.io.export import export_map
    res = export_map(_strips_map(tmp_path / 'map', offset_m), tmp_path / 'out', 'EPSG:32632', products=('dsm',),
                     min_pairs=2)
    assert res.dsm['one_pair_beyond_m'] == pytest.approx(res.dsm['fill_gaps_m'])
    x, y, z, pairs = _dsm_cells(res.files['dsm'])
    inner = (np.abs(y) < 19.0)
    far = inner & (np.abs(x) < 3.5)
    near = inner & (np.abs(x) > 4.5) & (np.abs(x) < 7.5)
    confirmed = inner & (np.abs(x) > 8.5) & (np.abs(x) < 15.5)
    assert far.sum() > 500 and (pairs[far] == 1).mean() > 0.95            # one pair, said so
    assert np.median(np.abs(z[far] - plane(x[far], y[far]) - offset_m)) < 0.05
    assert (pairs[near] == 0).all()                                        # interpolated: confirmed cells near
    assert (pairs[confirmed] >= 2).mean() > 0.95
    hull, foot, check = res.dsm['camera_hull'], res.dsm['footprint'], res.dsm['one_pair_check']
    assert 0.1 < hull['measured_one_pair'] < 0.3 and 0.1 < hull['filled_one_pair'] <= hull['filled']
    assert foot['cells'] > hull['cells'] and foot['measured_one_pair'] < hull['measured_one_pair']
    assert check['cells'] > 500
    if offset_m == 0.0:
        assert check['median_abs_dz_m'] < 0.1     # 0.012 m
    else:     # the interpolation runs from the confirmed plane to the one-pair band 1.5 m above it
        assert 0.3 < check['median_abs_dz_m'] < offset_m
    one = export_map(tmp_path / 'map', tmp_path / 'all', 'EPSG:32632', products=('dsm',), min_pairs=1)
    assert 'one_pair_check' not in one.dsm and 'filled_one_pair' not in one.dsm['camera_hull']


def _one_pair_map(folder, blob_m: float = 0.0):
    """A plane that only one pair per spot measured (60 % forward overlap), over 40 x 40 m, keyframes at 40 m
    over it; `blob_m`: a 2 m disk at (5, 5) m that pair put that far above the plane (a mismatch)."""
    rng = np.random.default_rng(7)

    def height(x, y):
        return plane(x, y) + np.where(np.hypot(x - 5.0, y - 5.0) < 1.0, blob_m, 0.0)

    def clouds():
        for k in range(4):
            yield pair_cloud(rng, height, -15.0 + 10 * k, 0.0, 5.0, 20.0, 60.0, 0.01)

    store = fused_map(folder, 0.2, clouds(), (LAT, LON, H))
    _nadir_keyframes(store, [(-16, -16), (16, -16), (16, 16), (-16, 16)])
    return folder


def test_a_survey_one_pair_measured_everywhere_is_mapped_over_its_footprint_by_that_pair(tmp_path):
    """No cell confirmed by two pairs: the DSM, its cloud and DTM still come from the one pair (band 2: 1) over
    what the cameras saw, where before the export failed ('no cell of the map was measured by 2 pairs')."""
    from photogram_ros.io.export import export_map
    res = export_map(_one_pair_map(tmp_path / 'map'), tmp_path / 'out', 'EPSG:32632',
                     products=('las', 'dsm', 'dtm'), min_pairs=2)
    x, y, z, pairs = _dsm_cells(res.files['dsm'])
    covered = (np.abs(x) < 19.5) & (np.abs(y) < 19.5)
    assert (pairs[covered] == 1).mean() > 0.95
    assert np.median(np.abs(z[covered] - plane(x[covered], y[covered]))) < 0.02
    hull = res.dsm['camera_hull']
    assert hull['measured_one_pair'] > 0.95 and hull['measured'] == hull['measured_one_pair']
    assert res.dsm['footprint']['measured'] > 0.5          # the rest: the margin beyond the pairs' 40 m square
    assert res.points > 0.9 * 40 * 40 / 0.2 ** 2           # the cloud holds the one-pair cells
    assert res.dtm['valid_share'] > 0.5
    # one_pair_beyond_m at ONE_PAIR_NEVER_M: only confirmed cells, of which there are none.
    from photogram_ros.errors import DataError
    from photogram_ros.io.export import DsmParams
    from photogram_ros.io.export_raster import ONE_PAIR_NEVER_M
    with pytest.raises(DataError, match='measured by 2 stereo pairs'):
        export_map(tmp_path / 'map', tmp_path / 'never', 'EPSG:32632', products=('dsm',), min_pairs=2,
                   dsm=DsmParams(one_pair_beyond_m=ONE_PAIR_NEVER_M))


def test_one_pair_cells_that_disagree_with_their_neighbours_or_stand_alone_are_dropped():
    """agrees_with_neighbours: a cell within the spread limit of the median of the one-pair cells around it (5x5)
    is kept; a 2x2 blob 3 m up (a mismatch), a lone cell and a cell with 5 neighbours are not; a 60 degree
    slope's cells agree with their neighbours' median (the plane through them)."""
    from photogram_ros.io.export_raster import agrees_with_neighbours
    Y, X = np.mgrid[0:40, 0:40].astype(float)
    d = (0.02 * X + 0.7 * (X > 25) * (X - 25)).astype(np.float32)     # flat, then 0.7 m per 0.4 m cell
    valid = np.ones(d.shape, bool)
    valid[:, 36:] = False
    d[10:12, 10:12] += 3.0                     # the blob
    valid[30:40, 0:10] = False
    valid[35, 5] = True                        # alone
    valid[37:40, 0:2] = True                   # a 3x2 sliver: each cell has 5 neighbours
    ok = agrees_with_neighbours(d, valid, valid, 0.707)
    assert not ok[10:12, 10:12].any() and not ok[35, 5] and not ok[37:40, 0:2].any()
    assert ok[20:28, 0:34].all()               # the plane and the slope, up to the covered edge
    # The slope's cells on the covered edge have their neighbours on one side only, a cell's 0.7 m below and more:
    # dropped (93 % kept)
    assert ok[valid].mean() > 0.9
