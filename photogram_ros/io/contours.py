"""Contour lines of a height raster (the DTM) as a GeoPackage (OGC 12-128r18), written with sqlite3.

The isolines are matplotlib's (marching squares with linear interpolation along cell edges, on the
cell centres); no-data cells are masked, so lines stop at the edge of the raster's data. The
GeoPackage holds one LINESTRING feature per line with its height `elevation_m` (in the raster's
heights: WGS84 ellipsoidal or EGM2008) in the table `contours`, in the horizontal CRS of the
products (its EPSG code as srs_id and its WKT). No GDAL vector driver is needed to write it.
"""

from __future__ import annotations

import sqlite3
import struct
from datetime import datetime, timezone
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


def _gpkg_linestring(xy: np.ndarray, srs_id: int) -> bytes:
    """GeoPackage geometry blob: header ('GP', version 0, flags: envelope [minx, maxx, miny, maxy], little
    endian), then the WKB LINESTRING."""
    env = struct.pack('<4d', xy[:, 0].min(), xy[:, 0].max(), xy[:, 1].min(), xy[:, 1].max())
    head = b'GP' + struct.pack('<BBi', 0, 0b00000011, srs_id) + env
    wkb = struct.pack('<BII', 1, 2, len(xy)) + np.ascontiguousarray(xy, '<f8').tobytes()
    return head + wkb


def write_contours_gpkg(lines: list[tuple[float, np.ndarray]], path: str | Path, crs: str,
                        description: str = '') -> Path:
    """The lines (contour_lines) as the feature table `contours` of a new GeoPackage at `path` (replaced)."""
    from pyproj import CRS
    c = CRS.from_user_input(crs)
    horizontal = c.sub_crs_list[0] if c.is_compound else c.to_2d()
    srs_id = horizontal.to_epsg()
    if srs_id is None:
        raise DataError(f'{crs} has no EPSG code for the GeoPackage\'s spatial reference')
    path = Path(path)
    path.unlink(missing_ok=True)
    con = sqlite3.connect(path)
    try:
        con.execute(f'PRAGMA application_id = {GPKG_APPLICATION_ID}')
        con.execute(f'PRAGMA user_version = {GPKG_USER_VERSION}')
        con.executescript('''
            CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER NOT NULL PRIMARY KEY,
                organization TEXT NOT NULL, organization_coordsys_id INTEGER NOT NULL, definition TEXT NOT NULL,
                description TEXT);
            CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL,
                identifier TEXT UNIQUE, description TEXT DEFAULT '', last_change DATETIME NOT NULL,
                min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER,
                CONSTRAINT fk_gc_r_srs_id FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys(srs_id));
            CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL,
                geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL, m TINYINT NOT NULL,
                CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name));
            CREATE TABLE contours (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, geom LINESTRING,
                elevation_m DOUBLE NOT NULL);
        ''')
        con.executemany('INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, ?, ?, ?, ?)', [
            ('Undefined cartesian SRS', -1, 'NONE', -1, 'undefined', 'undefined cartesian coordinate reference system'),
            ('Undefined geographic SRS', 0, 'NONE', 0, 'undefined', 'undefined geographic coordinate reference system'),
            ('WGS 84 geodetic', 4326, 'EPSG', 4326, CRS.from_epsg(4326).to_wkt('WKT1_GDAL'),
             'longitude/latitude coordinates in decimal degrees on the WGS 84 spheroid'),
        ] + ([(horizontal.name, srs_id, 'EPSG', srs_id, horizontal.to_wkt('WKT1_GDAL'), '')]
             if srs_id != 4326 else []))
        allxy = np.concatenate([xy for _, xy in lines]) if lines else np.zeros((1, 2))
        con.execute('INSERT INTO gpkg_contents VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)',
                    ('contours', 'features', 'contours', description,
                     datetime.now(timezone.utc).strftime('%Y-%m-%dT%H:%M:%S.000Z'),
                     float(allxy[:, 0].min()), float(allxy[:, 1].min()), float(allxy[:, 0].max()),
                     float(allxy[:, 1].max()), srs_id))
        con.execute('INSERT INTO gpkg_geometry_columns VALUES (?, ?, ?, ?, ?, ?)',
                    ('contours', 'geom', 'LINESTRING', srs_id, 0, 0))
        con.executemany('INSERT INTO contours (geom, elevation_m) VALUES (?, ?)',
                        [(_gpkg_linestring(xy, srs_id), h) for h, xy in lines])
        con.commit()
    finally:
        con.close()
    return path


def read_contours_gpkg(path: str | Path) -> tuple[int, list[tuple[float, np.ndarray]]]:
    """(srs_id, [(elevation_m, (N, 2) xy)]) of a GeoPackage written by write_contours_gpkg."""
    con = sqlite3.connect(Path(path))
    try:
        srs_id = con.execute("SELECT srs_id FROM gpkg_geometry_columns WHERE table_name = 'contours'").fetchone()[0]
        out = []
        for blob, h in con.execute('SELECT geom, elevation_m FROM contours ORDER BY fid'):
            flags = blob[3]
            env = {0: 0, 1: 32, 2: 48, 3: 48, 4: 64}[(flags >> 1) & 7]
            wkb = blob[8 + env:]
            n = struct.unpack('<I', wkb[5:9])[0]
            out.append((float(h), np.frombuffer(wkb[9:9 + 16 * n], '<f8').reshape(n, 2)))
    finally:
        con.close()
    return srs_id, out
