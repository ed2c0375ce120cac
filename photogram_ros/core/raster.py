"""Rasters from the fused map: the DSM, and the orthomosaic of keyframes draped on a DSM.

A Raster is north-up: row 0 is the northern edge, column 0 the western edge, square cells of
`res_m`. Its coordinates are those of a planar grid frame: the `map` ENU frame itself, or a
projected CRS (UTM, LV95, ...) when exports ask for one; functions that need map ENU take a
`grid_to_map` callable so the same code serves both.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.errors import DataError

NODATA = -9999.0


@dataclass
class Raster:
    data: np.ndarray      # (rows, cols) or (rows, cols, bands)
    x0_m: float           # western edge of column 0
    y1_m: float           # northern edge of row 0
    res_m: float
    nodata: float | None = NODATA

    @property
    def shape(self):
        return self.data.shape[:2]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(west, south, east, north) of the outer cell edges."""
        h, w = self.shape
        return self.x0_m, self.y1_m - h * self.res_m, self.x0_m + w * self.res_m, self.y1_m

    @property
    def geotransform(self) -> tuple:
        """GDAL geotransform (x0, dx, 0, y1, 0, -dy)."""
        return (self.x0_m, self.res_m, 0.0, self.y1_m, 0.0, -self.res_m)

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.shape
        xs = self.x0_m + (np.arange(w) + 0.5) * self.res_m
        ys = self.y1_m - (np.arange(h) + 0.5) * self.res_m
        return np.meshgrid(xs, ys)

    def valid(self) -> np.ndarray:
        d = self.data if self.data.ndim == 2 else self.data[..., 0]
        return np.isfinite(d) & (d != self.nodata) if self.nodata is not None else np.isfinite(d)

    def to_pixel(self, x, y):
        """Grid coordinates -> fractional (col, row) with integer values at cell centres."""
        return (np.asarray(x) - self.x0_m) / self.res_m - 0.5, (self.y1_m - np.asarray(y)) / self.res_m - 0.5


def grid_for(xmin: float, ymin: float, xmax: float, ymax: float, res_m: float, fill=NODATA,
             dtype=np.float32, bands: int = 0) -> Raster:
    """An empty raster covering the box, its edges snapped to multiples of res_m."""
    if not res_m > 0:
        raise DataError(f'raster cell size {res_m} m must be positive')
    x0 = np.floor(xmin / res_m) * res_m
    y1 = np.ceil(ymax / res_m) * res_m
    w = max(int(np.ceil((xmax - x0) / res_m)), 1)
    h = max(int(np.ceil((y1 - ymin) / res_m)), 1)
    if w * h > 400_000_000:
        raise DataError(f'a {w}x{h} raster at {res_m} m is too large: choose a coarser cell size')
    shape = (h, w, bands) if bands else (h, w)
    return Raster(np.full(shape, fill, dtype=dtype), float(x0), float(y1), float(res_m), fill)


def dsm_from_points(x, y, z, res_m: float, weights=None, bounds=None, fill_holes_px: int = 1,
                    max_spread_m: float | None = None, z_sigma=None, min_count: int = 1,
                    fill_gaps_m: float = 0.0, canopy: bool = False) -> Raster:
    """Mean height per cell (weighted by `weights`, e.g. points per fused cell); NODATA elsewhere.

    A cell whose points span more than `max_spread_m` in height is rough. A rough cell straddling a
    wall or roof edge has a mean that exists nowhere (half-way up the wall), so it becomes no-data.
    With `canopy` a rough cell whose 3x3 neighbourhood is vegetation instead
    (`rough_surface_cells`: its heights run on without a gap, where a wall splits them into a
    roof and a ground mode) keeps the upper quartile of its heights: the top of the vegetation,
    as a surface model has it. Holes no wider than `fill_holes_px` cells that are surrounded by
    data are filled with the mean of their neighbours (stereo leaves pinholes that a DSM user does
    not want) when those neighbours agree within `max_spread_m`; larger gaps stay no-data, since
    nothing was observed there.
    """
    x, y, z = (np.asarray(v, dtype=np.float64) for v in (x, y, z))
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    x, y, z = x[ok], y[ok], z[ok]
    w = np.ones_like(z) if weights is None else np.asarray(weights, np.float64)[ok]
    if bounds is None:
        if x.size == 0:
            raise DataError('cannot make a DSM from an empty map')
        bounds = (x.min(), y.min(), x.max(), y.max())
    r = grid_for(*bounds, res_m)
    h, wd = r.shape
    col = np.floor((x - r.x0_m) / res_m).astype(np.int64)
    row = np.floor((r.y1_m - y) / res_m).astype(np.int64)
    inside = (col >= 0) & (col < wd) & (row >= 0) & (row < h)
    key = row[inside] * wd + col[inside]
    sw = np.bincount(key, w[inside], minlength=h * wd)
    sz = np.bincount(key, w[inside] * z[inside], minlength=h * wd)
    have = sw > 0
    if min_count > 1:
        have &= np.bincount(key, minlength=h * wd) >= min_count
    out = np.full(h * wd, NODATA, dtype=np.float32)
    out[have] = sz[have] / sw[have]
    vegetation = np.zeros(h * wd, bool)
    if max_spread_m is not None and key.size:
        order = np.lexsort((z[inside], key))
        ks, zs = key[order], z[inside][order]
        starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
        ends = np.r_[starts[1:], ks.size]
        rough = zs[ends - 1] - zs[starts] > max_spread_m
        out[ks[starts[rough]]] = NODATA
        if canopy and rough.any():
            veg = rough_surface_cells(row[inside], col[inside], z[inside], ks[starts[rough]], wd)
            top = starts[rough][veg] + np.floor(0.75 * (ends - starts - 1)[rough][veg]).astype(np.int64)
            sel = have[ks[top]]
            out[ks[top][sel]] = zs[top][sel]
            vegetation[ks[top][sel]] = True
    r.data = out.reshape(h, wd)
    if fill_holes_px > 0:
        r.data = _fill_small_holes(r.data, fill_holes_px, max_spread_m)
    if fill_gaps_m > 0:
        r.data = fill_gaps(r.data, int(fill_gaps_m / res_m), 0.5 if max_spread_m is None else max_spread_m)
    if max_spread_m is not None:
        r.data = clear_step_feet(r.data, 2.0 * max_spread_m, vegetation.reshape(h, wd))
    return r


def rough_surface_cells(row: np.ndarray, col: np.ndarray, z: np.ndarray, cells: np.ndarray, width: int,
                        max_jump_share: float = 1 / 3, min_between_share: float = 0.2,
                        min_points: int = 12) -> np.ndarray:
    """Which of the flat cell indices `cells` (row * width + col) lie on a rough surface, not at a wall.

    A cell across a wall holds two modes, roof and ground, with next to no heights in between
    (stereo drops the disparities at a depth step, and a wall seen from above shows little face); a
    tree crown or shore scrub spreads as much, but its heights run on from the lowest to the top.
    Pools the points (`row`, `col`, `z`) of each cell's 3x3 neighbourhood and calls it rough
    surface when it holds at least `min_points` points, its sorted heights never jump by more than
    `max_jump_share` of their span, and at least `min_between_share` of them lie in the middle third
    of the span. On the simulator's walls (spans of 5 m) that middle third held 4-8 % of the points
    and the largest jump 30-50 % of the span; on the village flight's rough cells (trees, scrub) the
    median jump was 10 % of the span. A crown's rim over open ground is a step, as a wall is.
    """
    cells = np.asarray(cells, np.int64)
    if cells.size == 0:
        return np.zeros(0, bool)
    index = np.full(int(cells.max()) + 1, -1, np.int64)
    index[cells] = np.arange(cells.size)
    owner, heights = [], []
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            # A point at (row, col) lies in the neighbourhood of cell (row - dr, col - dc).
            r, c = row - dr, col - dc
            k = r * width + c
            hit = np.flatnonzero((r >= 0) & (c >= 0) & (c < width) & (k < index.size))
            hit = hit[index[k[hit]] >= 0]
            owner.append(index[k[hit]])
            heights.append(z[hit])
    owner, heights = np.concatenate(owner), np.concatenate(heights)
    order = np.lexsort((heights, owner))
    owner, heights = owner[order], heights[order]
    n = np.bincount(owner, minlength=cells.size)
    first = np.r_[0, np.cumsum(n)[:-1]]
    lo, hi = heights[np.minimum(first, heights.size - 1)], heights[np.maximum(first + n - 1, 0)]
    span = hi - lo
    jump = np.r_[np.diff(heights), 0.0]
    jump[np.r_[owner[1:] != owner[:-1], True]] = 0.0          # no jump from one cell's pool to the next
    largest = np.zeros(cells.size)
    np.maximum.at(largest, owner, jump)
    between = np.bincount(owner, (heights > lo[owner] + span[owner] / 3) & (heights < hi[owner] - span[owner] / 3),
                          minlength=cells.size)
    return (n >= min_points) & (largest <= max_jump_share * span) & (between >= min_between_share * n)


def clear_step_feet(d: np.ndarray, min_step_m: float, keep: np.ndarray | None = None) -> np.ndarray:
    """No-data for cells lower than a neighbour by more than `min_step_m`: the foot of a wall.

    Stereo places a wall up to a pixel or two off (the far ground is drawn into the roof outline),
    so the last ground cell before a wall often has its centre on the wall or roof edge: its height
    is right for where its points are but not for the cell. Cells in the mask `keep` (vegetation,
    whose heights are its own top and whose neighbours differ by nature) are left as they are.
    """
    valid = d != NODATA
    hi = cv2.dilate(np.where(valid, d, -np.inf).astype(np.float32), np.ones((3, 3), np.uint8))
    out = d.copy()
    foot = valid & (hi - d > min_step_m)
    if keep is not None:
        foot &= ~keep
    out[foot] = NODATA
    return out


def _nearest_along_rows(valid: np.ndarray):
    """Column index of the nearest valid cell to the west and to the east of every cell (-1 / w if none)."""
    h, w = valid.shape
    cols = np.broadcast_to(np.arange(w), (h, w))
    west = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
    east = np.minimum.accumulate(np.where(valid, cols, w)[:, ::-1], axis=1)[:, ::-1]
    return west, east


def fill_gaps(d: np.ndarray, max_cells: int, max_step_m: float) -> np.ndarray:
    """Linear interpolation across no-data runs of at most `max_cells` along rows, then columns.

    Only between two observed cells whose heights differ by at most `max_step_m`: a gap with roof
    on one side and ground on the other, or one open to the outside of the map, stays no-data.
    """
    out = d.copy()
    for transpose in (False, True):
        a = out.T if transpose else out
        valid = a != NODATA
        west, east = _nearest_along_rows(valid)
        h, w = a.shape
        gap = east - west
        cand = ~valid & (west >= 0) & (east < w) & (gap - 1 <= max_cells)
        r, c = np.nonzero(cand)
        if r.size == 0:
            continue
        zw, ze = a[r, west[r, c]], a[r, east[r, c]]
        g = gap[r, c]
        ok = np.abs(ze - zw) <= max_step_m
        t = (c - west[r, c]) / g
        a[r[ok], c[ok]] = (zw + (ze - zw) * t)[ok]
    return out


def _fill_small_holes(d: np.ndarray, radius: int, max_spread_m: float | None = None) -> np.ndarray:
    have = (d != NODATA).astype(np.float32)
    vals = np.where(d != NODATA, d, 0).astype(np.float32)
    k = 2 * radius + 1
    s = cv2.boxFilter(vals, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    c = cv2.boxFilter(have, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    # Fill only where most of the neighbourhood is observed: a pinhole, not the edge of the map.
    fill = (d == NODATA) & (c >= 0.6 * k * k)
    if max_spread_m is not None:
        # ... and not a gap along a wall: roof on one side, ground on the other.
        kern = np.ones((k, k), np.uint8)
        hi = cv2.dilate(np.where(d != NODATA, d, -np.inf).astype(np.float32), kern)
        lo = cv2.erode(np.where(d != NODATA, d, np.inf).astype(np.float32), kern)
        with np.errstate(invalid='ignore', over='ignore'):
            fill &= (hi - lo) <= max_spread_m
    out = d.copy()
    out[fill] = s[fill] / c[fill]
    return out


@dataclass
class Keyframe:
    image: np.ndarray         # BGR uint8 (H, W, 3)
    map_T_cam: np.ndarray     # optical camera -> map ENU, 4x4
    camera: PinholeCamera


def orthomosaic(dsm: Raster, keyframes: list[Keyframe], grid_to_map=None, res_m: float | None = None,
                margin_px: float = 2.0, max_off_nadir_deg: float = 45.0, progress=None) -> Raster:
    """Drape keyframes on the DSM; per cell the keyframe seeing it closest to vertical wins.

    Choosing the most vertical view keeps relief displacement and occlusion smallest, and makes
    seams fall between neighbouring keyframes where both see the ground alike. Returns BGRA uint8
    with alpha 0 where no keyframe sees the cell or the DSM has no data. `grid_to_map(X, Y, Z)`
    maps grid coordinates (N,) x3 to map ENU (N, 3); identity when the grid is the map frame.
    `progress(done, total)` (optional) is called before each keyframe and after the last.
    """
    if res_m is not None and abs(res_m - dsm.res_m) > 1e-9:
        dsm = resample(dsm, res_m)
    h, w = dsm.shape
    out = np.zeros((h, w, 4), dtype=np.uint8)
    valid = dsm.valid()
    X, Y = dsm.cell_centers()
    flat = np.flatnonzero(valid)
    if flat.size == 0 or not keyframes:
        return Raster(out, dsm.x0_m, dsm.y1_m, dsm.res_m, None)
    gx, gy, gz = X.ravel()[flat], Y.ravel()[flat], dsm.data.ravel()[flat].astype(np.float64)
    P = np.column_stack([gx, gy, gz]) if grid_to_map is None else np.asarray(grid_to_map(gx, gy, gz))
    best = np.full(flat.size, np.cos(np.radians(max_off_nadir_deg)), dtype=np.float64)
    colour = np.zeros((flat.size, 3), dtype=np.uint8)
    seen = np.zeros(flat.size, dtype=bool)
    for k, kf in enumerate(keyframes):
        if progress is not None:
            progress(k, len(keyframes))
        if kf.image is None or kf.image.ndim != 3:
            raise DataError('orthomosaic keyframes need BGR images')
        cam = kf.camera
        R, C = kf.map_T_cam[:3, :3], kf.map_T_cam[:3, 3]
        # Cheap footprint cull before projecting: ground within the view cone of the image diagonal.
        half_diag = np.hypot(cam.width, cam.height) / (2 * min(cam.fx, cam.fy)) * 1.3
        agl = np.maximum(C[2] - P[:, 2], 0.0)
        reach = agl * half_diag + np.abs(R[:2, 2]).max() * agl * 2.0
        near = (np.abs(P[:, 0] - C[0]) <= reach) & (np.abs(P[:, 1] - C[1]) <= reach)
        idx = np.flatnonzero(near)
        if idx.size == 0:
            continue
        d = P[idx] - C
        dist = np.linalg.norm(d, axis=1)
        cos_v = -d[:, 2] / np.maximum(dist, 1e-9)      # 1 when the ray looks straight down
        cand = cos_v > best[idx]
        idx, d, cos_v = idx[cand], d[cand], cos_v[cand]
        if idx.size == 0:
            continue
        pc = d @ R                                       # map -> camera: R^T d, row-wise
        uv, front = cam.project(pc)
        inside = front & cam.in_image(uv, margin_px)
        idx, uv, cos_v = idx[inside], uv[inside], cos_v[inside]
        if idx.size == 0:
            continue
        colour[idx] = _sample_image(kf.image, uv)
        best[idx] = cos_v
        seen[idx] = True
    if progress is not None:
        progress(len(keyframes), len(keyframes))
    flat_out = out.reshape(-1, 4)
    flat_out[flat[seen], :3] = colour[seen]
    flat_out[flat[seen], 3] = 255
    return Raster(out, dsm.x0_m, dsm.y1_m, dsm.res_m, None)


def _sample_image(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear colours at (N, 2) pixel positions; cv2.remap maps are limited to 32767 columns."""
    width = 4096
    n = uv.shape[0]
    pad = (-n) % width
    mapx = np.pad(uv[:, 0].astype(np.float32), (0, pad)).reshape(-1, width)
    mapy = np.pad(uv[:, 1].astype(np.float32), (0, pad)).reshape(-1, width)
    out = cv2.remap(image, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, image.shape[2])[:n]


def resample(r: Raster, res_m: float) -> Raster:
    """Nearest-neighbour resampling of a single-band raster to another cell size (same extent)."""
    w0, s0, e0, n0 = r.bounds
    out = grid_for(w0, s0, e0, n0, res_m)
    X, Y = out.cell_centers()
    c, rr = r.to_pixel(X, Y)
    ci = np.clip(np.rint(c).astype(int), 0, r.shape[1] - 1)
    ri = np.clip(np.rint(rr).astype(int), 0, r.shape[0] - 1)
    out.data = r.data[ri, ci].astype(np.float32)
    return out


def sample_bilinear(r: Raster, x, y) -> np.ndarray:
    """Bilinear heights at grid points; NaN where any neighbour is no-data or outside."""
    c, rr = r.to_pixel(np.asarray(x, float), np.asarray(y, float))
    h, w = r.shape
    c0, r0 = np.floor(c).astype(int), np.floor(rr).astype(int)
    fc, fr = c - c0, rr - r0
    ok = (c0 >= 0) & (r0 >= 0) & (c0 + 1 < w) & (r0 + 1 < h)
    c0, r0 = np.clip(c0, 0, w - 2), np.clip(r0, 0, h - 2)
    d = r.data.astype(np.float64)
    v00, v01, v10, v11 = d[r0, c0], d[r0, c0 + 1], d[r0 + 1, c0], d[r0 + 1, c0 + 1]
    bad = ~ok
    if r.nodata is not None:
        bad |= (v00 == r.nodata) | (v01 == r.nodata) | (v10 == r.nodata) | (v11 == r.nodata)
    out = (1 - fr) * ((1 - fc) * v00 + fc * v01) + fr * ((1 - fc) * v10 + fc * v11)
    return np.where(bad, np.nan, out)


def push_pull_fill(d: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Every cell of `d` interpolated from the `valid` cells by push-pull (Gortler et al. 1996, "The
    Lumigraph", SIGGRAPH, section 3.4: a pyramid of weighted 2x2 means pushed down to one cell, pulled
    back up by bilinear upsampling where a level has no data of its own).

    Valid cells keep their values; a hole takes a smooth blend of its surroundings, weighted towards
    the nearer ones (each pyramid level halves the resolution). float64 (rows, cols) out.
    """
    v = np.where(valid, d, 0.0).astype(np.float64)
    w = valid.astype(np.float64)
    levels = [(v, w)]
    while min(v.shape) > 1:
        h, wd = v.shape
        ph, pw = h % 2, wd % 2
        v = np.pad(v, ((0, ph), (0, pw)))
        w = np.pad(w, ((0, ph), (0, pw)))
        v = v.reshape(v.shape[0] // 2, 2, v.shape[1] // 2, 2).sum(axis=(1, 3))
        w = w.reshape(w.shape[0] // 2, 2, w.shape[1] // 2, 2).sum(axis=(1, 3))
        levels.append((v, w))
    v, w = levels[-1]
    est = np.where(w > 0, v / np.maximum(w, 1e-12), 0.0)
    for v, w in reversed(levels[:-1]):
        h, wd = v.shape
        up = cv2.resize(est, (2 * est.shape[1], 2 * est.shape[0]), interpolation=cv2.INTER_LINEAR)[:h, :wd]
        a = np.minimum(w, 1.0)     # a cell with data of its own at this level keeps its mean
        est = a * (v / np.maximum(w, 1e-12)) + (1.0 - a) * up
    return np.where(valid, d, est)


def fill_surface(d: np.ndarray, region: np.ndarray, nearest_px: int = 2, nodata: float = NODATA) -> np.ndarray:
    """Heights for the no-data cells of `d` (a DSM or DTM grid) inside the bool mask `region`.

    Cells within `nearest_px` cells of a height take the nearest height (a step such as a wall stays a
    step instead of a ramp), the rest push-pull interpolation (push_pull_fill) from all heights and
    those. Cells outside `region` are left as they are. Returns a float32 copy.
    """
    from scipy.ndimage import distance_transform_edt
    valid = d != nodata
    out = d.astype(np.float32).copy()
    todo = region & ~valid
    if not valid.any() or not todo.any():
        return out
    dist, (ri, ci) = distance_transform_edt(~valid, return_indices=True)
    near = todo & (dist <= nearest_px)
    out[near] = d[ri[near], ci[near]]
    far = todo & ~near
    if far.any():
        seeded = valid | near
        out[far] = push_pull_fill(out, seeded)[far].astype(np.float32)
    return out


def hull_mask(shape: tuple, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Bool (rows, cols) mask of the convex hull of the fractional pixel positions (cols, rows)."""
    out = np.zeros(shape, np.uint8)
    pts = np.column_stack([np.asarray(cols, float), np.asarray(rows, float)])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) >= 3:
        cv2.fillConvexPoly(out, cv2.convexHull(np.round(pts).astype(np.int32)), 1)
    return out.astype(bool)


def cell_max(x, y, values, like: Raster, fill=0) -> np.ndarray:
    """Largest of `values` per cell of the grid of `like` (points outside it are dropped); `fill` where none."""
    x, y, values = np.asarray(x, float), np.asarray(y, float), np.asarray(values)
    col = np.floor((x - like.x0_m) / like.res_m).astype(np.int64)
    row = np.floor((like.y1_m - y) / like.res_m).astype(np.int64)
    h, w = like.shape
    ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    out = np.full(h * w, fill, dtype=values.dtype)
    if ok.any():
        np.maximum.at(out, row[ok] * w + col[ok], values[ok])
    return out.reshape(h, w)


def on_grid(r: Raster, like: Raster) -> np.ndarray:
    """The single-band values of `r` on the grid of `like` (same cell size, edges on the same multiples
    of it, as grid_for makes them); r.nodata (or NODATA) where `r` does not reach."""
    if abs(r.res_m - like.res_m) > 1e-9:
        raise DataError(f'rasters of {r.res_m} m and {like.res_m} m cells are not on one grid')
    nod = NODATA if r.nodata is None else r.nodata
    out = np.full(like.shape, nod, dtype=r.data.dtype)
    dc = int(round((r.x0_m - like.x0_m) / like.res_m))
    dr = int(round((like.y1_m - r.y1_m) / like.res_m))
    h, w = r.shape
    r0, c0 = max(dr, 0), max(dc, 0)
    r1, c1 = min(dr + h, like.shape[0]), min(dc + w, like.shape[1])
    if r1 > r0 and c1 > c0:
        out[r0:r1, c0:c1] = r.data[r0 - dr:r1 - dr, c0 - dc:c1 - dc]
    return out
