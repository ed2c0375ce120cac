"""Ground and building classes of a point cloud: ASPRS LAS classes 2 (ground), 6 (building), 1 (the rest).

Works in any planar metric frame (map ENU or a projected CRS); heights may be ellipsoidal or
orthometric, the two differ by a smooth offset that no step here sees.

Ground: a progressive morphological filter (Zhang et al. 2003, IEEE TGRS 41(4), "A progressive
morphological filter for removing nonground measurements from airborne LIDAR data") on a grid of the
lowest point per cell (`cell_m`; empty cells take their nearest observed neighbour). Openings with
disks growing from 3 cells to `max_window_m` remove, at each size, what is narrower than the disk; a
cell is non-ground when an opening lowers it by more than the slope rule allows for that growth of
the window, `dh0_m + slope * growth`, never more than `dh_max_m`. A slope of terrain steeper than
`slope` (an embankment's flank) or an object lower than `dh_max_m` stays ground; a building, taller
than `dh_max_m` and narrower than the largest window, does not. The ground surface is then
interpolated (linearly) from the ground cells, each at the mean height of its lowest points, and a
point is ground when it lies within `ground_tol_m` of that surface.

Building: cells standing more than `building_min_height_m` above the ground surface, grouped into
connected regions of at least `building_min_area_m2`, kept only if the region has a roof of planes
(the median height residual of its cells against their neighbours below `roof_roughness_m`: trees
are rough, both within a cell, against the cell's best plane, and from cell to cell) and walls (at least `wall_fraction` of the cells around it are near ground level or
unobserved, as under a wall; a hillside rises gradually). Points of such regions higher than
`building_min_height_m` above the ground are class 6. Everything else (vegetation, vehicles,
noise, wall points) stays class 1: the classes are what a simple rule can tell reliably.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from photogram_ros.errors import DataError
from photogram_ros.params import param

UNCLASSIFIED, GROUND, BUILDING = 1, 2, 6


@dataclass
class GroundParams:
    cell_m: float = param(0.5, 'grid cell of the ground filter, m (a few points per cell)', min=0.05, max=10.0)
    max_window_m: float = param(20.0, 'largest opening window, m: wider than the largest building', min=1.0,
                                max=500.0)
    slope: float = param(0.7, 'terrain slope the filter keeps as ground (rise over run; 0.7 = 35 deg, a 1:1.5 '
                         'embankment flank)', min=0.0, max=10.0)
    dh0_m: float = param(0.3, 'height an opening may remove from ground at the smallest window, m', min=0.0,
                         max=10.0)
    dh_max_m: float = param(3.0, 'most an opening may remove from ground, m: above embankments and low objects, '
                            'below buildings', min=0.1, max=100.0)
    ground_tol_m: float = param(0.3, 'a point within this height of the ground surface is ground, m', min=0.01,
                                max=5.0)
    outlier_m: float = param(1.0, 'a cell lowest point this far below its neighbours\' median is noise, m',
                             min=0.1, max=100.0)
    building_min_height_m: float = param(2.0, 'building cells stand at least this high above the ground, m',
                                         min=0.5, max=100.0)
    building_min_area_m2: float = param(10.0, 'smallest building footprint, m^2', min=0.5, max=1e6)
    roof_roughness_m: float = param(0.15, 'largest median residual of a roof cell against its neighbours, m '
                                    '(planar roofs: a few cm; trees: decimetres)', min=0.01, max=10.0)
    wall_fraction: float = param(0.5, 'share of the cells around a building that must be near ground level or '
                                 'unobserved (walls)', min=0.0, max=1.0)


@dataclass
class Classification:
    classes: np.ndarray                 # (N,) uint8 ASPRS classes per point
    height_above_ground_m: np.ndarray   # (N,) float32, NaN where no ground surface
    buildings: int = 0                  # building regions found
    notes: list = field(default_factory=list)

    def counts(self) -> dict:
        values, n = np.unique(self.classes, return_counts=True)
        return {int(v): int(c) for v, c in zip(values, n)}


@dataclass
class _Grid:
    x0: float
    y0: float
    cell: float
    shape: tuple
    key: np.ndarray          # (N,) flat cell index of each point

    def centres(self):
        h, w = self.shape
        return np.meshgrid(self.x0 + (np.arange(w) + 0.5) * self.cell, self.y0 + (np.arange(h) + 0.5) * self.cell)

    def fractional(self, x, y):
        """(col, row) with integer values at cell centres."""
        return (x - self.x0) / self.cell - 0.5, (y - self.y0) / self.cell - 0.5


def classify_points(x, y, z, p: GroundParams | None = None) -> Classification:
    """ASPRS classes 1 / 2 / 6 of the points (see the module docstring)."""
    p = p or GroundParams()
    x, y, z = (np.asarray(v, np.float64) for v in (x, y, z))
    if x.size == 0:
        raise DataError('cannot classify an empty point cloud')
    if not (np.isfinite(x).all() and np.isfinite(y).all() and np.isfinite(z).all()):
        raise DataError('point coordinates must be finite to classify them')
    grid = _grid(x, y, p.cell_m)
    zmin, observed = _lowest_per_cell(grid, z, p.outlier_m)
    ground_cells = observed & ~_pmf_nonground(_nearest_fill(zmin, observed), grid.cell, p)
    notes = []
    if ground_cells.sum() < 3:
        notes.append('too few ground cells for a ground surface: every point left unclassified')
        return Classification(np.full(x.size, UNCLASSIFIED, np.uint8), np.full(x.size, np.nan, np.float32),
                              notes=notes)
    surface = _ground_surface(grid, z, zmin, ground_cells, p.ground_tol_m)
    hag = z - _bilinear(surface, *grid.fractional(x, y))
    classes = np.full(x.size, UNCLASSIFIED, np.uint8)
    classes[np.abs(hag) <= p.ground_tol_m] = GROUND
    cell_median = _median_per_cell(grid, z)
    plane_rms = _plane_rms_per_cell(grid, x, y, z)
    building_cells, n_buildings = _buildings(cell_median - surface, cell_median, plane_rms, observed, grid, p)
    classes[building_cells.ravel()[grid.key] & (hag > p.building_min_height_m)] = BUILDING
    return Classification(classes, hag.astype(np.float32), n_buildings, notes)


def _grid(x, y, cell: float) -> _Grid:
    x0, y0 = np.floor(x.min() / cell) * cell, np.floor(y.min() / cell) * cell
    w = int((x.max() - x0) // cell) + 1
    h = int((y.max() - y0) // cell) + 1
    if w * h > 100_000_000:
        raise DataError(f'a {w}x{h} ground-filter grid at {cell} m is too large: choose a coarser cell_m')
    col = np.minimum(((x - x0) // cell).astype(np.int64), w - 1)
    row = np.minimum(((y - y0) // cell).astype(np.int64), h - 1)
    return _Grid(float(x0), float(y0), float(cell), (h, w), row * w + col)


def _lowest_per_cell(grid: _Grid, z, outlier_m: float):
    n_cells = grid.shape[0] * grid.shape[1]
    zmin = np.full(n_cells, np.inf)
    np.minimum.at(zmin, grid.key, z)
    observed = np.isfinite(zmin)
    zmin = zmin.reshape(grid.shape).astype(np.float32)
    observed = observed.reshape(grid.shape)
    # A lowest point far below the neighbourhood's is noise (a mismatch): it would dig a pit the
    # opening keeps. The cell takes its neighbours' median instead.
    filled = _nearest_fill(zmin, observed)
    med = cv2.medianBlur(filled, 3) if filled.shape[0] > 1 and filled.shape[1] > 1 else filled
    pit = observed & (zmin < med - outlier_m)
    zmin[pit] = med[pit]
    return zmin, observed


def _nearest_fill(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    from scipy.ndimage import distance_transform_edt
    if valid.all():
        return values.astype(np.float32)
    _, (ri, ci) = distance_transform_edt(~valid, return_indices=True)
    return values[ri, ci].astype(np.float32)


def _windows_cells(cell_m: float, max_window_m: float) -> list[int]:
    """Odd window sizes 3, 5, 9, 17, ... cells (Zhang's exponential series), the last one max_window_m."""
    largest = max(int(round(max_window_m / cell_m)) | 1, 3)
    out, k = [], 1
    while True:
        w = 2 ** k + 1
        if w >= largest:
            out.append(largest)
            return out
        out.append(w)
        k += 1


def _pmf_nonground(surface: np.ndarray, cell_m: float, p: GroundParams) -> np.ndarray:
    nonground = np.zeros(surface.shape, bool)
    prev_w = 1
    for k, w in enumerate(_windows_cells(cell_m, p.max_window_m)):
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (w, w))
        opened = cv2.morphologyEx(surface, cv2.MORPH_OPEN, disk, borderType=cv2.BORDER_REPLICATE)
        dh = p.dh0_m if k == 0 else min(p.dh0_m + p.slope * (w - prev_w) * cell_m, p.dh_max_m)
        nonground |= surface - opened > dh
        surface, prev_w = opened, w
    return nonground


def _ground_surface(grid: _Grid, z, zmin, ground_cells, tol_m: float) -> np.ndarray:
    """Ground height on the grid: each ground cell at the mean of its points near its lowest one, the
    other cells filled from the ground cells around them (OpenCV's fast-marching inpainting, Telea 2004)."""
    low = z <= zmin.ravel()[grid.key] + tol_m
    n_cells = zmin.size
    s = np.bincount(grid.key[low], z[low], minlength=n_cells)
    c = np.bincount(grid.key[low], minlength=n_cells)
    level = np.where(c > 0, s / np.maximum(c, 1), zmin.ravel()).reshape(grid.shape)
    ref = float(np.mean(level[ground_cells]))
    rel = np.where(ground_cells, level - ref, 0.0).astype(np.float32)
    filled = cv2.inpaint(rel, (~ground_cells).astype(np.uint8), 3, cv2.INPAINT_TELEA)
    return np.where(ground_cells, level, filled.astype(np.float64) + ref)


def _bilinear(grid_values: np.ndarray, col, row) -> np.ndarray:
    h, w = grid_values.shape
    col = np.clip(col, 0, w - 1)
    row = np.clip(row, 0, h - 1)
    c0 = np.minimum(np.floor(col).astype(np.int64), max(w - 2, 0))
    r0 = np.minimum(np.floor(row).astype(np.int64), max(h - 2, 0))
    c1, r1 = np.minimum(c0 + 1, w - 1), np.minimum(r0 + 1, h - 1)
    fc, fr = col - c0, row - r0
    g = grid_values
    return ((1 - fr) * ((1 - fc) * g[r0, c0] + fc * g[r0, c1]) + fr * ((1 - fc) * g[r1, c0] + fc * g[r1, c1]))


def _median_per_cell(grid: _Grid, z) -> np.ndarray:
    """Median height of each cell's points (NaN where empty)."""
    order = np.lexsort((z, grid.key))
    ks, zs = grid.key[order], z[order]
    starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    counts = np.diff(np.r_[starts, ks.size])
    lo = zs[starts + (counts - 1) // 2]
    hi = zs[starts + counts // 2]
    out = np.full(grid.shape[0] * grid.shape[1], np.nan)
    out[ks[starts]] = 0.5 * (lo + hi)
    return out.reshape(grid.shape)


def _plane_rms_per_cell(grid: _Grid, x, y, z, min_points: int = 6) -> np.ndarray:
    """RMS of each cell's points about their least-squares plane (NaN with fewer than `min_points`).

    A roof, flat or pitched, leaves the matching noise; a tree crown leaves decimetres to metres.
    """
    n_cells = grid.shape[0] * grid.shape[1]
    col, row = grid.fractional(x, y)
    u = (col - np.round(col)) * grid.cell           # offsets from the cell centre, m
    v = (row - np.round(row)) * grid.cell
    k = grid.key
    n = np.bincount(k, minlength=n_cells).astype(np.float64)
    zc = z - (np.bincount(k, z, minlength=n_cells) / np.maximum(n, 1))[k]
    s = {name: np.bincount(k, w, minlength=n_cells) for name, w in
         (('u', u), ('v', v), ('uu', u * u), ('uv', u * v), ('vv', v * v), ('uz', u * zc), ('vz', v * zc),
          ('zz', zc * zc))}
    A = np.stack([np.stack([s['uu'], s['uv'], s['u']], -1), np.stack([s['uv'], s['vv'], s['v']], -1),
                  np.stack([s['u'], s['v'], n], -1)], -2)
    b = np.stack([s['uz'], s['vz'], np.zeros(n_cells)], -1)
    ok = n >= min_points
    coef = np.zeros((n_cells, 3))
    det = np.linalg.det(A[ok])
    good = np.flatnonzero(ok)[np.abs(det) > 1e-12]
    coef[good] = np.linalg.solve(A[good], b[good][..., None])[..., 0]
    # residual sum of squares = zz - coef . b  (normal equations; the centred z has zero mean)
    rss = s['zz'] - np.einsum('ij,ij->i', coef, b)
    out = np.full(n_cells, np.nan)
    out[good] = np.sqrt(np.maximum(rss[good], 0.0) / n[good])
    return out.reshape(grid.shape)


def _buildings(height: np.ndarray, cell_z: np.ndarray, plane_rms: np.ndarray, observed, grid: _Grid,
               p: GroundParams):
    """Cells of building regions (bool grid) and how many regions."""
    tall = observed & (height > p.building_min_height_m)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(tall.astype(np.uint8), connectivity=8)
    keep = np.zeros(tall.shape, bool)
    if n <= 1:
        return keep, 0
    roughness = _roughness(cell_z, tall)
    min_cells = p.building_min_area_m2 / grid.cell ** 2
    ring_kernel = np.ones((5, 5), np.uint8)
    found = 0
    for label in range(1, n):
        if stats[label, cv2.CC_STAT_AREA] < min_cells:
            continue
        x0, y0 = stats[label, cv2.CC_STAT_LEFT], stats[label, cv2.CC_STAT_TOP]
        bw, bh = stats[label, cv2.CC_STAT_WIDTH], stats[label, cv2.CC_STAT_HEIGHT]
        r0, r1 = max(y0 - 2, 0), min(y0 + bh + 2, tall.shape[0])
        c0, c1 = max(x0 - 2, 0), min(x0 + bw + 2, tall.shape[1])
        region = labels[r0:r1, c0:c1] == label
        rough = (roughness[r0:r1, c0:c1][region], plane_rms[r0:r1, c0:c1][region])
        if any(np.isfinite(r).any() and np.nanmedian(r) > p.roof_roughness_m for r in rough):
            continue
        ring = cv2.dilate(region.astype(np.uint8), ring_kernel).astype(bool) & ~region
        h_ring = height[r0:r1, c0:c1][ring]
        low = ~observed[r0:r1, c0:c1][ring] | (h_ring < 0.5 * p.building_min_height_m)
        if ring.any() and low.mean() < p.wall_fraction:
            continue
        keep[r0:r1, c0:c1] |= region
        found += 1
    return keep, found


def _roughness(cell_z: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """|height - plane through its masked 3x3 neighbours| per masked cell (NaN elsewhere).

    The mean of opposite neighbours lies on any plane through the cell, so a planar roof (flat or
    pitched) leaves only noise; a ridge or a roof edge leaves a residual on one line of cells.
    """
    z = np.where(mask, cell_z, 0.0).astype(np.float64)
    m = mask.astype(np.float64)
    best = np.full(cell_z.shape, np.nan)
    pz = np.pad(z, 1)
    pm = np.pad(m, 1)
    h, w = cell_z.shape
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = pz[1 + dr:1 + dr + h, 1 + dc:1 + dc + w]
        b = pz[1 - dr:1 - dr + h, 1 - dc:1 - dc + w]
        ok = mask & (pm[1 + dr:1 + dr + h, 1 + dc:1 + dc + w] > 0) & (pm[1 - dr:1 - dr + h, 1 - dc:1 - dc + w] > 0)
        r = np.where(ok, np.abs(z - 0.5 * (a + b)), np.nan)
        best = np.fmin(best, r)
    return best
