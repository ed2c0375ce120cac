"""The DTM (bare ground) of a point cloud, on the grid of its DSM.

Ground points are those core.ground classifies as ASPRS class 2: a progressive morphological filter
(Zhang et al. 2003, IEEE TGRS 41(4), "A progressive morphological filter for removing nonground
measurements from airborne LIDAR data") on the grid of the lowest point per cell, then every point
within `ground_tol_m` of the interpolated ground surface. A DTM cell holding ground points is at their
mean height (measured ground); every other cell inside `region` (buildings, trees, cells stereo did
not measure) is interpolated from the ground cells around it (core.raster.fill_surface: the nearest
ground next to measured ground, push-pull beyond), so the DTM runs under buildings and crowns as the
ground around them does. Works in any planar metric frame (map ENU or a projected CRS).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photogram_ros.core.ground import GROUND, GroundParams, classify_points
from photogram_ros.core.raster import NODATA, Raster, fill_surface


@dataclass
class Dtm:
    raster: Raster               # float32 heights, NODATA outside `region`
    ground: np.ndarray           # bool (rows, cols): cells holding ground points (the rest interpolated)
    ground_points: int           # points classified ground
    notes: list


def dtm_from_points(x, y, z, like: Raster, region: np.ndarray | None = None,
                    params: GroundParams | None = None, weights=None, classes=None) -> Dtm:
    """DTM of the points (x, y, z: (N,) in the grid's frame, m) on the grid of the raster `like`.

    region: bool (rows, cols) of the cells to fill (default: the cells of `like` that hold a value).
    weights: per point (e.g. observations per fused cell) for the cell means; default equal.
    classes: the points' ASPRS classes if already classified (core.ground.classify_points), else classified here.
    Raises DataError (core.ground) for an empty cloud.
    """
    x, y, z = (np.asarray(v, np.float64) for v in (x, y, z))
    w = np.ones_like(z) if weights is None else np.asarray(weights, np.float64)
    notes = []
    if classes is None:
        c = classify_points(x, y, z, params)
        classes, notes = c.classes, c.notes
    g = np.asarray(classes) == GROUND
    h, wd = like.shape
    col = np.floor((x[g] - like.x0_m) / like.res_m).astype(np.int64)
    row = np.floor((like.y1_m - y[g]) / like.res_m).astype(np.int64)
    ok = (col >= 0) & (col < wd) & (row >= 0) & (row < h)
    key = row[ok] * wd + col[ok]
    sw = np.bincount(key, w[g][ok], minlength=h * wd)
    sz = np.bincount(key, w[g][ok] * z[g][ok], minlength=h * wd)
    ground = sw > 0
    d = np.full(h * wd, NODATA, np.float32)
    d[ground] = sz[ground] / sw[ground]
    d, ground = d.reshape(h, wd), ground.reshape(h, wd)
    if region is None:
        region = like.valid()
    d = np.where(region, d, NODATA).astype(np.float32)
    filled = fill_surface(d, region)
    return Dtm(Raster(filled, like.x0_m, like.y1_m, like.res_m, NODATA), ground & region, int(g.sum()), notes)
