"""Ground / building classes (core.ground) against the simulator's terrain, whose ground and buildings are known.

The cloud is what stereo fusion gives on that terrain: points every 8 cm on the true DEM with 3 cm
noise, nothing on the walls, 7 % holes, the plain roofs (every other building) matched only along
their edges, a few gross mismatches, and a tree (rough, tall, no walls) that must not become a building.
"""

from __future__ import annotations

import numpy as np
import pytest

from photogram_ros.core.ground import BUILDING, GROUND, GroundParams, classify_points


@pytest.fixture(scope='module')
def sim_cloud():
    from photogram_ros.sim.terrain import make_dem
    rng = np.random.default_rng(3)
    dem, buildings = make_dem(rng, -60, -80, 120, 160, 0.2, relief_m=12.0, n_buildings=6)
    X, Y = np.meshgrid(np.arange(-55, 55, 0.08), np.arange(-75, 75, 0.08))
    x, y = X.ravel(), Y.ravel()
    z = dem.sample(x, y) + rng.normal(0, 0.03, x.size)
    in_building = np.zeros(x.size, bool)
    drop = rng.random(x.size) < 0.07
    for k, (x0, x1, y0, y1, _) in enumerate(buildings):
        in_building |= (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        outer = (x >= x0 - 0.3) & (x <= x1 + 0.3) & (y >= y0 - 0.3) & (y <= y1 + 0.3)
        inner = (x >= x0 + 0.3) & (x <= x1 - 0.3) & (y >= y0 + 0.3) & (y <= y1 - 0.3)
        drop |= outer & ~inner                                   # walls: no points
        if k % 2 == 0:                                           # a plain roof: only its edges matched
            drop |= (x >= x0 + 1) & (x <= x1 - 1) & (y >= y0 + 1) & (y <= y1 - 1)
    keep = ~drop
    x, y, z, in_building = x[keep], y[keep], z[keep], in_building[keep]
    # A tree away from the buildings: a 6 m crown of scattered heights 3-8 m above the ground.
    free = [(tx, ty) for tx in np.arange(-45, 45, 5.0) for ty in np.arange(-65, 65, 5.0)
            if all(not (b[0] - 8 < tx < b[1] + 8 and b[2] - 8 < ty < b[3] + 8) for b in buildings)]
    tx, ty = free[len(free) // 2]
    crown = np.hypot(x - tx, y - ty) < 3.0
    z[crown] += rng.uniform(3.0, 8.0, crown.sum())
    # Gross mismatches: 0.2 % of the points 1-4 m off, up or down.
    bad = rng.random(x.size) < 0.002
    z[bad] += rng.choice([-1, 1], bad.sum()) * rng.uniform(1, 4, bad.sum())
    gx, gy = np.gradient(dem.data.astype(np.float64), dem.res_m)
    steep = _slope_at(dem, gx, gy, x, y) > 0.4
    return dict(x=x, y=y, z=z, ground=~in_building & ~crown & ~bad, building=in_building & ~bad, tree=crown,
                steep=steep & ~in_building & ~crown & ~bad, n_buildings=len(buildings))


def _slope_at(dem, gx, gy, x, y):
    from photogram_ros.sim.terrain import Grid
    sx = Grid(gx.astype(np.float32), dem.x0_m, dem.y0_m, dem.res_m).sample(x, y)
    sy = Grid(gy.astype(np.float32), dem.x0_m, dem.y0_m, dem.res_m).sample(x, y)
    return np.hypot(sx, sy)


def test_ground_and_buildings_against_the_simulated_truth(sim_cloud):
    c = sim_cloud
    res = classify_points(c['x'], c['y'], c['z'])
    cls = res.classes
    scored = c['ground'] | c['building']
    is_ground = cls == GROUND
    accuracy = np.mean(is_ground[scored] == c['ground'][scored])
    recall = is_ground[c['ground']].mean()
    precision = c['ground'][is_ground].mean()
    steep_recall = is_ground[c['steep']].mean()
    building_recall = (cls[c['building']] == BUILDING).mean()
    false_building = (cls[c['ground']] == BUILDING).mean()
    print(f'{c["x"].size} points: ground accuracy {accuracy:.4f} (recall {recall:.4f}, precision {precision:.4f}, '
          f'steep slopes {steep_recall:.4f} of {c["steep"].sum()}), buildings {res.buildings}/{c["n_buildings"]} '
          f'(points {building_recall:.4f}), false building {false_building:.5f}, tree as building '
          f'{(cls[c["tree"]] == BUILDING).mean():.3f}')
    assert c['steep'].sum() > 10_000          # the embankment's flanks are in the scene
    assert accuracy > 0.995 and recall > 0.995 and precision > 0.999
    assert steep_recall > 0.98                 # slopes up to 1:1.5 stay ground
    assert res.buildings == c['n_buildings'] and building_recall > 0.98 and false_building < 0.001
    assert (cls[c['tree']] == BUILDING).mean() < 0.05     # rough and wall-less: not a building
    assert (cls[c['tree']] == GROUND).mean() < 0.05


def test_without_the_slope_rule_the_embankment_is_lost(sim_cloud):
    """The slope term is what keeps steep ground: a flat threshold of dh0 at every window cuts it."""
    c = sim_cloud
    flat = classify_points(c['x'], c['y'], c['z'], GroundParams(slope=0.0, dh_max_m=0.3))
    assert (flat.classes[c['steep']] == GROUND).mean() < 0.9


def test_bad_input_is_refused():
    from photogram_ros.errors import DataError
    with pytest.raises(DataError):
        classify_points([], [], [])
    with pytest.raises(DataError):
        classify_points([0.0, 1.0], [0.0, np.nan], [0.0, 0.0])
