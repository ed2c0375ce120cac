"""DSM over vegetation: a tree crown spreads as much as a wall, but must keep its top, and the wall must not.

The oracle is a synthetic fused cloud (one point per 0.12 m fused cell, as the map has it, gridded at
0.24 m with the map's rules: spread 0.5 m, 3 fused cells a cell): a slope, a flat-roofed building
(tests/test_dsm_walls.py) and two tree crowns whose points lie at random depths under the crown surface
(foliage seen through). The old rule made the rough crown cells no-data.
"""
import numpy as np
import pytest

from photogram_ros.core.raster import dsm_from_points, rough_surface_cells

CROWNS = ((14.0, 5.0, 2.6, 6.0), (14.5, 14.0, 3.0, 7.0))   # x, y, radius, height above ground, m
RULES = dict(max_spread_m=0.5, min_count=3, fill_gaps_m=3.0)


def _ground(x):
    return 0.1 * x


def _roof(x, y):
    return (x > 3.05) & (x < 6.95) & (y > 3.05) & (y < 6.95)


def _crown_top(x, y):
    """Height of the crown surface above the ground (0 outside the crowns): a half-ellipsoid."""
    top = np.zeros_like(x)
    for cx, cy, r, h in CROWNS:
        q = 1.0 - ((x - cx) ** 2 + (y - cy) ** 2) / r ** 2
        top = np.maximum(top, h * np.sqrt(np.clip(q, 0.0, None)))
    return top


def _scene(seed=0, spacing=0.12):
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(0, 20, spacing), np.arange(0, 20, spacing))
    x = x.ravel() + rng.uniform(0, spacing, x.size)
    y = y.ravel() + rng.uniform(0, spacing, y.size)
    crown = _crown_top(x, y) > 1.0
    depth = np.minimum(rng.exponential(0.4, x.size), 2.0)   # how far into the foliage stereo saw
    z = np.where(_roof(x, y), 8.0, _ground(x) + np.where(crown, _crown_top(x, y) - depth, 0.0))
    return x, y, z + rng.normal(0, 0.02, x.size)


def _cells(r):
    X, Y = r.cell_centers()
    return X, Y, r.valid()


@pytest.fixture(scope='module')
def dsms():
    x, y, z = _scene()
    return (dsm_from_points(x, y, z, 0.24, **RULES),
            dsm_from_points(x, y, z, 0.24, canopy=True, **RULES))


def test_crowns_keep_their_top_where_the_old_rule_left_holes(dsms):
    old, new = dsms
    X, Y, _ = _cells(new)
    top = _crown_top(X, Y)
    # The crown's body, away from its rim (where the crown meets the ground in a step).
    body = top > 2.0
    share_old, share_new = old.valid()[body].mean(), new.valid()[body].mean()
    assert share_old < 0.6, share_old
    assert share_new > 0.9, share_new
    v = new.valid() & body
    dz = new.data[v] - (_ground(X[v]) + top[v])
    # The top of the foliage (an upper quartile), not its mean, and not above the crown.
    assert np.median(np.abs(dz)) < 0.25
    assert np.percentile(dz, 99) < 0.25
    mean_dsm = dsm_from_points(*_scene(), 0.24, min_count=3)
    assert np.median(new.data[v]) > np.median(mean_dsm.data[v]) + 0.1


def test_the_wall_grows_no_skirt(dsms):
    old, new = dsms
    X, Y, v = _cells(new)
    near_building = (X > 2.0) & (X < 8.0) & (Y > 2.0) & (Y < 8.0)
    truth = np.where(_roof(X, Y), 8.0, _ground(X))
    for r in (old, new):
        ok = r.valid() & near_building
        assert np.abs(r.data[ok] - truth[ok]).max() < 0.2          # no cell half-way up the wall
    # The cells the wall runs through stay no-data, and the rest keep their heights, exactly as before.
    assert np.array_equal(old.valid() & near_building, new.valid() & near_building)
    assert np.array_equal(old.data[near_building], new.data[near_building])
    assert (~new.valid() & near_building).sum() > 60          # the wall's outline: 4 sides of 16 cells


def test_a_bimodal_neighbourhood_is_a_wall_a_continuous_one_is_not():
    rng = np.random.default_rng(1)
    # 3x3 cells of 4 points each: one split 8 m / 0 m (a wall), one spread evenly over 3 m (a crown).
    row = np.repeat(np.arange(3), 12)
    col = np.tile(np.repeat(np.arange(3), 4), 3)
    wall_z = np.where(col == 0, 8.0, 0.0) + rng.normal(0, 0.02, row.size)
    wall_z[(col == 1) & (np.arange(row.size) % 2 == 0)] = 8.0
    crown_z = rng.uniform(4.0, 7.0, row.size)
    assert not rough_surface_cells(row, col, wall_z, np.array([4]), 3)[0]
    assert rough_surface_cells(row, col, crown_z, np.array([4]), 3)[0]
    # Too few points to tell: a wall, as before.
    assert not rough_surface_cells(row[:8], col[:8], crown_z[:8], np.array([4]), 3)[0]
