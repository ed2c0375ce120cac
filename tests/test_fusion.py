"""Map fusion: running means against a numpy oracle, pair-consistency rejection, tiles evicted and
reloaded with flat memory, a crash-torn tile file, and the DSM against the simulator's true DEM."""

from __future__ import annotations

import numpy as np
import pytest

from helpers.clouds import CLOUD_DTYPE, pair_cloud
from photogram_ros.core.fusion import Fusion, FusionConfig
from photogram_ros.core.raster import dsm_from_points
from photogram_ros.io.map_store import MapStore


def plane(x, y):
    return 10.0 + 0.1 * x - 0.05 * y


def test_running_means_match_a_numpy_oracle():
    rng = np.random.default_rng(0)
    a = pair_cloud(rng, plane, 0.0, 0.0, 3.0, 2.0, 400.0, 0.02)
    b = pair_cloud(rng, plane, 1.0, 0.5, 3.0, 2.0, 400.0, 0.02)
    a['rgb'] = rng.integers(0, 2**24, a.size)
    b['rgb'] = rng.integers(0, 2**24, b.size)
    f = Fusion(FusionConfig(cell_m=0.1, tile_cells=16))      # 1.6 m tiles: clouds span many tiles
    f.add(a)
    f.add(b)
    allp = np.concatenate([a, b])
    ix = np.floor(allp['x'] / 0.1).astype(int)
    iy = np.floor(allp['y'] / 0.1).astype(int)
    key = (ix + 1000) * 10000 + (iy + 1000)
    uniq, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    red = (allp['rgb'] >> 16) & 0xFF
    oracle = {'x': np.bincount(inv, allp['x']) / cnt, 'z': np.bincount(inv, allp['z']) / cnt,
              'r': np.bincount(inv, red) / cnt, 'n': cnt}
    var = np.bincount(inv, allp['z'] ** 2) / cnt - oracle['z'] ** 2
    p = f.points()
    mine = np.argsort((p['ix'] + 1000) * 10000 + (p['iy'] + 1000))
    assert p['x'].size == uniq.size
    assert np.array_equal(p['n'][mine], cnt)
    assert np.abs(p['z'][mine] - oracle['z']).max() < 1e-4
    assert np.abs(p['x'][mine] - oracle['x']).max() < 1e-4
    assert np.abs(p['r'][mine] - oracle['r']).max() < 1e-3
    many = cnt > 3
    assert np.allclose(p['sigma_z'][mine][many] ** 2, (var * cnt / (cnt - 1))[many], rtol=1e-2, atol=1e-6)
    assert f.stats.points_fused == allp.size and f.stats.points_rejected == 0


def test_inconsistent_pair_is_rejected_then_outvoted():
    rng = np.random.default_rng(1)
    f = Fusion(FusionConfig(cell_m=0.1, tile_cells=64))
    for _ in range(2):
        f.add(pair_cloud(rng, plane, 0, 0, 2, 2, 300, 0.02))
    before = f.points()
    z_before = dict(zip(zip(before['ix'].tolist(), before['iy'].tolist()), before['z'].tolist()))
    lifted = lambda x, y: plane(x, y) + 1.5   # noqa: E731  a pair 1.5 m off (bad pose or mismatch)
    c = pair_cloud(rng, lifted, 0, 0, 2, 2, 300, 0.02)
    f.add(c)
    after = f.points()
    kept = [z_before[k] == z for k, z in zip(zip(after['ix'].tolist(), after['iy'].tolist()), after['z'].tolist())
            if k in z_before]
    assert len(kept) == len(z_before) and all(kept)        # no fused cell moved
    # Every point landing on an existing cell was rejected; only never-seen cells took the rest.
    assert after['x'].size - len(z_before) < 0.01 * len(z_before)
    assert f.stats.points_rejected >= 0.99 * c.size
    # Two more lifted pairs: rejections outnumber the pairs behind the cells, which are rebuilt.
    for _ in range(2):
        f.add(pair_cloud(rng, lifted, 0, 0, 2, 2, 300, 0.02))
    p = f.points()
    assert f.stats.cells_replaced > 0.8 * p["x"].size   # cells hit by all three lifted pairs (~86 %)
    assert np.median(p['z'] - plane(p['x'], p['y'])) == pytest.approx(1.5, abs=0.02)


def test_isolated_speckle_is_dropped_inside_a_pair():
    rng = np.random.default_rng(2)
    f = Fusion(FusionConfig(cell_m=0.08))
    c = pair_cloud(rng, plane, 0, 0, 5, 5, 160, 0.02, outlier_fraction=0.02)
    f.add(c)
    p = f.points()
    err = np.abs(p['z'] - plane(p['x'], p['y']))
    assert np.percentile(err, 99.5) < 0.1
    assert (err > 1.0).mean() < 0.002                     # of ~2 % outlier points
    assert f.stats.points_rejected >= 0.9 * 0.02 * c.size


def test_bad_clouds_raise_or_are_skipped():
    from photogram_ros.errors import DataError
    f = Fusion(FusionConfig(cell_m=0.08))
    with pytest.raises(DataError):
        f.add(np.zeros(3, dtype=[('x', 'f8'), ('y', 'f8')]))
    c = np.zeros(4, dtype=CLOUD_DTYPE)
    c['z'] = np.nan
    assert f.add(c) == 0 and f.stats.points_invalid == 4


def test_long_track_memory_flat_tiles_evicted_and_reloaded(tmp_path):
    """2 km of clouds with at most 6 tiles in memory: memory is bounded, evicted tiles reload intact."""
    import tracemalloc
    rng = np.random.default_rng(3)
    store = MapStore(tmp_path / 'map', 0.08, 128)
    f = Fusion(FusionConfig(cell_m=0.08, tile_cells=128, max_tiles_in_memory=6), store)
    first = pair_cloud(rng, plane, 0.0, 0.0, 8.0, 6.0, 100.0, 0.02)
    peaks = []
    tracemalloc.start()
    for k in range(160):                        # 12.5 m steps: 2 km north
        c = first if k == 0 else pair_cloud(rng, plane, 0.0, 12.5 * k, 8.0, 6.0, 100.0, 0.02)
        f.add(c)
        if k % 10 == 9:
            f.flush()
            peaks.append(tracemalloc.get_traced_memory()[0])
    tracemalloc.stop()
    one_tile = 128 * 128 * (40 + 1)
    assert len(f.tiles) <= 6 + 4                # the cloud being fused may span 4 tiles
    assert f.memory_bytes <= 10 * one_tile
    assert f.stats.tiles_evicted > 100
    # Flat: memory after 2 km is no larger than after the first 200 m (within 20 %).
    assert max(peaks[5:]) < 1.2 * max(peaks[:2]) + 2e6, [round(p / 1e6, 1) for p in peaks]
    assert len(store.tile_keys()) > 100
    # The first tile went to disk long ago; fusing there again reloads it with its content.
    f.add(first)
    assert f.stats.tiles_loaded >= 1
    p = f.points()
    near = (np.abs(p['x']) < 8) & (np.abs(p['y']) < 6)
    assert np.median(p['n_pairs'][near]) == 2


def test_torn_tail_of_a_crash_is_ignored_and_cut(tmp_path):
    rng = np.random.default_rng(4)
    store = MapStore(tmp_path / 'm', 0.1, 64)
    f = Fusion(FusionConfig(cell_m=0.1, tile_cells=64), store)
    f.add(pair_cloud(rng, plane, 3.2, 3.2, 3.0, 3.0, 1000, 0.01))
    f.flush()
    good = f.points()
    path = store.tiles_dir / '0_0.pgt'
    with open(path, 'ab') as fh:                # a crash in the middle of the next block
        fh.write(b'PBLK' + b'\x05\x00\x00\x00' + b'garbage' * 9)
    store2 = MapStore(tmp_path / 'm')
    f2 = Fusion(FusionConfig(cell_m=0.1, tile_cells=64), store2)
    reloaded = f2.points()
    assert reloaded['x'].size == good['x'].size and np.allclose(np.sort(reloaded['z']), np.sort(good['z']))
    f2.add(pair_cloud(rng, plane, 3.2, 3.2, 3.0, 3.0, 1000, 0.01))    # appends after cutting the tail
    f2.flush()
    again = Fusion(FusionConfig(cell_m=0.1, tile_cells=64), MapStore(tmp_path / 'm')).points()
    assert np.median(again['n_pairs']) == 2
    with pytest.raises(Exception):
        MapStore(tmp_path / 'm', 0.2, 64)     # a different grid on the same folder is refused


def test_dsm_against_the_true_dem():
    """Pair clouds sampled from the simulator's DEM with 5 cm noise and 2 % gross outliers."""
    from photogram_ros.sim.scenario import build_world, preset
    cfg = preset('tiny')
    rng = np.random.default_rng(cfg.seed)
    flight, terrain, _ = build_world(cfg, rng)
    gsd = cfg.gsd_m
    hw, hh = cfg.width_px * gsd / 2 * 0.8, cfg.height_px * gsd / 2 * 0.8
    f = Fusion(FusionConfig(cell_m=0.08))
    feet = []
    for t in np.arange(0.0, flight.duration_s, 2.0):
        st = flight.state(t)
        if st.on_line:
            cx, cy = st.pos_enu[:2]
            f.add(pair_cloud(rng, terrain.height_at, cx, cy, hw, hh, 1.5 / 0.08 ** 2, 0.05, 0.02))
            feet.append((cx, cy))
    p = f.points()
    dsm = dsm_from_points(p['x'], p['y'], p['z'], 2 * gsd, weights=p['n'])
    X, Y = dsm.cell_centers()
    surveyed = np.zeros(dsm.shape, dtype=bool)
    for cx, cy in feet:
        surveyed |= (np.abs(X - cx) < hw - 0.2) & (np.abs(Y - cy) < hh - 0.2)
    have = dsm.valid() & surveyed
    err = (dsm.data - terrain.height_at(X, Y))[have]
    rmse = float(np.sqrt(np.mean(err ** 2)))
    completeness = have.sum() / surveyed.sum()
    print(f'DSM vs true DEM: RMSE {rmse / gsd:.2f} GSD, median |dz| {np.median(np.abs(err)) / gsd:.2f} GSD, '
          f'completeness {completeness:.3f}')
    assert rmse <= 2 * gsd
    assert completeness >= 0.95


def test_a_pair_that_the_map_rejects_everywhere_fuses_nothing_and_goes_on():
    """A pair cloud whose every point lands on a fused cell and disagrees with it (1.5 m off) adds nothing,
    counts its points as rejected and leaves the map as it was."""
    rng = np.random.default_rng(2)
    f = Fusion(FusionConfig(cell_m=0.1, tile_cells=64))
    first = pair_cloud(rng, plane, 0, 0, 2, 2, 300, 0.02)
    f.add(first)
    f.add(pair_cloud(rng, plane, 0, 0, 2, 2, 300, 0.02))
    before = f.points()
    lifted = first.copy()
    lifted['z'] += 1.5
    rejected = f.stats.points_rejected
    assert f.add(lifted) == 0
    assert f.stats.points_rejected - rejected == lifted.size
    after = f.points()
    assert after['x'].size == before['x'].size and np.array_equal(after['z'], before['z'])
