"""DSM rasterisation at walls: a perfect cloud of a flat-roofed building must give ~0 error, not mixed cells."""
import numpy as np

from photogram_ros.core.raster import NODATA, dsm_from_points, fill_gaps


def _building_cloud(spacing=0.03, seed=0):
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(0, 10, spacing), np.arange(0, 10, spacing))
    x = x.ravel() + rng.uniform(0, spacing, x.size)
    y = y.ravel() + rng.uniform(0, spacing, y.size)
    roof = (x > 3.05) & (x < 6.95) & (y > 3.05) & (y < 6.95)
    return x, y, np.where(roof, 8.0, 0.1 * x), roof


def _truth(x, y):
    return np.where((x > 3.05) & (x < 6.95) & (y > 3.05) & (y < 6.95), 8.0, 0.1 * x)


def test_cells_straddling_a_wall_are_nodata_not_half_way_up():
    x, y, z, _ = _building_cloud()
    plain = dsm_from_points(x, y, z, 0.24)
    clean = dsm_from_points(x, y, z, 0.24, max_spread_m=0.5)
    for r, expect_big in ((plain, True), (clean, False)):
        X, Y = r.cell_centers()
        v = r.valid()
        err = r.data[v] - _truth(X[v], Y[v])
        assert (np.abs(err).max() > 2.0) == expect_big
    X, Y = clean.cell_centers()
    v = clean.valid()
    # Only the cells the wall runs through are lost (~4 sides x 4 m / 0.24 m of 1700).
    assert 0.9 * v.size < v.sum() < v.size
    assert np.sqrt(np.mean((clean.data[v] - _truth(X[v], Y[v])) ** 2)) < 0.05


def test_gap_fill_bridges_agreeing_sides_only():
    d = np.full((5, 20), 1.0, np.float32)
    d[:, 8:12] = NODATA           # a 4-cell track between equal fields: filled
    d[0, 8:12] = NODATA
    d[4, :] = 1.0
    d[4, 12:] = 6.0               # ... but not where one side is a roof
    d[4, 8:12] = NODATA
    d[:, 17:] = NODATA            # open to the map edge: stays no-data
    out = fill_gaps(d, 4, 0.5)
    assert np.allclose(out[1, 8:12], 1.0)
    assert np.all(out[4, 8:12] == NODATA)
    assert np.all(out[:, 17:] == NODATA)
    assert np.all(fill_gaps(d, 3, 0.5)[1, 8:12] == NODATA)   # wider than allowed


def test_foot_of_a_step_is_cleared():
    from photogram_ros.core.raster import clear_step_feet
    d = np.zeros((6, 6), np.float32)
    d[:, 3:] = 5.0
    out = clear_step_feet(d, 1.0)
    assert np.all(out[:, 2] == NODATA) and np.all(out[:, 3:] == 5.0) and np.all(out[:, :2] == 0.0)
