"""Survey products from a map folder: LAS 1.4 / LAZ, PLY, DSM, DTM and orthomosaic GeoTIFFs, in any CRS.

`export_map` opens the map, makes its cloud in the output CRS and runs each chosen product of the registry
(io/products/: one module per product) in its order, then writes export.json. The cloud and its files are
in io/export_cloud.py, the rasters in io/export_raster.py, writing a file whole in io/export_files.py; their
public names are importable from here too.

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

The DSM holds the cells stereo measured (min_pairs pairs, or one pair where no confirmed cell is near:
covering_clouds) and, inside what the photos saw (the camera centres' hull, widened), heights interpolated
where stereo measured none (surface_in_crs); its band 2 gives the stereo pairs that measured each cell (1: one
pair, unconfirmed), 0 where interpolated; export.json's dsm.footprint gives those shares over the footprint. The DTM (core.dtm) is the ground class of the cloud on
the DSM's grid, interpolated under buildings and vegetation; contours of it on request (io/contours.py).

Rasters are built in the output CRS's own grid (north-up in that CRS), so GIS tools need no
reprojection: the DSM from the fused cells' CRS coordinates, the orthomosaic by mapping each of
its cells back to map ENU and draping the keyframes (core.raster.orthomosaic).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from photogram_ros.core import geoid
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.errors import ConfigError, DataError, StorageError
from photogram_ros.io.export_cloud import (EGM2008_HEIGHT, HEIGHTS, GeoCloud, check_projected, classify_cloud,
                                           crs_to_enu, enu_to_crs, map_cloud, map_clouds, open_map, product_crs, read_ply,
                                           write_las, write_ply)
from photogram_ros.io.export_files import ExportResult, ProductsIncomplete, part_path, write_whole
from photogram_ros.io.export_raster import (COG_BLOCK_PX, FILL_MARGIN_AGL, FILLED, DsmParams, StoredKeyframes,
                                            Surface, cameras_in_crs, covering_clouds, dsm_in_crs, ortho_in_crs,
                                            read_crs, surface_in_crs, write_geotiff)
from photogram_ros.io.map_store import MapStore, as_map_store
from photogram_ros.io.products import PRODUCTS, ExportJob, Writers, plan, product_names
from photogram_ros.io.progress import Steps
from photogram_ros.params import validate


def export_map(map_dir: str | Path | MapStore, out_dir: str | Path, crs: str, heights: str = 'ellipsoidal',
               dsm_res_m: float = 0.0, ortho_res_m: float = 0.0, products: Sequence[str] | None = None,
               origin: LocalFrame | None = None, min_pairs: int = 1, dsm: DsmParams | None = None,
               contour_interval_m: float = 0.0, say=None, damaged: list | None = None) -> ExportResult:
    """Write the requested products of a map folder (or an open MapStore) into out_dir (created).

    `products`: names of the registry's products (io/products: las, laz, ply, dsm, dtm, ortho; None: all).
    min_pairs=2 exports the cells confirmed by two stereo pairs, and cells one pair saw only where no confirmed
    cell is near (io/export_raster.covering_clouds; band 2 of dsm.tif says 1 there): a cell one pair saw cannot
    be checked for gross matching errors (on the sample flight they hold most of the large errors), but on a
    survey with one pair per spot it is the only evidence.
    `dsm`: the DSM rules (default DsmParams(): lengths from the map's cell size).
    contour_interval_m > 0 also writes contours.gpkg: the DTM's contour lines at that interval (io/contours.py).
    say(text): progress lines (io/progress.py): each product as it starts, the orthomosaic's keyframes
    counted; None: none. The map's tiles are checked first (MapStore.check_tiles): each damaged tile is
    named in the notes and export.json's damaged_tiles, with what rebuilds its points; `damaged`: tiles of
    another map these products were rebuilt for (named the same way, as rebuilt).
    """
    products = product_names() if products is None else tuple(products)
    unknown = [k for k in products if k not in product_names()]
    if unknown:
        raise ConfigError(f'unknown products {unknown}; choose from {list(product_names())}')
    if contour_interval_m < 0:
        raise ConfigError(f'the contour interval must be positive (0: no contours), not {contour_interval_m} m')
    dsm = dsm or DsmParams()
    validate(dsm)
    check_projected(crs)
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
    job = ExportJob(store, fusion, origin, crs, heights, out, products, min_pairs, dsm_res_m or 2.0 * store.cell_m,
                    ortho_res_m or store.cell_m, dsm.for_cell(store.cell_m), contour_interval_m,
                    np.array([k['map_T_cam'][:3, 3] for k in store.keyframes()]).reshape(-1, 3), None, res,
                    None, Writers(write_las, write_ply, write_geotiff), say)
    res.keyframes = len(job.centres)   # the posed keyframes; the orthomosaic counts those it drapes
    chosen = [p for p in PRODUCTS if p.chosen(job)]
    job.steps = steps = Steps('export', len(plan(chosen)), say)
    steps.start('cloud')
    job.cloud, job.fewer = covering_clouds(*map_clouds(fusion, origin, crs, heights, min_pairs), job.dsm_res_m,
                                           job.rules, cameras_in_crs(origin, job.centres, crs, heights), min_pairs)
    res.points = job.cloud.x.size
    vertical_crs, note = product_crs(crs, heights)
    res.crs_with_heights = vertical_crs.name
    if note:
        res.notes.append(note)
    rules = job.rules
    res.dsm = {'cell_m': store.cell_m, 'res_m': job.dsm_res_m, 'max_spread_m': rules.max_spread_m,
               'min_count': rules.min_count, 'fill_gaps_m': rules.fill_gaps_m, 'canopy_top': rules.canopy_top,
               'one_pair_beyond_m': rules.one_pair_beyond_m}
    for product in chosen:
        for name in product.needs:
            job.need(name)
        if product.step:
            steps.start(product.step)
        product.write(job)
    failed = job.failed
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


__all__ = ['COG_BLOCK_PX', 'EGM2008_HEIGHT', 'FILLED', 'FILL_MARGIN_AGL', 'HEIGHTS', 'DsmParams', 'ExportResult',
           'GeoCloud', 'ProductsIncomplete', 'StoredKeyframes', 'Surface', 'classify_cloud', 'crs_to_enu',
           'dsm_in_crs', 'enu_to_crs', 'export_map', 'map_cloud', 'open_map', 'ortho_in_crs', 'part_path',
           'product_crs', 'read_crs', 'read_ply', 'surface_in_crs', 'write_geotiff', 'write_las', 'write_ply',
           'write_whole']
