"""Survey products from a map folder: LAS 1.4 / LAZ, PLY, DSM, DTM and orthomosaic GeoTIFFs, in any CRS.

Map ENU coordinates go to WGS84 through the map's LocalFrame, then to the requested CRS with pyproj
(easting, northing). Heights are WGS84 ellipsoidal by default; `heights='orthometric'` gives
heights above the EGM2008 geoid instead. Only the horizontal part of the CRS is taken from PROJ,
so a datum shift between WGS84 and e.g. CH1903+ never changes the height reference silently. GIS tools
name the products' CRS by its EPSG code (io/crs_tags.py): the GeoTIFFs hold the 2D CRS in their GeoKeys
and the DSM and DTM their vertical datum in their metadata (HEIGHTS, VERTICAL_DATUM, VERTICAL_CRS); the
LAS WKT is the projected CRS, compound with EGM2008 height (e.g. EPSG:32632+3855) for orthometric heights.

LAS/LAZ points are classified (core.ground: 2 ground, 6 building, 1 the rest) with return 1 of 1.
Rasters are Cloud-Optimized GeoTIFFs (GDAL's COG driver: tiled, deflate, overviews) whose CRS and
vertical datum are in the file itself (write_geotiff): a .tif copied alone keeps them.

The DSM holds the cells stereo measured and, inside what the photos saw (the camera centres' hull),
heights interpolated where stereo measured none (surface_in_crs); its band 2 gives the stereo pairs
that measured each cell, 0 where interpolated. The DTM (core.dtm) is the ground class of the cloud on
the DSM's grid, interpolated under buildings and vegetation; contours of it on request (io/contours.py).

Rasters are built in the output CRS's own grid (north-up in that CRS), so GIS tools need no
reprojection: the DSM from the fused cells' CRS coordinates, the orthomosaic by mapping each of
its cells back to map ENU and draping the keyframes (core.raster.orthomosaic).
"""

from __future__ import annotations

import errno
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from photogram_ros.core import geoid
from photogram_ros.core.gsd import AUTO, dsm_lengths_for_cell
from photogram_ros.core.fusion import Fusion, FusionConfig
from photogram_ros.core.ground import GroundParams, classify_points
from photogram_ros.core.geodesy import LocalFrame, crs_to_geodetic, geodetic_to_crs
from photogram_ros.core.dtm import dtm_from_points
from photogram_ros.core.raster import (NODATA, Keyframe, Raster, cell_max, dsm_from_points, fill_surface, hull_mask,
                                       orthomosaic)
from photogram_ros.errors import ConfigError, DataError, GeodesyError, StorageError
from photogram_ros.io.crs_tags import describe_las, geotiff_georef
from photogram_ros.io.map_store import MapStore, as_map_store
from photogram_ros.io.progress import Progress, Steps
from photogram_ros.params import param, validate

HEIGHTS = ('ellipsoidal', 'orthometric')


@dataclass
class GeoCloud:
    """Fused map cells in an output CRS."""
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    rgb: np.ndarray           # (N, 3) uint8 R, G, B
    count: np.ndarray         # points fused per cell
    confidence: np.ndarray
    crs: str
    heights: str
    sigma_z: np.ndarray | None = None   # height spread of the points fused in each cell, m
    pairs: np.ndarray | None = None     # stereo pairs that measured each cell
    classes: np.ndarray | None = None   # ASPRS class per point (core.ground); None: not classified (1)


# --- coordinates -----------------------------------------------------------------------------------


def enu_to_crs(origin: LocalFrame, enu: np.ndarray, crs: str, heights: str = 'ellipsoidal'):
    """(N, 3) map ENU -> easting, northing, height in `crs` (heights per `heights`)."""
    if heights not in HEIGHTS:
        raise GeodesyError(f'heights must be one of {HEIGHTS}, not {heights!r}')
    lat, lon, h = origin.enu_to_geodetic(np.asarray(enu, float))
    e, n, _ = geodetic_to_crs(lat, lon, h, crs)
    if heights == 'orthometric':
        h = geoid.ellipsoid_to_msl_m(lat, lon, h)
    return np.asarray(e, float), np.asarray(n, float), np.asarray(h, float)


def crs_to_enu(origin: LocalFrame, e, n, h_ellipsoidal, crs: str) -> np.ndarray:
    """Easting, northing in `crs` with WGS84 ellipsoidal heights -> (N, 3) map ENU."""
    lat, lon, _ = crs_to_geodetic(e, n, np.zeros_like(np.asarray(e, float)), crs)
    return origin.geodetic_to_enu(lat, lon, np.asarray(h_ellipsoidal, float))


EGM2008_HEIGHT = 'EPSG:3855'


def product_crs(crs: str, heights: str):
    """(pyproj CRS with the products' vertical reference, note or '') for a projected `crs`.

    orthometric: compound with EGM2008 height; ellipsoidal: the CRS promoted to 3D (ellipsoidal
    height axis) when its datum is WGS84, else the 2D CRS and a note saying why.
    """
    from pyproj import CRS
    from pyproj.crs import CompoundCRS
    if heights not in HEIGHTS:
        raise GeodesyError(f'heights must be one of {HEIGHTS}, not {heights!r}')
    c = CRS.from_user_input(crs)
    horizontal = c.sub_crs_list[0] if c.is_compound else c.to_2d()
    if heights == 'orthometric':
        vertical = CRS.from_user_input(EGM2008_HEIGHT)
        return CompoundCRS(f'{horizontal.name} + {vertical.name}', [horizontal, vertical]), ''
    if 'World Geodetic System 1984' in (horizontal.datum.name if horizontal.datum else ''):
        return horizontal.to_3d(), ''
    return horizontal, (f'heights are WGS84 ellipsoidal, which a CRS on the {horizontal.datum.name} datum cannot '
                        'state: the products\' CRS is 2D (--heights orthometric gives a compound CRS with EGM2008)')


def _check_projected(crs: str) -> None:
    from pyproj import CRS
    c = CRS.from_user_input(crs)
    if not c.is_projected:
        raise GeodesyError(f'{crs} is not a projected CRS: rasters and clouds need metric easting/northing '
                           '(e.g. the UTM zone EPSG:326xx, or a national grid such as EPSG:2056)')


# --- whole files ----------------------------------------------------------------------------------


class ProductsIncomplete(StorageError):
    """Some products could not be written (a full disk): the message names each path and why; `result`
    (ExportResult) holds the products that were written whole, and export.json says which failed."""

    def __init__(self, message: str, errno_: int | None, result: 'ExportResult'):
        super().__init__(message, errno_)
        self.result = result


def part_path(path: Path) -> Path:
    """The temporary name a product is written under until it is whole: '.cloud.part.laz' beside
    'cloud.laz' (the suffix kept: writers choose their format by it)."""
    return path.with_name(f'.{path.stem}.part{path.suffix}')


def write_whole(path: str | Path, write) -> Path:
    """`write(tmp)` writes the file under part_path(path); once it returned, the file is flushed to disk and
    renamed to `path`. A failure (a full disk) removes the partial file and raises a StorageError naming
    `path`: a product is on disk whole under its final name, or not at all."""
    import os
    path = Path(path)
    tmp = part_path(path)
    try:
        write(tmp)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        Path(str(tmp) + '.aux.xml').unlink(missing_ok=True)
        cause = _disk_full(exc) or exc
        why = 'the disk is full' if cause.errno == errno.ENOSPC else (cause.strerror or str(cause))
        raise StorageError(f'{path}: not written: {why}', cause.errno) from exc
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _disk_full(exc: BaseException) -> OSError | None:
    """The OSError behind a writer's failure (rasterio and laspy wrap the system's error), else None."""
    seen = exc
    while seen is not None:
        if 'No space left on device' in str(seen):
            return OSError(errno.ENOSPC, 'No space left on device')
        if isinstance(seen, OSError) and seen.errno is not None:
            return seen
        seen = seen.__cause__ or seen.__context__
    return None


# --- reading a map folder --------------------------------------------------------------------------


def open_map(map_dir: str | Path | MapStore) -> tuple[MapStore, Fusion]:
    """The map folder (or the open MapStore) and a fusion over all its tiles, for reading."""
    store = as_map_store(map_dir)
    return store, Fusion(FusionConfig(store.cell_m, store.tile_cells, max_tiles_in_memory=10**6), store)


def map_cloud(fusion: Fusion, origin: LocalFrame, crs: str, heights: str = 'ellipsoidal',
              min_pairs: int = 1) -> GeoCloud:
    """Fused cells in `crs`; `min_pairs` keeps only cells that that many stereo pairs agreed on."""
    p = fusion.points()
    if min_pairs > 1:
        keep = p['n_pairs'] >= min_pairs
        p = {k: v[keep] for k, v in p.items()}
    if p['x'].size == 0:
        raise DataError('the map holds no fused points yet' if min_pairs <= 1 else
                        f'no cell of the map was seen by {min_pairs} stereo pairs (lower min_pairs)')
    e, n, h = enu_to_crs(origin, np.column_stack([p['x'], p['y'], p['z']]), crs, heights)
    rgb = np.column_stack([p['r'], p['g'], p['b']])
    return GeoCloud(e, n, h, np.clip(np.rint(rgb), 0, 255).astype(np.uint8), p['n'].astype(np.uint32),
                    p['confidence'].astype(np.float32), crs, heights, p['sigma_z'].astype(np.float32),
                    p['n_pairs'].astype(np.uint32))


def classify_cloud(cloud: GeoCloud, p: GroundParams | None = None) -> dict:
    """Set cloud.classes (ground / building / unclassified, core.ground) and return the class counts."""
    c = classify_points(cloud.x, cloud.y, cloud.z, p)
    cloud.classes = c.classes
    return {'counts': c.counts(), 'buildings': c.buildings, 'notes': c.notes}


# --- point clouds ----------------------------------------------------------------------------------


def write_las(cloud: GeoCloud, path: str | Path) -> Path:
    """LAS 1.4 point format 7 (RGB), CRS as an OGC WKT1 VLR with EPSG ids (io/crs_tags.py); .laz compresses (lazrs).

    Every point is return 1 of 1 (a photogrammetric point is the only return of its ray; 0 is invalid
    in LAS 1.4) with its class from cloud.classes (1, unclassified, when not classified).
    """
    import laspy
    path = Path(path)
    header = laspy.LasHeader(point_format=7, version='1.4')
    xyz = (cloud.x, cloud.y, cloud.z)
    if not all(np.all(np.isfinite(v)) for v in xyz):
        raise DataError(f'{path.name}: the cloud holds non-finite coordinates; nothing written')
    header.offsets = [np.floor(v.min()) if v.size else 0.0 for v in xyz]
    # Millimetres, or the finest power of ten whose 32-bit integers span the cloud's extent.
    header.scales = [_las_scale(float(np.ptp(v)) if v.size else 0.0) for v in xyz]
    describe_las(header, cloud.crs, cloud.heights)     # WKT1 with EPSG ids, System Identifier (io/crs_tags.py)
    header.add_extra_dims([laspy.ExtraBytesParams('observations', np.uint32, 'points fused in the cell'),
                           laspy.ExtraBytesParams('confidence', np.float32, 'mean stereo confidence')])
    header.generating_software = 'photogram_ros'
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud.x, cloud.y, cloud.z
    las.return_number = np.ones(cloud.x.size, np.uint8)
    las.number_of_returns = np.ones(cloud.x.size, np.uint8)
    las.classification = cloud.classes if cloud.classes is not None else np.ones(cloud.x.size, np.uint8)
    # LAS colour is 16-bit: scale 0..255 to 0..65535 as GIS tools expect.
    las.red = cloud.rgb[:, 0].astype(np.uint16) * 257
    las.green = cloud.rgb[:, 1].astype(np.uint16) * 257
    las.blue = cloud.rgb[:, 2].astype(np.uint16) * 257
    las.observations = cloud.count
    las.confidence = cloud.confidence
    las.write(str(path))
    return path


def _las_scale(extent_m: float) -> float:
    scale = 0.001
    while extent_m / scale > 2_000_000_000:
        scale *= 10.0
    return scale


_PLY_FIELDS = [('x', '<f8', 'double'), ('y', '<f8', 'double'), ('z', '<f8', 'double'),
               ('red', 'u1', 'uchar'), ('green', 'u1', 'uchar'), ('blue', 'u1', 'uchar'),
               ('confidence', '<f4', 'float'), ('observations', '<u4', 'uint'), ('classification', 'u1', 'uchar')]
_PLY_TYPES = {'char': 'i1', 'uchar': 'u1', 'short': '<i2', 'ushort': '<u2', 'int': '<i4', 'uint': '<u4',
              'float': '<f4', 'double': '<f8', 'int8': 'i1', 'uint8': 'u1', 'int16': '<i2', 'uint16': '<u2',
              'int32': '<i4', 'uint32': '<u4', 'float32': '<f4', 'float64': '<f8'}


def write_ply(cloud: GeoCloud, path: str | Path) -> Path:
    """Binary little-endian PLY; coordinates in double so projected eastings keep millimetres."""
    path = Path(path)
    arr = np.empty(cloud.x.size, dtype=[(n, t) for n, t, _ in _PLY_FIELDS])
    arr['x'], arr['y'], arr['z'] = cloud.x, cloud.y, cloud.z
    arr['red'], arr['green'], arr['blue'] = cloud.rgb[:, 0], cloud.rgb[:, 1], cloud.rgb[:, 2]
    arr['confidence'], arr['observations'] = cloud.confidence, cloud.count
    arr['classification'] = cloud.classes if cloud.classes is not None else 1
    lines = ['ply', 'format binary_little_endian 1.0', 'comment generated by photogram_ros',
             f'comment crs {cloud.crs}', f'comment heights {cloud.heights}', f'element vertex {arr.size}']
    lines += [f'property {ply} {n}' for n, _, ply in _PLY_FIELDS] + ['end_header']
    with open(path, 'wb') as f:
        f.write(('\n'.join(lines) + '\n').encode('ascii'))
        f.write(arr.tobytes())
    return path


def read_ply(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """Vertices of a binary little-endian PLY (scalar properties) and its comments."""
    data = Path(path).read_bytes()
    end = data.find(b'end_header\n')
    if not data.startswith(b'ply\n') or end < 0:
        raise DataError(f'{path} is not a PLY file')
    header = data[:end].decode('ascii').splitlines()
    if 'format binary_little_endian 1.0' not in header:
        raise DataError(f'{path}: only binary little-endian PLY is read here')
    fields, comments, n, in_vertex = [], [], 0, False
    for line in header:
        parts = line.split()
        if parts[:1] == ['comment']:
            comments.append(line[8:])
        elif parts[:1] == ['element']:
            in_vertex = parts[1] == 'vertex'
            if in_vertex:
                n = int(parts[2])
            elif fields:
                break
        elif parts[:1] == ['property'] and in_vertex:
            if parts[1] == 'list':
                raise DataError(f'{path}: list properties in vertices are not supported')
            fields.append((parts[2], _PLY_TYPES[parts[1]]))
    return np.frombuffer(data, dtype=np.dtype(fields), count=n, offset=end + len('end_header\n')).copy(), comments


# --- rasters ---------------------------------------------------------------------------------------


COG_BLOCK_PX = 256


def write_geotiff(r: Raster, path: str | Path, crs: str, description: str = '', rgba: bool = False,
                  heights: str | None = None, band_names: tuple = ()) -> Path:
    """A Cloud-Optimized GeoTIFF (GDAL's COG driver: 256-px tiles, deflate, overviews down to one tile).

    The 2D CRS is in the file's GeoKeys by its EPSG code; with `heights` (not for rgba) the vertical
    datum is in the metadata and band 1's unit is metre (io/crs_tags.geotiff_georef): the .tif copied
    alone keeps both, no .aux.xml sidecar is written. Overviews average (no-data and alpha aware).
    `band_names` describe the bands (GDAL band descriptions).
    """
    import rasterio
    from rasterio.enums import ColorInterp
    from rasterio.transform import from_origin
    path = Path(path)
    data = r.data
    bands = data.shape[2] if data.ndim == 3 else 1
    g = geotiff_georef(crs, None if rgba else heights)     # 2D CRS by EPSG code, vertical datum tags (io/crs_tags.py)
    profile = dict(driver='COG', width=r.shape[1], height=r.shape[0], count=bands, dtype=data.dtype,
                   crs=g.crs, transform=from_origin(r.x0_m, r.y1_m, r.res_m, r.res_m),
                   compress='deflate', predictor='yes', blocksize=COG_BLOCK_PX, overviews='auto',
                   resampling='average', bigtiff='if_safer')
    if r.nodata is not None and not rgba:
        profile['nodata'] = r.nodata
    with rasterio.Env(GDAL_PAM_ENABLED='NO'):
        with rasterio.open(path, 'w', **profile) as ds:
            if data.ndim == 2:
                ds.write(data, 1)
            else:
                for b in range(bands):
                    ds.write(data[:, :, b], b + 1)
            if rgba:
                ds.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]
            elif g.height_unit:
                ds.units = (g.height_unit,) + ('',) * (bands - 1)
            for i, name in enumerate(band_names[:bands]):
                ds.set_band_description(i + 1, name)
            ds.update_tags(**g.tags, **({'DESCRIPTION': description} if description else {}))
    Path(str(path) + '.aux.xml').unlink(missing_ok=True)
    return path


def read_crs(path: str | Path):
    """The pyproj CRS a GeoTIFF holds in its own GeoKeys (no sidecar read), or None."""
    import rasterio
    from pyproj import CRS
    with rasterio.Env(GDAL_PAM_ENABLED='NO'):
        with rasterio.open(path) as ds:
            return CRS.from_wkt(ds.crs.to_wkt()) if ds.crs else None


@dataclass
class DsmParams:
    """How the DSM is gridded from the fused cells (core/raster.dsm_from_points).

    A DSM cell straddling a wall is no-data rather than half-way up it; a cell needs `min_count` fused
    cells (a sliver of roof or ground alone sits off the cell centre, where a wall makes its height
    wrong); gaps up to `fill_gaps_m` between agreeing sides (textureless tracks) are interpolated. On
    the sample flight these took the DSM RMSE against the true DEM from 2.8 to 2.0 GSD. The two
    lengths are the sample's (0.5 m, 3 m with 0.12 m cells) scaled with the map's cell size unless
    set (core/gsd.dsm_lengths_for_cell): with the sample's lengths a 1080p flight at 166 m, whose
    cells are 0.4 m, kept 2.8 % of its DSM.
    """
    max_spread_m: float = param(AUTO, 'a DSM cell whose fused points span more height is no-data (a wall), m; '
                                      '-1: from the map cell (0.5 m at 0.12 m cells)', min=AUTO, max=1e3)
    min_count: int = param(3, 'fused cells a DSM cell needs', min=1, max=100)
    fill_gaps_m: float = param(AUTO, 'gaps up to this wide between agreeing sides are interpolated, m (0: none); '
                                     '-1: from the map cell (3 m at 0.12 m cells)', min=AUTO, max=1e4)
    canopy_top: bool = param(True, 'a DSM cell whose points spread more than max_spread_m keeps the top (upper '
                                   'quartile) of its heights when the heights around it run on without a wall\'s '
                                   'gap (vegetation: core/raster.rough_surface_cells); False: every such cell is '
                                   'no-data')
    fill: bool = param(True, 'cells stereo did not measure, inside the hull of the camera centres (widened by a '
                             'quarter of the flying height), are interpolated from the measured heights around '
                             'them; band 2 of dsm.tif says which: pairs that measured the cell, 0 where '
                             'interpolated; False: no-data there')

    def check(self) -> None:
        for name in ('max_spread_m', 'fill_gaps_m'):
            v = getattr(self, name)
            if v != AUTO and v < 0:
                raise ConfigError(f'DSM parameter {name!r} = {v} must be at least 0, or -1 to follow the map cell')

    def for_cell(self, cell_m: float) -> 'DsmParams':
        """A copy with the AUTO lengths set for fused cells of `cell_m`."""
        spread, gaps = dsm_lengths_for_cell(cell_m)
        return DsmParams(spread if self.max_spread_m == AUTO else self.max_spread_m, self.min_count,
                         gaps if self.fill_gaps_m == AUTO else self.fill_gaps_m, self.canopy_top, self.fill)


def dsm_in_crs(cloud: GeoCloud, res_m: float, dsm: DsmParams, bounds=None) -> Raster:
    """The DSM of `cloud` at `res_m` with resolved DsmParams (DsmParams.for_cell); `bounds` (west, south,
    east, north) fixes the grid (default: the cloud's extent)."""
    if AUTO in (dsm.max_spread_m, dsm.fill_gaps_m):
        raise ConfigError('DsmParams left to the map cell: resolve them first (DsmParams.for_cell)')
    return dsm_from_points(cloud.x, cloud.y, cloud.z, res_m, weights=cloud.count, max_spread_m=dsm.max_spread_m,
                           z_sigma=cloud.sigma_z, min_count=dsm.min_count, fill_gaps_m=dsm.fill_gaps_m,
                           canopy=dsm.canopy_top, bounds=bounds)


FILLED = 0.0     # band 2 of dsm.tif for a cell no stereo pair measured (interpolated)
FILL_MARGIN_AGL = 0.25   # the filled area reaches this share of the flying height beyond the camera centres' hull


@dataclass
class Surface:
    """The DSM as exported: heights (band 1) and how each cell was obtained (band 2)."""
    dsm: Raster                  # float32 heights, NODATA where nothing is known
    pairs: np.ndarray            # float32 (rows, cols): pairs that measured the cell; FILLED; NODATA
    region: np.ndarray           # bool: the cells filling may reach (camera centres' hull, widened)
    camera_hull: np.ndarray      # bool: the cells inside the convex hull of the camera centres

    def shares(self, mask: np.ndarray) -> dict:
        """Shares of the cells of `mask` holding a height, measured by stereo pairs, interpolated."""
        n = max(int(mask.sum()), 1)
        p = self.pairs[mask]
        return {'cells': int(mask.sum()), 'valid': float(np.sum(p != NODATA) / n),
                'measured': float(np.sum((p != NODATA) & (p >= 1)) / n),
                'filled': float(np.sum(p == FILLED) / n)}


def surface_in_crs(fusion: Fusion, origin: LocalFrame, crs: str, heights: str, res_m: float, rules: DsmParams,
                   min_pairs: int, camera_centres_map: np.ndarray, cloud: GeoCloud | None = None) -> Surface:
    """The DSM in `crs` from the cells `min_pairs` pairs measured; with rules.fill the cells it leaves
    inside what the photos saw are interpolated from the heights around them (core/raster.fill_surface).

    What the photos saw: the convex hull of the camera centres (`camera_centres_map`, (K, 3) map ENU),
    widened by FILL_MARGIN_AGL times the height above the DSM's median (the ground around the nadir
    points that every photo of a line holds). Cells one pair measured are not used: on the simulator
    they were worse than interpolation (median 1.5 against 1.1 GSD over the flown area), on brighton
    no better (0.32 against 0.32 m median against OpenDroneMap). `cloud`: map_cloud(fusion, origin,
    crs, heights, min_pairs) if already made.
    """
    cloud = cloud or map_cloud(fusion, origin, crs, heights, min_pairs)
    grid = dsm_in_crs(cloud, res_m, rules)
    measured = grid.valid()
    pairs = np.where(measured, cell_max(cloud.x, cloud.y, cloud.pairs, grid).astype(np.float32), NODATA)
    cam_hull = region = np.zeros(grid.shape, bool)
    if len(camera_centres_map) and measured.any():
        ce, cn, ch = enu_to_crs(origin, np.asarray(camera_centres_map, float), crs, heights)
        cam_hull = hull_mask(grid.shape, *grid.to_pixel(ce, cn))
        agl_m = max(float(np.median(ch) - np.median(grid.data[measured])), 0.0)
        r = int(round(FILL_MARGIN_AGL * agl_m / grid.res_m))
        region = cam_hull.copy()
        if r > 0:
            import cv2
            cols, rows = grid.to_pixel(ce, cn)
            seed = np.zeros(grid.shape, np.uint8)
            seed[cam_hull] = 1
            ok = (cols >= 0) & (rows >= 0) & (cols < grid.shape[1]) & (rows < grid.shape[0])
            seed[np.round(rows[ok]).astype(int), np.round(cols[ok]).astype(int)] = 1
            region = cv2.dilate(seed, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) > 0
    if rules.fill and region.any():
        d = fill_surface(grid.data, region)
        pairs[(d != NODATA) & (pairs == NODATA)] = FILLED
        grid = Raster(d, grid.x0_m, grid.y1_m, grid.res_m, NODATA)
    pairs[(grid.data != NODATA) & (pairs == NODATA)] = FILLED
    return Surface(grid, pairs, region, cam_hull)


class StoredKeyframes(Sequence):
    """The map folder's keyframes whose image has the camera's size, as core/raster.Keyframe, each image
    decoded when it is read (the orthomosaic drapes them one at a time): one image in memory, not the
    flight's. The sizes come from the JPEG headers (with their EXIF orientation, as cv2.imread applies it)."""

    def __init__(self, store: MapStore):
        self.camera = store.load_camera()
        self.entries = []
        if self.camera is None:
            return
        for kf in store.keyframes():
            if _image_size(kf['image_path']) == (self.camera.width, self.camera.height):
                self.entries.append((kf['image_path'], kf['map_T_cam']))

    def __len__(self) -> int:
        return len(self.entries)

    def __getitem__(self, i) -> Keyframe:
        import cv2
        path, map_T_cam = self.entries[i]
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None or img.shape[:2] != (self.camera.height, self.camera.width):
            raise DataError(f'keyframe image {path} cannot be read as a {self.camera.width}x{self.camera.height} '
                            'photo (changed since the export began?)')
        return Keyframe(img, map_T_cam, self.camera)


def _image_size(path) -> tuple[int, int] | None:
    """(width, height) of an image file as cv2.imread would decode it (EXIF orientation applied), from its
    header; None when it cannot be read."""
    from PIL import Image, UnidentifiedImageError
    try:
        with Image.open(path) as im:
            w, h = im.size
            turned = im.getexif().get(0x0112, 1) in (5, 6, 7, 8)
    except (OSError, UnidentifiedImageError, ValueError):
        return None
    return (h, w) if turned else (w, h)


def ortho_in_crs(dsm_ellipsoidal: Raster, keyframes: Sequence[Keyframe], origin: LocalFrame, crs: str,
                 res_m: float | None = None, progress=None) -> Raster:
    """Orthomosaic on a DSM gridded in `crs` whose values are WGS84 ellipsoidal heights. RGBA.
    `progress(done, total)`: keyframes draped so far (core/raster.orthomosaic)."""
    bgra = orthomosaic(dsm_ellipsoidal, keyframes, lambda e, n, h: crs_to_enu(origin, e, n, h, crs), res_m,
                       progress=progress)
    rgba = bgra.data[:, :, [2, 1, 0, 3]].copy()
    return Raster(rgba, bgra.x0_m, bgra.y1_m, bgra.res_m, None)


@dataclass
class ExportResult:
    files: dict = field(default_factory=dict)    # product -> path
    points: int = 0
    keyframes: int = 0
    notes: list = field(default_factory=list)
    crs_with_heights: str = ''                  # the products' CRS, with its vertical part
    dsm: dict | None = None                     # the DSM rules used (DsmParams, resolved)
    classes: dict | None = None                 # LAS/PLY classes: ground, building, unclassified, buildings
    dtm: dict | None = None                     # ground points and cells of the DTM
    ortho: dict | None = None                   # the orthomosaic's cell size and cells holding a colour


def export_map(map_dir: str | Path | MapStore, out_dir: str | Path, crs: str, heights: str = 'ellipsoidal',
               dsm_res_m: float = 0.0, ortho_res_m: float = 0.0, products=('las', 'laz', 'ply', 'dsm', 'dtm', 'ortho'),
               origin: LocalFrame | None = None, min_pairs: int = 1, dsm: DsmParams | None = None,
               contour_interval_m: float = 0.0, say=None, damaged: list | None = None) -> ExportResult:
    """Write the requested products of a map folder (or an open MapStore) into out_dir (created).

    min_pairs=2 exports only cells confirmed by two stereo pairs: a cell one pair saw cannot be
    checked for gross matching errors (on the sample flight they hold most of the large errors).
    `dsm`: the DSM rules (default DsmParams(): lengths from the map's cell size).
    contour_interval_m > 0 also writes contours.gpkg: the DTM's contour lines at that interval (io/contours.py).
    say(text): progress lines (io/progress.py): each product as it starts, the orthomosaic's keyframes
    counted; None: none. The map's tiles are checked first (MapStore.check_tiles): each damaged tile is
    named in the notes and export.json's damaged_tiles, with what rebuilds its points; `damaged`: tiles of
    another map these products were rebuilt for (named the same way, as rebuilt).
    """
    dsm = dsm or DsmParams()
    validate(dsm)
    _check_projected(crs)
    store = as_map_store(map_dir)
    damage = [f'{store.tiles_dir / d.path.name}: {d.what}' for d in store.check_tiles()]
    store, fusion = open_map(store)
    origin = origin or store.origin
    if origin is None:
        raise DataError(f'{store.root} has no geodetic origin (map.json "origin" is null): the map node never '
                        'received /map/georeference; pass the origin explicitly (--origin LAT,LON,H)')
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    res = ExportResult()
    for d in damage:
        res.notes.append(f'damaged map tile {d}; its points are missing from these products: photogram-ros export '
                         f'{store.root} --densify rebuilds them from the keyframes')
        if say is not None:
            say(f'export: damaged map tile {d}')
    res.notes += [f'damaged map tile {d}; its points were rebuilt from the keyframes (matched again)'
                  for d in damaged or []]
    unposed = store.unposed_keyframe_images()
    if unposed:
        res.notes.append(f'{len(unposed)} keyframe images of {store.root} have no pose (taken before the flight was '
                         f'cut short, never oriented; first {unposed[0].name}): not in these products')
    surface = any(k in products for k in ('dsm', 'dtm', 'ortho')) or contour_interval_m > 0
    plan = (['cloud'] + [name for k, name in (('las', 'LAS'), ('laz', 'LAZ'), ('ply', 'PLY')) if k in products]
            + ['DSM'] * surface + ['DTM'] * ('dtm' in products or contour_interval_m > 0)
            + ['contours'] * (contour_interval_m > 0) + ['ortho'] * ('ortho' in products))
    steps = Steps('export', len(plan), say)
    steps.start('cloud')
    cloud = map_cloud(fusion, origin, crs, heights, min_pairs)
    res.points = cloud.x.size
    vertical_crs, note = product_crs(crs, heights)
    res.crs_with_heights = vertical_crs.name
    if note:
        res.notes.append(note)
    if any(k in products for k in ('las', 'laz', 'ply')):
        c = classify_cloud(cloud)
        res.notes += c['notes']
        res.classes = {'ground': c['counts'].get(2, 0), 'building': c['counts'].get(6, 0),
                       'unclassified': c['counts'].get(1, 0), 'buildings': c['buildings']}
    failed: dict = {}   # product -> why it was not written (each named with its path)

    def keep(key, path, write) -> None:
        """The product `key` written whole at `path` by write(tmp), or its failure recorded: a full disk
        stops this product, not the smaller ones after it."""
        try:
            res.files[key] = write_whole(path, write)
        except StorageError as exc:
            failed[key] = (str(exc), exc.errno)
        except Exception as exc:   # a writer that wraps the system's error (rasterio, laspy)
            cause = _disk_full(exc)
            if cause is None:
                raise
            failed[key] = (f'{path}: not written: ' + ('the disk is full' if cause.errno == errno.ENOSPC else
                                                      cause.strerror or str(cause)), cause.errno)
        if key in failed and say is not None:
            say(f'export: {failed[key][0]}')

    for key, name, write in (('las', 'LAS', write_las), ('laz', 'LAZ', write_las), ('ply', 'PLY', write_ply)):
        if key in products:
            steps.start(name)
            keep(key, out / f'cloud.{key}', lambda tmp, write=write: write(cloud, tmp))
    dsm_res = dsm_res_m or 2.0 * store.cell_m
    rules = dsm.for_cell(store.cell_m)
    res.dsm = {'cell_m': store.cell_m, 'res_m': dsm_res, 'max_spread_m': rules.max_spread_m,
               'min_count': rules.min_count, 'fill_gaps_m': rules.fill_gaps_m,
               'canopy_top': rules.canopy_top}
    centres = np.array([k['map_T_cam'][:3, 3] for k in store.keyframes()]).reshape(-1, 3)
    if contour_interval_m < 0:
        raise ConfigError(f'the contour interval must be positive (0: no contours), not {contour_interval_m} m')
    if surface:
        steps.start('DSM')
        surf = surface_in_crs(fusion, origin, crs, heights, dsm_res, rules, min_pairs, centres, cloud)
        grid = surf.dsm
        res.dsm['valid_share'] = float(np.mean(grid.valid())) if grid.data.size else 0.0
        res.dsm['raster'] = surf.shares(np.ones(grid.shape, bool))
        if surf.camera_hull.any():
            res.dsm['camera_hull'] = surf.shares(surf.camera_hull)
        if 'dsm' in products:
            keep('dsm', out / 'dsm.tif', lambda tmp: write_geotiff(
                Raster(np.dstack([grid.data, surf.pairs]), grid.x0_m, grid.y1_m, grid.res_m, NODATA),
                tmp, crs, f'DSM, {heights} heights (m); band 2: stereo pairs that measured the cell, '
                f'0 where interpolated', heights=heights, band_names=('height_m', 'pairs')))
    if 'dtm' in products or contour_interval_m > 0:
        steps.start('DTM')
        dtm = dtm_from_points(cloud.x, cloud.y, cloud.z, grid, grid.valid(), weights=cloud.count, classes=cloud.classes)
        res.notes += [f'DTM: {n}' for n in dtm.notes]
        res.dtm = {'ground_points': dtm.ground_points, 'ground_cells_share': float(dtm.ground.mean()),
                   'valid_share': float(np.mean(dtm.raster.valid()))}
        if 'dtm' in products:
            keep('dtm', out / 'dtm.tif', lambda tmp: write_geotiff(
                dtm.raster, tmp, crs, f'DTM (bare ground, from the cloud\'s ground class), {heights} heights (m)',
                heights=heights))
        if contour_interval_m > 0:
            from photogram_ros.io.contours import contour_lines, write_contours_gpkg
            steps.start('contours')
            lines = contour_lines(dtm.raster, contour_interval_m)
            keep('contours', out / 'contours.gpkg', lambda tmp: write_contours_gpkg(
                lines, tmp, crs, f'DTM contours every {contour_interval_m:g} m, {heights} heights (elevation_m)'))
            res.dtm['contour_lines'] = len(lines)
    if 'ortho' in products:
        steps.start('ortho')
        kfs = StoredKeyframes(store)
        res.keyframes = len(kfs)
        if not kfs:
            res.notes.append('no orthomosaic: the map folder holds no keyframes with images, poses and camera')
        else:
            dsm_ell = grid if heights == 'ellipsoidal' else surface_in_crs(
                fusion, origin, crs, 'ellipsoidal', dsm_res, rules, min_pairs, centres).dsm
            draped = Progress('export: ortho', len(kfs), 'keyframes', say, clock=steps.clock)
            ortho = ortho_in_crs(dsm_ell, kfs, origin, crs, ortho_res_m or store.cell_m, draped.callback())
            seen = ortho.data[..., 3] > 0
            res.ortho = {'res_m': ortho.res_m, 'valid_share': float(seen.mean())}
            if len(centres):
                ce, cn, _ = enu_to_crs(origin, centres, crs, heights)
                inside = hull_mask(ortho.shape, *ortho.to_pixel(ce, cn))
                if inside.any():
                    res.ortho['camera_hull'] = {'cells': int(inside.sum()), 'valid': float(seen[inside].mean())}
            keep('ortho', out / 'ortho.tif', lambda tmp: write_geotiff(ortho, tmp, crs, 'orthomosaic RGBA', rgba=True,
                                                                       heights=heights))
    meta = {'crs': crs, 'heights': heights, 'origin': origin.to_dict(), 'points': res.points, 'min_pairs': min_pairs,
            'keyframes': res.keyframes, 'files': {k: str(v) for k, v in res.files.items()}, 'notes': res.notes,
            'geoid': geoid.MODEL_NAME if heights == 'orthometric' else None, 'crs_with_heights': res.crs_with_heights,
            'classes': res.classes, 'dsm': res.dsm, 'dtm': res.dtm, 'ortho': res.ortho,
            'damaged_tiles': [{'tile': d, 'points': 'missing'} for d in damage]
            + [{'tile': d, 'points': 'rebuilt from the keyframes'} for d in damaged or []],
            'failed': {k: why for k, (why, _) in failed.items()}}
    try:
        write_whole(out / 'export.json', lambda tmp: tmp.write_text(json.dumps(meta, indent=1)))
    except StorageError as exc:
        failed['export.json'] = (str(exc), exc.errno)
    steps.finish()
    if failed:
        kept = ', '.join(sorted(Path(v).name for v in res.files.values())) or 'none'
        raise ProductsIncomplete('; '.join(why for why, _ in failed.values()) + f' (written whole: {kept}; the map '
                                 f'in {store.root} is safe: free space and export again)',
                                 next(iter(failed.values()))[1], res)
    return res
