"""The rasters of the exports: Cloud-Optimized GeoTIFFs, the DSM with its filled cells, the orthomosaic.

Rasters are Cloud-Optimized GeoTIFFs (GDAL's COG driver: tiled, deflate, overviews) whose CRS and
vertical datum are in the file itself (write_geotiff, io/crs_tags.py): a .tif copied alone keeps them.
The DSM covers what the photos saw (the cameras' footprint: the camera centres' hull, widened): the cells
min_pairs stereo pairs confirmed, the cells one pair measured where no confirmed cell is near
(covering_clouds), and heights interpolated where stereo measured none (surface_in_crs); its band 2 gives the
stereo pairs that measured each cell (1: one pair, unconfirmed), 0 where interpolated. Rasters are built in the output CRS's own grid
(north-up in that CRS): the DSM from the fused cells' CRS coordinates, the orthomosaic by mapping each
of its cells back to map ENU and draping the keyframes (core.raster.orthomosaic).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from photogram_ros.core.fusion import Fusion
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.gsd import AUTO, dsm_lengths_for_cell
from photogram_ros.core.raster import (NODATA, Keyframe, Raster, cell_max, dsm_from_points, fill_surface, hull_mask,
                                       orthomosaic)
from photogram_ros.errors import ConfigError, DataError
from photogram_ros.io.crs_tags import geotiff_georef
from photogram_ros.io.export_cloud import GeoCloud, too_few_pairs, crs_to_enu, enu_to_crs, map_clouds
from photogram_ros.io.map_store import MapStore
from photogram_ros.params import param

# --- rasters ---------------------------------------------------------------------------------------


COG_BLOCK_PX = 256
ONE_PAIR_NEVER_M = 1e4    # DsmParams.one_pair_beyond_m at this length: no one-pair cell holds a height


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
    cells are 0.4 m, kept 2.8 % of its DSM. Cells one stereo pair measured hold the DSM where no confirmed
    cell lies within `one_pair_beyond_m` (covering_clouds).
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
    one_pair_beyond_m: float = param(AUTO, 'a DSM cell that fewer stereo pairs than min_pairs measured (one pair, '
                                           'unconfirmed) takes that height when no cell min_pairs pairs measured lies '
                                           'within this distance (nearer, it is interpolated from the confirmed '
                                           'ones); m; -1: the gap-filling length (fill_gaps_m); 1e4: never (only '
                                           'confirmed cells, as before one-pair cells were used)',
                                     min=AUTO, max=ONE_PAIR_NEVER_M)

    def check(self) -> None:
        for name in ('max_spread_m', 'fill_gaps_m', 'one_pair_beyond_m'):
            v = getattr(self, name)
            if v != AUTO and v < 0:
                raise ConfigError(f'DSM parameter {name!r} = {v} must be at least 0, or -1 to follow the map cell')

    def for_cell(self, cell_m: float) -> 'DsmParams':
        """A copy with the AUTO lengths set for fused cells of `cell_m`."""
        spread, gaps = dsm_lengths_for_cell(cell_m)
        gaps = gaps if self.fill_gaps_m == AUTO else self.fill_gaps_m
        return dataclasses.replace(self, max_spread_m=spread if self.max_spread_m == AUTO else self.max_spread_m,
                                   fill_gaps_m=gaps, one_pair_beyond_m=gaps if self.one_pair_beyond_m == AUTO
                                   else self.one_pair_beyond_m)


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
# A cell one stereo pair measured (unconfirmed, DsmParams.one_pair_beyond_m) is kept when it agrees with the
# one-pair cells around it: within the DSM's spread limit of the median of those within ONE_PAIR_WINDOW_PX cells
# (a 5x5 window), of which at least ONE_PAIR_MIN_NEIGHBOURS of the 24 hold a height (a lone speck of mismatches
# has nothing to agree with; a cell on a straight edge of the covered area has 14 neighbours, in a corner 8).
ONE_PAIR_WINDOW_PX = 2
ONE_PAIR_MIN_NEIGHBOURS = 6


@dataclass
class Surface:
    """The DSM as exported: heights (band 1) and how each cell was obtained (band 2)."""
    dsm: Raster                  # float32 heights, NODATA where nothing is known
    pairs: np.ndarray            # float32 (rows, cols): pairs that measured the cell (1: one, unconfirmed); FILLED; NODATA
    region: np.ndarray           # bool: the cameras' footprint, which filling may reach (camera centres' hull, widened)
    camera_hull: np.ndarray      # bool: the cells inside the convex hull of the camera centres
    # Interpolated cells that fewer stereo pairs than min_pairs measured (one pair, not used for the heights: a
    # confirmed cell is near), and that height minus the interpolated one, m (NaN elsewhere). None: not looked
    # at (min_pairs 1).
    one_pair: np.ndarray | None = None
    one_pair_dz_m: np.ndarray | None = None

    def shares(self, mask: np.ndarray) -> dict:
        """Shares of the cells of `mask` holding a height, measured by stereo pairs (any number), by one pair
        only (`measured_one_pair`), interpolated, and of the interpolated ones those that fewer pairs than
        min_pairs measured too (`filled_one_pair`)."""
        n = max(int(mask.sum()), 1)
        p = self.pairs[mask]
        out = {'cells': int(mask.sum()), 'valid': float(np.sum(p != NODATA) / n),
               'measured': float(np.sum((p != NODATA) & (p >= 1)) / n),
               'measured_one_pair': float(np.sum(p == 1) / n),
               'filled': float(np.sum(p == FILLED) / n)}
        if self.one_pair is not None:
            out['filled_one_pair'] = float(np.sum(self.one_pair[mask]) / n)
        return out

    def one_pair_check(self, mask: np.ndarray | None = None) -> dict | None:
        """How the interpolated heights agree with what one stereo pair measured in the same cells (within
        `mask`, default all): cells compared and |dz| median / p90, bias (median dz), m. None when there is
        nothing to compare."""
        if self.one_pair is None:
            return None
        sel = self.one_pair if mask is None else self.one_pair & mask
        dz = self.one_pair_dz_m[sel]
        if dz.size == 0:
            return {'cells': 0}
        a = np.abs(dz)
        return {'cells': int(dz.size), 'median_abs_dz_m': float(np.median(a)),
                'p90_abs_dz_m': float(np.percentile(a, 90)), 'bias_m': float(np.median(dz))}


def cameras_in_crs(origin: LocalFrame, camera_centres_map: np.ndarray, crs: str, heights: str):
    """(easting, northing, height) arrays of the camera centres ((K, 3) map ENU) in `crs`; None without any."""
    c = np.asarray(camera_centres_map, float).reshape(-1, 3)
    return enu_to_crs(origin, c, crs, heights) if len(c) else None


def _box(*clouds: GeoCloud) -> tuple[float, float, float, float] | None:
    xs = [c.x for c in clouds if c is not None and c.x.size]
    ys = [c.y for c in clouds if c is not None and c.y.size]
    if not xs:
        return None
    return (min(float(x.min()) for x in xs), min(float(y.min()) for y in ys),
            max(float(x.max()) for x in xs), max(float(y.max()) for y in ys))


def _union(a, b):
    if a is None or b is None:
        return a or b
    return min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])


def _footprint_box(cams, ground_m: float, res_m: float):
    """The box around the camera centres that their footprint (the fill region, _footprint) fits in."""
    ce, cn, ch = cams
    m = FILL_MARGIN_AGL * max(float(np.median(ch)) - ground_m, 0.0) + 2.0 * res_m
    return float(ce.min()) - m, float(cn.min()) - m, float(ce.max()) + m, float(cn.max()) + m


def _footprint(grid: Raster, cams, ground_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(inside the camera centres' convex hull, the cameras' footprint: that hull widened by FILL_MARGIN_AGL
    times the height of the cameras above `ground_m`, with every camera's nadir point) as masks of `grid`."""
    cam_hull = region = np.zeros(grid.shape, bool)
    if cams is None:
        return cam_hull, region
    import cv2
    ce, cn, ch = cams
    cols, rows = grid.to_pixel(ce, cn)
    cam_hull = hull_mask(grid.shape, cols, rows)
    r = int(round(FILL_MARGIN_AGL * max(float(np.median(ch)) - ground_m, 0.0) / grid.res_m))
    region = cam_hull.copy()
    if r > 0:
        seed = np.zeros(grid.shape, np.uint8)
        seed[cam_hull] = 1
        ok = (cols >= 0) & (rows >= 0) & (cols < grid.shape[1]) & (rows < grid.shape[0])
        seed[np.round(rows[ok]).astype(int), np.round(cols[ok]).astype(int)] = 1
        region = cv2.dilate(seed, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) > 0
    return cam_hull, region


def _one_pair_grid(fewer: GeoCloud, rules: DsmParams, like: Raster) -> Raster:
    """The cells of `fewer` (fewer pairs than the DSM asks) gridded on the grid of `like` by the DSM's spread
    rules, one fused cell being enough (a pair's points are sparser than the DSM's cells at a quarter scale),
    without gap filling."""
    half = 0.25 * like.res_m      # inside the grid's own edges: grid_for snaps them back to the same grid
    west, south, east, north = like.bounds
    one = dsm_from_points(fewer.x, fewer.y, fewer.z, like.res_m, weights=fewer.count,
                          bounds=(west + half, south + half, east - half, north - half),
                          max_spread_m=rules.max_spread_m, z_sigma=fewer.sigma_z,
                          min_count=1, fill_gaps_m=0.0, canopy=rules.canopy_top)
    if one.shape != like.shape:
        raise DataError(f'the one-pair grid {one.shape} does not match the DSM\'s {like.shape}')
    return one


def agrees_with_neighbours(d: np.ndarray, valid: np.ndarray, todo: np.ndarray, tol_m: float,
                           radius_px: int = ONE_PAIR_WINDOW_PX, min_neighbours: int = ONE_PAIR_MIN_NEIGHBOURS,
                           chunk: int = 200_000) -> np.ndarray:
    """Bool mask: the cells of `todo` (within `valid`) whose height is within `tol_m` of the median of the
    `valid` cells around them (within `radius_px`, the cell itself left out), at least `min_neighbours` of
    which hold a height."""
    out = np.zeros(d.shape, bool)
    rows, cols = np.nonzero(todo & valid)
    if rows.size == 0:
        return out
    k = radius_px
    zp = np.pad(np.where(valid, d, np.nan).astype(np.float32), k, constant_values=np.nan)
    offsets = [(dr, dc) for dr in range(-k, k + 1) for dc in range(-k, k + 1) if dr or dc]
    for i in range(0, rows.size, chunk):
        r, c = rows[i:i + chunk] + k, cols[i:i + chunk] + k
        win = np.sort(np.stack([zp[r + dr, c + dc] for dr, dc in offsets], axis=1), axis=1)   # NaN last
        n = np.isfinite(win).sum(axis=1)
        at = np.arange(r.size)
        lo, hi = np.maximum((n - 1) // 2, 0), np.maximum(n // 2, 0)
        median = 0.5 * (win[at, lo] + win[at, np.minimum(hi, win.shape[1] - 1)])
        ok = (n >= min_neighbours) & (np.abs(zp[r, c] - median) <= tol_m)
        out[r[ok] - k, c[ok] - k] = True
    return out


def join_clouds(a: GeoCloud, b: GeoCloud) -> GeoCloud:
    """The cells of `a` and of `b` (same CRS and heights) in one cloud."""
    def cat(u, v):
        return None if u is None or v is None else np.concatenate([u, v])
    return GeoCloud(np.concatenate([a.x, b.x]), np.concatenate([a.y, b.y]), np.concatenate([a.z, b.z]),
                    np.concatenate([a.rgb, b.rgb]), np.concatenate([a.count, b.count]),
                    np.concatenate([a.confidence, b.confidence]), a.crs, a.heights, cat(a.sigma_z, b.sigma_z),
                    cat(a.pairs, b.pairs), cat(a.classes, b.classes))


def covering_clouds(cloud: GeoCloud, fewer: GeoCloud | None, res_m: float, rules: DsmParams, cams,
                    min_pairs: int) -> tuple[GeoCloud, GeoCloud | None]:
    """(`cloud` with the cells of `fewer` the products use, the other cells of `fewer`): the products' cloud and
    what checks the DSM's interpolation (Surface.one_pair).

    `cloud`: the cells min_pairs stereo pairs measured; `fewer`: those fewer pairs (one, with min_pairs 2)
    measured (map_clouds); `cams`: cameras_in_crs. A cell one pair measured is used where no cell min_pairs pairs measured
    lies within rules.one_pair_beyond_m (on the DSM's grid of `res_m`, inside the cameras' footprint) and it
    agrees with the one-pair cells around it (agrees_with_neighbours): near confirmed cells interpolation from
    them was better on the simulator (1.1 against 1.5 GSD median) and no worse on brighton; beyond the reach of
    the gap filling (fill_gaps_m, the default) a survey with one pair per spot (60 % forward overlap) has no
    other evidence, and interpolating from a far patch of confirmed cells (or from none) is far worse.
    DataError when neither holds a cell."""
    if fewer is None or not fewer.x.size or cams is None or rules.one_pair_beyond_m >= ONE_PAIR_NEVER_M:
        if not cloud.x.size:
            raise too_few_pairs(min_pairs)
        return cloud, fewer
    ground_m = float(np.median(cloud.z if cloud.x.size else fewer.z))
    west, south, east, north = _footprint_box(cams, ground_m, res_m)
    inside = (fewer.x >= west) & (fewer.x <= east) & (fewer.y >= south) & (fewer.y <= north)
    bounds = _union(_box(cloud), _box(fewer.subset(inside)))
    if bounds is None:
        raise too_few_pairs(min_pairs)
    two = dsm_in_crs(cloud, res_m, rules, bounds)
    confirmed = two.valid()
    one = _one_pair_grid(fewer, rules, two)
    _, region = _footprint(two, cams, float(np.median(two.data[confirmed])) if confirmed.any() else ground_m)
    todo = one.valid() & ~confirmed & region
    if confirmed.any():
        from scipy.ndimage import distance_transform_edt
        todo &= distance_transform_edt(~confirmed) * two.res_m > rules.one_pair_beyond_m
    use = agrees_with_neighbours(one.data, one.valid(), todo, rules.max_spread_m)
    col = np.floor((fewer.x - two.x0_m) / two.res_m).astype(np.int64)
    row = np.floor((two.y1_m - fewer.y) / two.res_m).astype(np.int64)
    ok = (col >= 0) & (row >= 0) & (col < two.shape[1]) & (row < two.shape[0])
    sel = np.zeros(fewer.x.size, bool)
    sel[ok] = use[row[ok], col[ok]]
    merged = join_clouds(cloud, fewer.subset(sel)) if sel.any() else cloud
    if not merged.x.size:
        raise too_few_pairs(min_pairs)
    return merged, fewer.subset(~sel)


def surface_in_crs(fusion: Fusion, origin: LocalFrame, crs: str, heights: str, res_m: float, rules: DsmParams,
                   min_pairs: int, camera_centres_map: np.ndarray,
                   clouds: tuple[GeoCloud, GeoCloud | None] | None = None) -> Surface:
    """The DSM in `crs` over the cameras' footprint, from the cells `min_pairs` pairs measured and, where no
    such cell is near, the cells one pair measured (covering_clouds; band 2 says 1 there); with rules.fill the
    cells it leaves inside the footprint are interpolated from the heights around them
    (core/raster.fill_surface).

    The cameras' footprint (what the photos saw): the convex hull of the camera centres (`camera_centres_map`,
    (K, 3) map ENU), widened by FILL_MARGIN_AGL times the height above the DSM's median (the ground around the
    nadir points that every photo of a line holds); the raster covers it and the cloud. The cells one pair
    measured near confirmed ones check the interpolation instead (Surface.one_pair, one_pair_check): where the
    DSM is interpolated their heights are compared with it. `clouds`: covering_clouds(*map_clouds(fusion,
    origin, crs, heights, min_pairs), ...) if already made (the products' cloud, and the cells fewer pairs
    measured that it leaves out).
    """
    cams = cameras_in_crs(origin, camera_centres_map, crs, heights)
    if clouds is None:
        clouds = covering_clouds(*map_clouds(fusion, origin, crs, heights, min_pairs), res_m, rules, cams, min_pairs)
    cloud, fewer = clouds
    confirmed = (cloud.pairs >= min_pairs) if (min_pairs > 1 and cloud.pairs is not None) else np.ones(cloud.x.size,
                                                                                                          bool)
    two, one_pair = cloud.subset(confirmed), cloud.subset(~confirmed)
    ground_m = float(np.median(two.z if two.x.size else cloud.z))
    bounds = _box(cloud) if cams is None else _union(_box(cloud), _footprint_box(cams, ground_m, res_m))
    grid = dsm_in_crs(two, res_m, rules, bounds)
    measured = grid.valid()
    ground_m = float(np.median(grid.data[measured])) if measured.any() else ground_m
    pairs = np.where(measured, cell_max(two.x, two.y, two.pairs, grid).astype(np.float32), NODATA)
    if one_pair.x.size:
        one = _one_pair_grid(one_pair, rules, grid)
        put = one.valid() & ~measured & (cell_max(one_pair.x, one_pair.y, np.ones(one_pair.x.size), grid) > 0)
        grid.data[put] = one.data[put]
        pairs[put] = np.maximum(cell_max(one_pair.x, one_pair.y, one_pair.pairs, grid), 1)[put]
    measured = grid.valid()
    cam_hull = region = np.zeros(grid.shape, bool)
    if measured.any():
        cam_hull, region = _footprint(grid, cams, ground_m)
    if rules.fill and region.any():
        d = fill_surface(grid.data, region)
        pairs[(d != NODATA) & (pairs == NODATA)] = FILLED
        grid = Raster(d, grid.x0_m, grid.y1_m, grid.res_m, NODATA)
    pairs[(grid.data != NODATA) & (pairs == NODATA)] = FILLED
    surface = Surface(grid, pairs, region, cam_hull)
    if fewer is not None:
        surface.one_pair, surface.one_pair_dz_m = _one_pair_check(fewer, rules, surface)
    return surface


def _one_pair_check(fewer: GeoCloud, rules: DsmParams, surface: Surface) -> tuple[np.ndarray, np.ndarray]:
    """The interpolated cells of `surface` that the cells of `fewer` (measured by fewer pairs than the DSM
    asks, not used for its heights) fall in, gridded by _one_pair_grid, and there that height minus the
    interpolated one (NaN elsewhere)."""
    shape = surface.dsm.shape
    where, dz = np.zeros(shape, bool), np.full(shape, np.nan, np.float32)
    if not fewer.x.size:
        return where, dz
    grid = surface.dsm
    one = _one_pair_grid(fewer, rules, grid)
    where = (surface.pairs == FILLED) & one.valid()
    dz[where] = one.data[where] - grid.data[where]
    return where, dz


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
