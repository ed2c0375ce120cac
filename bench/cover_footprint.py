"""The DSM against the cameras' footprint, read from dsm.tif alone (bench/real_surveys.py adds these figures to
each run's row): the convex hull of the camera centres on the DSM's grid extended to hold all of it, so a raster
that covers a patch of the block reads as that patch (dsm_completeness's hull is clipped to the raster)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from photogram_ros.core.geodesy import geodetic_to_crs


def dsm_footprint_shares(dsm_path: str | Path, lat_deg, lon_deg) -> dict:
    """The DSM against the cameras' footprint, taken as the convex hull of the camera centres (lat/lon) on the
    DSM's grid extended to hold all of it (cells the raster does not reach count as empty, unlike
    dsm_completeness, whose hull is clipped to the raster): shares of the hull's cells holding a height, measured
    by stereo (band 2 >= 1: any pairs) and by one pair only (band 2 = 1)."""
    import cv2
    import rasterio
    with rasterio.open(dsm_path) as ds:
        z = ds.read(1, masked=True).astype(float).filled(np.nan)
        pairs = ds.read(2) if ds.count > 1 else None
        tr, crs = ds.transform, ds.crs.to_string()
    e, n, _ = geodetic_to_crs(np.asarray(lat_deg, float), np.asarray(lon_deg, float), np.zeros(len(lat_deg)), crs)
    cols, rows = ~tr @ (np.asarray(e, float), np.asarray(n, float))
    c0, r0 = int(np.floor(min(cols.min(), 0))), int(np.floor(min(rows.min(), 0)))
    w = int(np.ceil(max(cols.max() + 1, z.shape[1]))) - c0
    h = int(np.ceil(max(rows.max() + 1, z.shape[0]))) - r0
    hull = cv2.convexHull(np.column_stack([cols - c0, rows - r0]).astype(np.float32))
    mask = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull.reshape(-1, 2)).astype(np.int32), 1)
    inside = mask[-r0:-r0 + z.shape[0], -c0:-c0 + z.shape[1]].astype(bool)
    cells = int(mask.sum())
    valid = np.isfinite(z)
    measured = valid if pairs is None else valid & (pairs >= 1)
    one = np.zeros_like(valid) if pairs is None else valid & (pairs == 1)
    share = (lambda m: float(m[inside].sum() / cells)) if cells else (lambda m: float('nan'))
    return {'footprint_hull_cells': cells, 'footprint_hull_in_raster': float(inside.sum() / cells) if cells else 0.0,
            'dsm_footprint_valid_share': share(valid), 'dsm_footprint_measured_share': share(measured),
            'dsm_footprint_one_pair_share': share(one)}
