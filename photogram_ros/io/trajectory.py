"""Adjusted camera poses as a CSV table: the image, its centre in a CRS and in WGS84, omega-phi-kappa.

One writer for the two tables of this kind: `photogram-ros triangulate`'s poses.csv
(`POSES_COLUMNS`) and the flight report's trajectory.csv (`TRAJECTORY_COLUMNS`). Each keeps the
column names and decimals it has always had (users' scripts read them); the values are the same:
- easting, northing: the camera centre in `crs`, from its WGS84 position;
- height: above the WGS84 ellipsoid (`h_m`, `h_ellipsoid_m`); poses.csv's `z` in the datum asked (`heights`:
  the same number as `h_m`, or above the EGM2008 geoid, core/geoid.py, at the camera's latitude and longitude)
  and its `crs` column the CRS with those heights (io/crs_tags.crs_with_heights: EPSG:<code>+3855);
- omega, phi, kappa (degrees): the camera rotation in the map ENU frame (within a fraction of a
  degree of the projected frame over a few km; grid convergence is not applied).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from photogram_ros.core.geodesy import LocalFrame, geodetic_to_crs
from photogram_ros.core.rotations import opk_from_map_R_cam


@dataclass(frozen=True)
class Column:
    header: str
    value: str          # 'image', 'stamp_ns', 'crs', or a numeric value of pose_table()
    fmt: str = ''       # format spec of a numeric value ('.4f')

POSES_COLUMNS = (Column('image', 'image'), Column('x', 'easting_m', '.4f'), Column('y', 'northing_m', '.4f'),
                 Column('z', 'height_m', '.4f'), Column('crs', 'crs'), Column('lat_deg', 'lat_deg', '.9f'),
                 Column('lon_deg', 'lon_deg', '.9f'), Column('h_m', 'h_m', '.4f'),
                 Column('omega_deg', 'omega_deg', '.5f'), Column('phi_deg', 'phi_deg', '.5f'),
                 Column('kappa_deg', 'kappa_deg', '.5f'))

TRAJECTORY_COLUMNS = (Column('image', 'image'), Column('stamp_ns', 'stamp_ns'),
                      Column('easting_m', 'easting_m', '.4f'), Column('northing_m', 'northing_m', '.4f'),
                      Column('h_ellipsoid_m', 'h_m', '.4f'), Column('lat_deg', 'lat_deg', '.9f'),
                      Column('lon_deg', 'lon_deg', '.9f'), Column('omega_deg', 'omega_deg', '.4f'),
                      Column('phi_deg', 'phi_deg', '.4f'), Column('kappa_deg', 'kappa_deg', '.4f'))


def pose_table(map_T_cams: np.ndarray, origin: LocalFrame, crs: str, heights: str = 'ellipsoidal'
               ) -> dict[str, np.ndarray]:
    """(N, 4, 4) map_T_cam -> {value name: (N,) array} for the numeric VALUES, plus 'centres_map' (N, 3).
    'h_m' is ellipsoidal, 'height_m' in the datum `heights` ('ellipsoidal' or 'orthometric': EGM2008)."""
    from photogram_ros.core import geoid
    T = np.asarray(map_T_cams, float).reshape(-1, 4, 4)
    C = T[:, :3, 3]
    lat, lon, h = (np.asarray(v, float).reshape(-1) for v in origin.enu_to_geodetic(C))
    e, n, _ = (np.asarray(v, float).reshape(-1) for v in geodetic_to_crs(lat, lon, h, crs))
    opk = np.array([np.degrees(opk_from_map_R_cam(R)) for R in T[:, :3, :3]]).reshape(-1, 3)
    height = np.asarray(geoid.ellipsoid_to_msl_m(lat, lon, h), float).reshape(-1) if heights == 'orthometric' else h
    return {'easting_m': e, 'northing_m': n, 'h_m': h, 'height_m': height, 'lat_deg': lat, 'lon_deg': lon,
            'omega_deg': opk[:, 0], 'phi_deg': opk[:, 1], 'kappa_deg': opk[:, 2], 'centres_map': C}


def write_trajectory_csv(path: str | Path, columns: tuple[Column, ...], images: list[str],
                         map_T_cams: np.ndarray, origin: LocalFrame, crs: str,
                         stamps_ns: list[int] | None = None, heights: str = 'ellipsoidal') -> dict[str, np.ndarray]:
    """Write one row per pose with `columns` (POSES_COLUMNS or TRAJECTORY_COLUMNS); returns pose_table().

    `images`: the image name of each pose; `stamps_ns`: needed only by a 'stamp_ns' column; `heights`: the datum
    of a 'height_m' column (poses.csv's z), and the 'crs' column the CRS with those heights.
    """
    from photogram_ros.io.crs_tags import crs_with_heights
    with_heights = crs_with_heights(crs, heights)
    table = pose_table(map_T_cams, origin, crs, heights)
    text = {'image': [str(s) for s in images], 'crs': [with_heights] * len(images)}
    if stamps_ns is not None:
        text['stamp_ns'] = [str(int(s)) for s in stamps_ns]
    elif any(c.value == 'stamp_ns' for c in columns):
        raise ValueError('a stamp_ns column needs stamps_ns')
    with open(path, 'w', newline='') as fh:
        w = csv.writer(fh, lineterminator='\n')
        w.writerow([c.header for c in columns])
        for k in range(len(images)):
            w.writerow([text[c.value][k] if c.value in text else format(float(table[c.value][k]), c.fmt)
                        for c in columns])
    return table
