"""A keyframe's fused cloud follows its pose (issue #43, the cloud within seconds of the exposure): core/fusion.py
takes a recorded contribution out of its cells exactly and fuses it again where the new pose places it, as
fusing from scratch at the new pose would."""
from __future__ import annotations

import numpy as np
import pytest

from photogram_ros.core.fusion import Fusion, FusionConfig, pack_rgb

CELL = 0.1


def _cloud(rng, x0, y0, nx, ny, z0=10.0, colour=(200, 100, 50)):
    """One point near the middle of each cell of an nx x ny patch (a gentle slope), with colour and confidence."""
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny))
    x = x0 + (ix.ravel() + 0.5 + rng.uniform(-0.2, 0.2, ix.size)) * CELL
    y = y0 + (iy.ravel() + 0.5 + rng.uniform(-0.2, 0.2, ix.size)) * CELL
    pts = np.zeros(x.size, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('rgb', 'u4'), ('confidence', 'f4')])
    pts['x'], pts['y'] = x, y
    pts['z'] = z0 + 0.02 * (x - x0) + rng.normal(0, 0.01, x.size)
    pts['rgb'] = pack_rgb(*colour)
    pts['confidence'] = 0.9
    return pts


def _moved(pts, T):
    out = pts.copy()
    xyz = np.column_stack([pts['x'], pts['y'], pts['z']]).astype(float) @ T[:3, :3].T + T[:3, 3]
    out['x'], out['y'], out['z'] = xyz.T
    return out


def _cells(f: Fusion) -> dict:
    p = f.points()
    return {(int(i), int(j)): (n, z, x, y, r, npairs) for i, j, n, z, x, y, r, npairs in
            zip(p['ix'], p['iy'], p['n'], p['z'], p['x'], p['y'], p['r'], p['n_pairs'])}


def _fusion():
    return Fusion(FusionConfig(cell_m=CELL, tile_cells=64, min_tolerance_m=0.3))


def _shift(dx, dy, dz=0.0, yaw_rad=0.0):
    T = np.eye(4)
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = dx, dy, dz
    return T


@pytest.mark.parametrize('delta', [_shift(2.0, -1.0, 0.05), _shift(0.33, 0.27, 0.1, np.radians(2.0))],
                         ids=['whole_cells', 'rotated'])
def test_a_moved_contribution_leaves_its_old_cells_and_lands_as_fused_from_scratch(delta):
    rng = np.random.default_rng(3)
    a = _cloud(rng, 0.0, 0.0, 60, 40, colour=(40, 80, 120))       # another keyframe's cloud, never moved
    b = _cloud(rng, 3.0, 1.0, 50, 30, z0=10.05)                   # the keyframe whose pose moves
    f = _fusion()
    f.add(a)
    _, cb = f.add(b, record=True)
    before = _cells(f)
    moved_n, cb2 = f.move(cb, delta)
    after = _cells(f)

    # From scratch: a, then b placed by the new pose.
    g = _fusion()
    g.add(a)
    scratch_n = g.add(_moved(b, delta))
    scratch = _cells(g)
    assert cb2 is not None and moved_n == scratch_n > 0.5 * b.size

    # The cell means a contribution keeps sit within 1/256 of a cell of its points: moved by whole cells they
    # land exactly where the points would; rotated, a point on a cell border may land in the cell beside.
    exact = np.allclose(delta[:3, :3], np.eye(3))
    allowed = 0 if exact else max(1, len(scratch) // 200)
    # Cells at the old placement only: b's points are gone (a's alone, or empty).
    old_only = {k for k in before if before[k][5] >= 1} - set(scratch)
    assert len(old_only) > 100, 'the move must leave cells b alone covered'
    assert len(old_only & set(after)) <= allowed
    assert len(set(after) ^ set(scratch)) <= 2 * allowed
    keys = sorted(set(scratch) & set(after))
    s_arr = np.array([scratch[k][:5] for k in keys], float)
    a_arr = np.array([after[k][:5] for k in keys], float)
    tol_xy = 0.5 / 256 * CELL + 1e-4 if exact else CELL
    assert np.sum(a_arr[:, 0] != s_arr[:, 0]) <= 2 * allowed              # points per cell
    same = a_arr[:, 0] == s_arr[:, 0]
    assert np.max(np.abs(a_arr[same, 1] - s_arr[same, 1])) < 1e-4          # z
    assert np.max(np.abs(a_arr[same, 2:4] - s_arr[same, 2:4])) <= tol_xy
    assert np.max(np.abs(a_arr[same, 4] - s_arr[same, 4])) <= 1.0          # colour, in byte steps
    # Where a and b overlap at the new placement, the cell holds both pairs.
    both = [k for k in keys if scratch[k][5] == 2]
    assert len(both) > 50 and sum(after[k][5] != 2 for k in both) <= allowed


def test_taking_a_contribution_out_gives_the_map_without_it():
    rng = np.random.default_rng(5)
    a, b = _cloud(rng, 0.0, 0.0, 40, 40), _cloud(rng, 2.0, 2.0, 40, 40, z0=10.1, colour=(10, 250, 10))
    f = _fusion()
    f.add(a)
    _, cb = f.add(b, record=True)
    f.remove(cb)
    g = _fusion()
    g.add(a)
    got, want = _cells(f), _cells(g)
    assert set(got) == set(want)
    for k in want:
        assert got[k][0] == want[k][0] and got[k][5] == want[k][5]
        assert abs(got[k][1] - want[k][1]) < 1e-4 and abs(got[k][4] - want[k][4]) <= 1.0
