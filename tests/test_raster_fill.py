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
    assert (p[~in_disk] >= 2).mean() > 0.9                           # the rest: measured by 2+ pairs
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
    jpg = cv2.imencode('.jpg', np.zeros((8, 8, 3), np.uint8))[1].tobytes()
    for k, (x, y) in enumerate([(-16, -20), (16, -20), (16, 20), (-16, 20)]):
        T = np.eye(4)
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])
        T[:3, 3] = (x, y, 40.0)
        store.save_keyframe_image(k, jpg)
        store.save_keyframe_pose(k, T)
    return folder


@pytest.mark.parametrize('offset_m', [0.0, 1.5])
def test_one_pair_cells_check_the_interpolated_dsm_and_say_how_far_they_differ(tmp_path, offset_m):
    """With min_pairs 2 the cells one pair measured are not in the DSM's heights (interpolated there) but
    export.json's dsm.one_pair_check compares them with the interpolation: a plane agrees, a strip one pair put
    1.5 m off the interpolation between its confirmed neighbours is named by that difference."""
    from photogram_ros.io.export import export_map
    res = export_map(_strips_map(tmp_path / 'map', offset_m), tmp_path / 'out', 'EPSG:32632', products=('dsm',),
                     min_pairs=2)
    hull, check = res.dsm['camera_hull'], res.dsm['one_pair_check']
    assert 0.3 < hull['filled_one_pair'] <= hull['filled']          # the inner strips: one pair, interpolated
    assert check['cells'] > 1000
    if offset_m == 0.0:
        assert check['median_abs_dz_m'] < 0.14    # 0.095 m: push-pull bends across the 16 m wide hole
    else:
        assert check['median_abs_dz_m'] == pytest.approx(offset_m, abs=0.3)
    one = export_map(tmp_path / 'map', tmp_path / 'all', 'EPSG:32632', products=('dsm',), min_pairs=1)
    assert 'one_pair_check' not in one.dsm and 'filled_one_pair' not in one.dsm['camera_hull']
