"""The DTM (core/dtm.py) follows the bare ground of the simulator's terrain, under its buildings too, and
dtm.tif is written beside dsm.tif on the same grid."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope='module')
def world():
    """The simulator's terrain (hills, an embankment, flat-roofed buildings) sampled like a dense cloud,
    and the same terrain without its buildings (the truth of the DTM)."""
    from photogram_ros.sim.terrain import make_dem
    rng = np.random.default_rng(11)
    dem, buildings = make_dem(rng, 0.0, 0.0, 120.0, 100.0, 0.25, n_buildings=6)
    ground = make_dem(np.random.default_rng(11), 0.0, 0.0, 120.0, 100.0, 0.25, n_buildings=0)[0]
    n = 250_000
    x, y = rng.uniform(0, 120, n), rng.uniform(0, 100, n)
    z = dem.sample(x, y) + rng.normal(0, 0.03, n)
    return dem, ground, buildings, x, y, z


def _near_buildings(buildings, x, y, margin_m):
    out = np.zeros(np.shape(x), bool)
    for x0, x1, y0, y1, _ in buildings:
        out |= (x > x0 - margin_m) & (x < x1 + margin_m) & (y > y0 - margin_m) & (y < y1 + margin_m)
    return out


def test_dtm_is_the_ground_away_from_and_under_buildings(world):
    from photogram_ros.core.dtm import dtm_from_points
    from photogram_ros.core.raster import grid_for
    dem, ground, buildings, x, y, z = world
    assert len(buildings) >= 4
    # the ground without buildings is the same terrain: the generator draws the buildings last
    assert np.allclose(ground.sample(5.0, 5.0), dem.sample(5.0, 5.0))
    like = grid_for(0.0, 0.0, 120.0, 100.0, 0.5)
    like.data[:] = 0.0
    res = dtm_from_points(x, y, z, like)
    X, Y = like.cell_centers()
    err = res.raster.data - ground.sample(X, Y)
    away = ~_near_buildings(buildings, X, Y, 2.0)
    inside = (X > 3) & (X < 117) & (Y > 3) & (Y < 97)
    rmse_away = float(np.sqrt(np.mean(err[away & inside] ** 2)))
    under = _near_buildings(buildings, X, Y, -1.0)
    print(f'DTM RMSE away from buildings {rmse_away:.3f} m; under buildings median |dz| '
          f'{np.median(np.abs(err[under])):.2f} m')
    assert rmse_away <= 0.036                    # measured 0.024 m (0.5 m cells, 3 cm noise)
    assert np.median(np.abs(err[under])) < 0.36  # measured 0.24 m: the ground runs on under roofs 4-10 m up
    assert res.ground[under].mean() < 0.05       # roofs are not ground
    assert res.ground[away & inside].mean() > 0.9


def test_export_writes_dtm_beside_the_dsm_on_its_grid(tmp_path):
    import rasterio
    from helpers.clouds import pair_cloud
    from photogram_ros.core.fusion import Fusion, FusionConfig
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.io.export import export_map
    from photogram_ros.io.map_store import MapStore

    def terrain(x, y):   # a 6 m block 8 m wide on a gentle slope
        return 1.0 + 0.03 * x + np.where((np.abs(x) < 4) & (np.abs(y) < 4), 6.0, 0.0)

    store = MapStore(tmp_path / 'map', 0.25, 256)
    store.set_origin(LocalFrame(47.3977, 8.5456, 488.0))
    f = Fusion(FusionConfig(0.25, 256), store)
    rng = np.random.default_rng(2)
    for _ in range(2):
        f.add(pair_cloud(rng, terrain, 0.0, 0.0, 20.0, 20.0, 40.0, 0.01))
    f.flush()
    res = export_map(store, tmp_path / 'out', 'EPSG:32632', products=('dsm', 'dtm'), min_pairs=2)
    with rasterio.open(res.files['dsm']) as a, rasterio.open(res.files['dtm']) as b:
        assert a.transform == b.transform and a.shape == b.shape
        dsm, dtm = a.read(1), b.read(1)
        centre = tuple(int(v) for v in ~a.transform * (a.bounds.left + 0.5 * (a.bounds.right - a.bounds.left),
                                                         a.bounds.bottom + 0.5 * (a.bounds.top - a.bounds.bottom)))
    c, r = centre
    assert dsm[r, c] - dtm[r, c] == pytest.approx(6.0, abs=0.5)   # the block in the DSM, not in the DTM
    assert res.dtm['ground_points'] > 0
