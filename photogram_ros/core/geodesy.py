"""Geodesy: WGS84 geodetic <-> ECEF <-> local ENU, and any EPSG CRS through pyproj.

Conventions: latitudes and longitudes in degrees, heights in metres above the WGS84 ellipsoid
(`h_m`), ECEF and ENU in metres. The `map` frame of photogram_ros is the ENU frame tangent to the
ellipsoid at a geodetic origin (REP-105). All functions take scalars or numpy arrays.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from photogram_ros.errors import GeodesyError

WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B_M = WGS84_A_M * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)


def _check_lat_lon(lat_deg, lon_deg) -> None:
    lat = np.asarray(lat_deg, dtype=float)
    lon = np.asarray(lon_deg, dtype=float)
    if not (np.all(np.isfinite(lat)) and np.all(np.isfinite(lon))):
        raise GeodesyError('latitude/longitude must be finite numbers')
    if np.any(np.abs(lat) > 90.0):
        raise GeodesyError(f'latitude out of [-90, 90] degrees: {lat[np.abs(lat) > 90.0].ravel()[:3]}')
    if np.any(np.abs(lon) > 360.0):
        raise GeodesyError(f'longitude out of [-360, 360] degrees: {lon[np.abs(lon) > 360.0].ravel()[:3]}')


def geodetic_to_ecef(lat_deg, lon_deg, h_m):
    """WGS84 geodetic (deg, deg, m above ellipsoid) -> ECEF (m). Returns (x, y, z)."""
    _check_lat_lon(lat_deg, lon_deg)
    lat = np.radians(lat_deg)
    lon = np.radians(lon_deg)
    h = np.asarray(h_m, dtype=float)
    sin_lat = np.sin(lat)
    n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    x = (n + h) * np.cos(lat) * np.cos(lon)
    y = (n + h) * np.cos(lat) * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * sin_lat
    return x, y, z


def ecef_to_geodetic(x_m, y_m, z_m):
    """ECEF (m) -> WGS84 geodetic (lat_deg, lon_deg, h_m), sub-millimetre everywhere near Earth.

    Bowring's initial guess refined by Newton steps on the latitude.
    """
    x = np.asarray(x_m, dtype=float)
    y = np.asarray(y_m, dtype=float)
    z = np.asarray(z_m, dtype=float)
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    theta = np.arctan2(z * WGS84_A_M, p * WGS84_B_M)
    lat = np.arctan2(z + WGS84_EP2 * WGS84_B_M * np.sin(theta) ** 3,
                     p - WGS84_E2 * WGS84_A_M * np.cos(theta) ** 3)
    for _ in range(2):
        sin_lat = np.sin(lat)
        n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin_lat**2)
        h = np.where(np.abs(np.cos(lat)) > 1e-9, p / np.maximum(np.cos(lat), 1e-12) - n,
                     np.abs(z) - WGS84_B_M)
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n / (n + h)))
    sin_lat = np.sin(lat)
    n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    # This form of h stays accurate at every latitude (no division by cos(lat)).
    h = p * np.cos(lat) + z * sin_lat - WGS84_A_M**2 / n
    return np.degrees(lat), np.degrees(lon), h


def ecef_R_enu(lat_deg, lon_deg) -> np.ndarray:
    """Rotation whose columns are the E, N, U axes expressed in ECEF, at one geodetic point."""
    lat = np.radians(float(lat_deg))
    lon = np.radians(float(lon_deg))
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    return np.array([[-so, -sl * co, cl * co],
                     [co, -sl * so, cl * so],
                     [0.0, cl, sl]])


@dataclass(frozen=True)
class LocalFrame:
    """A local ENU frame (the `map` frame) anchored at a geodetic origin on WGS84."""

    lat_deg: float
    lon_deg: float
    h_m: float

    def __post_init__(self):
        _check_lat_lon(self.lat_deg, self.lon_deg)
        if not np.isfinite(self.h_m) or abs(self.h_m) > 1e5:
            raise GeodesyError(f'origin height {self.h_m} m is not a plausible ellipsoidal height')

    @property
    def origin_ecef(self) -> np.ndarray:
        return np.array(geodetic_to_ecef(self.lat_deg, self.lon_deg, self.h_m), dtype=float)

    @property
    def ecef_R_enu(self) -> np.ndarray:
        return ecef_R_enu(self.lat_deg, self.lon_deg)

    def ecef_to_enu(self, ecef_m: np.ndarray) -> np.ndarray:
        """(N, 3) ECEF -> (N, 3) ENU in this frame."""
        d = np.asarray(ecef_m, dtype=float) - self.origin_ecef
        return d @ self.ecef_R_enu

    def enu_to_ecef(self, enu_m: np.ndarray) -> np.ndarray:
        """(N, 3) ENU in this frame -> (N, 3) ECEF."""
        return np.asarray(enu_m, dtype=float) @ self.ecef_R_enu.T + self.origin_ecef

    def geodetic_to_enu(self, lat_deg, lon_deg, h_m) -> np.ndarray:
        """Geodetic arrays -> (N, 3) ENU (or (3,) for scalars)."""
        ecef = np.stack(geodetic_to_ecef(lat_deg, lon_deg, h_m), axis=-1)
        return self.ecef_to_enu(ecef)

    def enu_to_geodetic(self, enu_m: np.ndarray):
        """(N, 3) or (3,) ENU -> (lat_deg, lon_deg, h_m)."""
        ecef = self.enu_to_ecef(enu_m)
        return ecef_to_geodetic(ecef[..., 0], ecef[..., 1], ecef[..., 2])

    def to_dict(self) -> dict:
        return {'lat_deg': self.lat_deg, 'lon_deg': self.lon_deg, 'h_m': self.h_m}

    @classmethod
    def from_dict(cls, d: dict) -> 'LocalFrame':
        return cls(float(d['lat_deg']), float(d['lon_deg']), float(d['h_m']))


def utm_epsg(lat_deg: float, lon_deg: float) -> int:
    """EPSG code of the WGS84 UTM zone that contains the point (326xx north, 327xx south)."""
    _check_lat_lon(lat_deg, lon_deg)
    lon = ((float(lon_deg) + 180.0) % 360.0) - 180.0
    zone = int((lon + 180.0) // 6.0) + 1
    zone = min(max(zone, 1), 60)
    return (32600 if lat_deg >= 0 else 32700) + zone


@lru_cache(maxsize=32)
def _transformer(src: str, dst: str):
    from pyproj import CRS, Transformer
    from pyproj.exceptions import CRSError
    try:
        return Transformer.from_crs(CRS.from_user_input(src), CRS.from_user_input(dst), always_xy=True)
    except CRSError as exc:
        raise GeodesyError(f'cannot use coordinate reference system {src!r} or {dst!r}: {exc}') from exc


def crs_wkt(crs: str) -> str:
    """WKT of a CRS named as 'EPSG:32632', a PROJ string or WKT."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError
    try:
        return CRS.from_user_input(crs).to_wkt()
    except CRSError as exc:
        raise GeodesyError(f'unknown coordinate reference system {crs!r}: {exc}') from exc


def geodetic_to_crs(lat_deg, lon_deg, h_m, crs: str):
    """WGS84 geodetic (ellipsoidal height) -> (x, y, z) in `crs` (easting/northing order).

    The height passes through unchanged unless the target CRS has a vertical component, in
    which case PROJ converts it (which needs a geoid grid; see core.geoid for the one we ship).
    """
    _check_lat_lon(lat_deg, lon_deg)
    t = _transformer('EPSG:4979', crs)
    x, y, z = t.transform(np.asarray(lon_deg, float), np.asarray(lat_deg, float), np.asarray(h_m, float))
    return np.asarray(x), np.asarray(y), np.asarray(z)


def crs_to_geodetic(x, y, z, crs: str):
    """(x, y, z) in `crs` -> WGS84 (lat_deg, lon_deg, h_m)."""
    t = _transformer(crs, 'EPSG:4979')
    lon, lat, h = t.transform(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
    return np.asarray(lat), np.asarray(lon), np.asarray(h)
