"""Synthetic terrain: a DEM with real relief and a colour texture with detail below the GSD.

Grids are stored with row index increasing northward: `dem[j, i]` is the ground height (m, in the
`map` ENU frame) at x = x0_m + i * res_m, y = y0_m + j * res_m. The texture uses the same
convention at its own (finer) spacing, so one bilinear lookup serves both.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Grid:
    """A north-up-by-rows raster sampled at nodes x0 + i*res, y0 + j*res."""

    data: np.ndarray
    x0_m: float
    y0_m: float
    res_m: float

    @property
    def shape(self):
        return self.data.shape[:2]

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the grid nodes."""
        h, w = self.shape
        return (self.x0_m, self.x0_m + (w - 1) * self.res_m, self.y0_m, self.y0_m + (h - 1) * self.res_m)

    def to_pixel(self, x_m, y_m):
        return (np.asarray(x_m) - self.x0_m) / self.res_m, (np.asarray(y_m) - self.y0_m) / self.res_m

    def sample(self, x_m, y_m) -> np.ndarray:
        """Bilinear samples at arbitrary points (float64, exact: no fixed-point remap)."""
        u, v = self.to_pixel(np.asarray(x_m, float), np.asarray(y_m, float))
        h, w = self.shape
        u = np.clip(u, 0, w - 1.000001)
        v = np.clip(v, 0, h - 1.000001)
        i, j = np.floor(u).astype(int), np.floor(v).astype(int)
        fu, fv = u - i, v - j
        d = self.data.astype(np.float64) if self.data.dtype != np.float64 else self.data
        if d.ndim == 3:
            fu, fv = fu[..., None], fv[..., None]
        return ((1 - fu) * (1 - fv) * d[j, i] + fu * (1 - fv) * d[j, i + 1]
                + (1 - fu) * fv * d[j + 1, i] + fu * fv * d[j + 1, i + 1])


@dataclass
class Terrain:
    dem: Grid          # float32 heights, m
    texture: Grid      # uint8 BGR albedo with shading baked in
    buildings: list    # [(xmin, xmax, ymin, ymax, roof_height_m)]

    def height_at(self, x_m, y_m) -> np.ndarray:
        return self.dem.sample(x_m, y_m)


def _smooth_noise(rng: np.random.Generator, shape, cell_px: float) -> np.ndarray:
    """Band-limited noise in [-1, 1] with features about `cell_px` pixels across."""
    h, w = shape
    ch, cw = max(int(np.ceil(h / cell_px)) + 3, 4), max(int(np.ceil(w / cell_px)) + 3, 4)
    coarse = rng.standard_normal((ch, cw)).astype(np.float32)
    big = cv2.resize(coarse, (int(cw * cell_px), int(ch * cell_px)), interpolation=cv2.INTER_CUBIC)
    out = big[:h, :w]
    return np.clip(out / 2.0, -1.0, 1.0)


def make_dem(rng: np.random.Generator, x0_m: float, y0_m: float, width_m: float, height_m: float,
             res_m: float, relief_m: float = 12.0, n_buildings: int = 6,
             keep_clear: list | None = None) -> tuple[Grid, list]:
    """Hills, a regional slope, an embankment and flat-roofed buildings with vertical walls."""
    w = int(np.ceil(width_m / res_m)) + 1
    h = int(np.ceil(height_m / res_m)) + 1
    xs = x0_m + np.arange(w) * res_m
    ys = y0_m + np.arange(h) * res_m
    X, Y = np.meshgrid(xs, ys)
    cx, cy = x0_m + width_m / 2, y0_m + height_m / 2
    z = np.zeros((h, w), dtype=np.float64)
    # Regional slope of a few percent.
    ang = rng.uniform(0, 2 * np.pi)
    z += 0.04 * ((X - cx) * np.cos(ang) + (Y - cy) * np.sin(ang))
    # Hills and hollows.
    for _ in range(7):
        hx, hy = rng.uniform(x0_m, x0_m + width_m), rng.uniform(y0_m, y0_m + height_m)
        s = rng.uniform(15, 45)
        a = rng.uniform(-0.5, 1.0) * relief_m * 0.6
        z += a * np.exp(-((X - hx) ** 2 + (Y - hy) ** 2) / (2 * s * s))
    # Gentle undulation at the 10-m scale.
    z += 0.6 * _smooth_noise(rng, (h, w), 10.0 / res_m)
    # An embankment (road or dyke) across the area: trapezoid 2.5 m high, 5 m crest, 1:1.5 sides.
    e_ang = rng.uniform(0, np.pi)
    d = np.abs((X - cx) * np.sin(e_ang) - (Y - cy) * np.cos(e_ang) - rng.uniform(-0.25, 0.25) * width_m)
    z += np.clip((2.5 - np.maximum(d - 2.5, 0) / 1.5), 0, 2.5)
    buildings = []
    clear = keep_clear or []
    tries = 0
    while len(buildings) < n_buildings and tries < 200:
        tries += 1
        bw, bh = rng.uniform(6, 14), rng.uniform(6, 14)
        bx = rng.uniform(x0_m + 10, x0_m + width_m - 10 - bw)
        by = rng.uniform(y0_m + 10, y0_m + height_m - 10 - bh)
        box = (bx, bx + bw, by, by + bh)
        if any(not (box[1] + 4 < b[0] or b[1] + 4 < box[0] or box[3] + 4 < b[2] or b[3] + 4 < box[2])
               for b in buildings):
            continue
        if any(box[0] - 6 < px < box[1] + 6 and box[2] - 6 < py < box[3] + 6 for px, py in clear):
            continue
        inside = (X >= box[0]) & (X <= box[1]) & (Y >= box[2]) & (Y <= box[3])
        roof = float(z[inside].max()) + rng.uniform(4, 10)
        z[inside] = roof
        buildings.append(box + (roof,))
    return Grid(z.astype(np.float32), x0_m, y0_m, res_m), buildings


def make_texture(rng: np.random.Generator, dem: Grid, buildings: list, res_m: float) -> Grid:
    """Fields, tracks, roofs and fine clutter, shaded by the DEM's relief."""
    xmin, xmax, ymin, ymax = dem.extent_m
    w = int(np.floor((xmax - xmin) / res_m)) + 1
    h = int(np.floor((ymax - ymin) / res_m)) + 1
    px_per_m = 1.0 / res_m
    # Land cover classes from low-frequency noise.
    cover = _smooth_noise(rng, (h, w), 40 * px_per_m) + 0.4 * _smooth_noise(rng, (h, w), 12 * px_per_m)
    palette = np.array([[60, 120, 70], [90, 150, 110], [70, 110, 150], [110, 150, 170],
                        [50, 90, 60]], dtype=np.float32)  # BGR: grass, meadow, soil, dry field, scrub
    cls = np.clip(((cover + 1.2) / 2.4 * len(palette)).astype(np.int32), 0, len(palette) - 1)
    img = palette[cls]
    del cover
    # Detail at every scale from 4 m down to two texels: what features and stereo lock onto.
    detail = np.zeros((h, w), dtype=np.float32)
    for scale_m, amp in ((4.0, 18), (1.2, 16), (0.4, 14), (0.15, 12), (2.5 * res_m, 10)):
        detail += amp * _smooth_noise(rng, (h, w), max(scale_m * px_per_m, 2.0))
    # Field rows in the soil and dry-field classes.
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    rows = np.sin((xx * np.cos(0.3) + yy * np.sin(0.3)) * res_m * 2 * np.pi / 1.5)
    detail += np.where((cls == 2) | (cls == 3), 14 * rows, 0)
    del rows, xx, yy, cls
    img += detail[..., None]
    del detail
    # Scattered bushes and stones, 0.2-0.8 m across: crisp corners at the GSD scale.
    n_blobs = int((xmax - xmin) * (ymax - ymin) / 12)
    for _ in range(n_blobs):
        u, v = rng.uniform(0, w), rng.uniform(0, h)
        r = rng.uniform(0.1, 0.4) * px_per_m
        col = rng.choice([[30, 60, 35], [170, 180, 185], [40, 50, 60], [200, 210, 215]])
        cv2.circle(img, (int(u), int(v)), max(int(r), 1), tuple(float(c) for c in col), -1)
    # Unpaved tracks.
    for _ in range(2):
        p0 = (rng.uniform(0, w), 0.0)
        p1 = (rng.uniform(0, w), float(h))
        cv2.line(img, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])), (120, 140, 150),
                 int(3.0 * px_per_m))
    # Roofs: plain colour, a ridge and some tiles.
    for (bx0, bx1, by0, by1, _roof) in buildings:
        u0, u1 = int((bx0 - xmin) * px_per_m), int((bx1 - xmin) * px_per_m)
        v0, v1 = int((by0 - ymin) * px_per_m), int((by1 - ymin) * px_per_m)
        col = np.array(rng.choice([[50, 60, 150], [120, 120, 125], [60, 80, 110]]), dtype=np.float32)
        patch = col + 10 * _smooth_noise(rng, (v1 - v0, u1 - u0), 0.3 * px_per_m)[..., None]
        img[v0:v1, u0:u1] = patch
        cv2.line(img, (u0, (v0 + v1) // 2), (u1, (v0 + v1) // 2), (200, 200, 200), max(int(0.2 * px_per_m), 1))
        cv2.rectangle(img, (u0, v0), (u1 - 1, v1 - 1), (30, 30, 30), max(int(0.25 * px_per_m), 1))
    # Relief shading (sun from the north-west, 45 degrees up) so hills read as hills.
    gy, gx = np.gradient(dem.data.astype(np.float64), dem.res_m)
    nrm = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    sun = np.array([-0.5, 0.5, 0.7071])
    shade = (0.55 + 0.45 * np.clip(nrm @ sun / 0.7071, 0, 1.4)).astype(np.float32)
    shade = cv2.resize(shade, (w, h), interpolation=cv2.INTER_LINEAR)
    img *= shade[..., None]
    tex = np.clip(img, 0, 255).astype(np.uint8)
    return Grid(tex, xmin, ymin, res_m)
