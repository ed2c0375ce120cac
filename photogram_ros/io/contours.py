"""Contour lines of a height raster (the DTM) as a GeoPackage (OGC 12-128), written by GDAL through pyogrio.

The isolines are matplotlib's (marching squares with linear interpolation along cell edges, on the
cell centres); no-data cells are masked, so lines stop at the edge of the raster's data. The
GeoPackage holds one LINESTRING feature per line with its height `elevation_m` (in the raster's
heights: WGS84 ellipsoidal or EGM2008) in the layer `contours`, in the horizontal CRS of the
products (its EPSG code as srs_id).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from photogram_ros.core.raster import Raster
from photogram_ros.errors import ConfigError, DataError

GPKG_APPLICATION_ID = 0x47504B47     # 'GPKG'
GPKG_USER_VERSION = 10200            # GeoPackage 1.2


def contour_lines(r: Raster, interval_m: float, min_length_cells: float = 10.0) -> list[tuple[float, np.ndarray]]:
    """[(height, (N, 2) x, y)] of the isolines of `r` at multiples of `interval_m` (m); lines shorter than
    `min_length_cells` cells (the rings of single bumps, noise) are left out."""
    if not interval_m > 0:
        raise ConfigError(f'the contour interval must be positive, not {interval_m} m')
    valid = r.valid()
    if valid.sum() < 4:
        return []
    z = r.data.astype(np.float64)
    lo, hi = float(z[valid].min()), float(z[valid].max())
    levels = np.arange(np.ceil(lo / interval_m), np.floor(hi / interval_m) + 1) * interval_m
    if levels.size == 0:
        return []
    if levels.size > 5000:
        raise ConfigError(f'{levels.size} contour levels at {interval_m} m over {hi - lo:.1f} m of relief: '
                          'choose a larger interval')
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    X, Y = r.cell_centers()
    fig, ax = plt.subplots()
    try:
        cs = ax.contour(X, Y, np.ma.masked_array(z, ~valid), levels=levels)
        out = []
        for level, path in zip(cs.levels, cs.get_paths()):
            for line in path.to_polygons(closed_only=False):
                line = np.asarray(line, float)
                if len(line) >= 2 and np.hypot(*np.diff(line, axis=0).T).sum() >= min_length_cells * r.res_m:
                    out.append((float(level), line))
    finally:
        plt.close(fig)
    return out


def _wkb_linestring(xy: np.ndarray) -> bytes:
    """ISO WKB LINESTRING, little endian (what GDAL's vector drivers take)."""
    return struct.pack('<BII', 1, 2, len(xy)) + np.ascontiguousarray(xy, '<f8').tobytes()


def write_contours_gpkg(lines: list[tuple[float, np.ndarray]], path: str | Path, crs: str,
                        description: str = '') -> Path:
    """The lines (contour_lines) as the layer `contours` (LINESTRING, field elevation_m) of a new GeoPackage at
    `path` (replaced), written by GDAL's GPKG driver through pyogrio."""
    from pyogrio.raw import write
    from pyproj import CRS
    c = CRS.from_user_input(crs)
    horizontal = c.sub_crs_list[0] if c.is_compound else c.to_2d()
    srs_id = horizontal.to_epsg()
    if srs_id is None:
        raise DataError(f'{crs} has no EPSG code for the GeoPackage\'s spatial reference')
    path = Path(path)
    path.unlink(missing_ok=True)
    geometry = np.array([_wkb_linestring(xy) for _, xy in lines], dtype=object)
    elevation = np.array([h for h, _ in lines], dtype=np.float64)
    write(str(path), geometry, [elevation], ['elevation_m'], layer='contours', driver='GPKG',
          geometry_type='LineString', crs=f'EPSG:{srs_id}',
          layer_options={'DESCRIPTION': description} if description else None)
    return path


def read_contours_gpkg(path: str | Path) -> tuple[int, list[tuple[float, np.ndarray]]]:
    """(srs_id, [(elevation_m, (N, 2) xy)]) of the `contours` layer of a GeoPackage, read through pyogrio."""
    from pyogrio.raw import read
    from pyproj import CRS
    meta, _, geometry, fields = read(str(Path(path)), layer='contours')
    names = list(meta['fields'])
    heights = fields[names.index('elevation_m')]
    out = []
    for wkb, h in zip(geometry, heights):
        n = struct.unpack('<I', wkb[5:9])[0]
        out.append((float(h), np.frombuffer(wkb[9:9 + 16 * n], '<f8').reshape(n, 2)))
    return CRS.from_user_input(meta['crs']).to_epsg(), out
