"""photogram-ros export: survey products of a map folder (LAS/LAZ, PLY, DSM, DTM and orthomosaic GeoTIFFs)."""

from __future__ import annotations

import sys

from photogram_ros.commands import common_args
from photogram_ros.io.products import product_names

HELP = 'write LAS/LAZ, PLY, DSM, DTM and orthomosaic GeoTIFFs of a map folder in any EPSG CRS'
PRODUCTS = product_names()   # the export registry's products by name (io/products/), in its order
EXIT_EXPORT_FAILED = 3   # some products not written (a full disk): the others are whole, export.json says which


def add_arguments(p) -> None:
    p.add_argument('map_dir', help='map folder written by map_node (map_dir parameter)')
    p.add_argument('--crs', required=True, help='output CRS, e.g. EPSG:32632 (UTM 32N) or EPSG:2056 (Swiss LV95)')
    p.add_argument('--out', required=True, help='output folder (created)')
    common_args.add_heights(p)
    p.add_argument('--dsm-res-m', type=float, default=0.0,
                   help='DSM cell size in metres (default: 2 fusion cells, about 2 GSD)')
    p.add_argument('--ortho-res-m', type=float, default=0.0,
                   help='orthomosaic cell size in metres (default: one fusion cell, about 1 GSD)')
    p.add_argument('--products', default=','.join(PRODUCTS), help=f'comma-separated subset of {",".join(PRODUCTS)}')
    p.add_argument('--min-pairs', type=int, default=2,
                   help='keep cells confirmed by this many stereo pairs (2, as replay does: a cell one pair saw '
                        'cannot be checked for gross matching errors; 1 keeps every fused cell)')
    p.add_argument('--contours-m', type=float, default=0.0,
                   help='also write contours.gpkg: contour lines of the DTM every this many metres (0: none)')
    p.add_argument('--origin', default='', help='LAT,LON,H of the map origin, if map.json lacks it')
    p.add_argument('--densify', action='store_true',
                   help='first match the keyframes again with their poses (the final ones when the flight ended '
                        'with its final adjustment) into OUT/map_final (the in-flight map paired them with the '
                        'poses they had when they left the bundle window) and export that')
    p.add_argument('--params', default=None,
                   help='parameter file whose stereo_node and map_node sections --densify uses (the flight\'s; '
                        'default: the package\'s config/replay.yaml)')
    p.add_argument('--keep-damaged', action='store_true',
                   help='export what the map\'s tiles hold when some are damaged or missing (named in the output '
                        'and export.json) instead of rebuilding the cloud from the keyframes as --densify does')
    p.add_argument('--quiet', action='store_true', help='no progress lines (on stderr)')


def poses_label(end: dict | None) -> str:
    """What the poses of a map are, from its flight_end.json (`end`; None: there is none): "the final
    poses" only when the final adjustment is recorded as done."""
    if end is None:
        return ('the in-flight poses (the flight did not end cleanly: no flight_end.json, so no final adjustment '
                'is known to have been made, e.g. a kill -9 or a power loss)')
    state = end.get('final_adjustment')
    if state == 'done':
        return 'the final poses (final adjustment)'
    if state == 'unknown':
        return 'the poses in the map (run --separate: bundle_node adjusts at its own exit, not checked)'
    why = end.get('reason') or state
    if state == 'failed':
        return f'the in-flight poses (the final adjustment failed: {why})'
    return f'the in-flight poses (no final adjustment: {why})'


def run(a) -> int:
    from photogram_ros.errors import ConfigError, DataError
    from photogram_ros.io.export import ProductsIncomplete, export_map
    from photogram_ros.io.map_store import MapStore
    from photogram_ros.io.progress import say_stderr

    products = tuple(s.strip() for s in a.products.split(',') if s.strip())
    bad = [s for s in products if s not in PRODUCTS]
    if bad:
        raise ConfigError(f'unknown products {bad}; choose from {list(PRODUCTS)}')
    if a.min_pairs < 1:
        raise ConfigError(f'--min-pairs must be at least 1, not {a.min_pairs}')
    for opt, v, what in (('--dsm-res-m', a.dsm_res_m, 'the DSM cell size'), ('--ortho-res-m', a.ortho_res_m,
                                                                            'the orthomosaic cell size'),
                         ('--contours-m', a.contours_m, 'the contour interval')):
        if not 0 <= v < 1e6:   # said before any matching or writing, not after minutes of it
            raise ConfigError(f'{opt} {v:g}: {what} in metres, more than 0 (0: the default)')
    if a.crs:
        from photogram_ros.commands.products import check_output_crs
        check_output_crs(a.crs)   # before any matching or writing
    from photogram_ros.commands.products import parse_origin
    origin = parse_origin(a.origin) if a.origin else None
    store = MapStore(a.map_dir)
    unposed = store.unposed_keyframe_images()
    if unposed:
        print(f'note: {len(unposed)} keyframe images have no pose (taken before the flight was cut short, never '
              f'oriented): not in the products; {len(store.keyframes())} posed keyframes are', flush=True)
    damage = store.check_tiles()
    for d in damage:
        print(f'damaged map tile {store.tiles_dir / d.path.name}: {d.what}', flush=True)
    rebuilt, auto = [], False
    if damage and not a.densify:
        if a.keep_damaged:
            print(f'--keep-damaged: the products hold what the other tiles hold; photogram-ros export {a.map_dir} '
                  '--densify rebuilds the lost points from the keyframes', flush=True)
        else:
            print(f'rebuilding the cloud from the {len(store.keyframes())} keyframes (as --densify; --keep-damaged '
                  'exports what the tiles hold)', flush=True)
            a.densify = auto = True
    if a.densify and damage:
        rebuilt = [f'{store.tiles_dir / d.path.name}: {d.what}' for d in damage]
    if a.densify:
        from pathlib import Path

        from photogram_ros.commands.products import densify_with_params
        from photogram_ros.package_files import config_file
        found = config_file('replay.yaml')   # the package's, wherever the command runs
        params = a.params if a.params is not None or found is None else str(found)
        try:
            d = densify_with_params(store, Path(a.out) / 'map_final', params, progress=not a.quiet)
        except DataError as exc:
            if not auto:
                raise
            print(f'the damaged tiles cannot be rebuilt ({exc}): the products hold what the other tiles hold',
                  flush=True)
            a.densify, rebuilt = False, []
    if a.densify:
        print(f'{d.pairs_done} pairs matched again from {poses_label(store.flight_end())} in {d.seconds:.1f} s '
              f'-> {d.map_dir}'
              + (f'; skipped {d.pairs_skipped}' if d.pairs_skipped else ''))
        for why in d.pairs_failed:
            print(f'  pair not matched: {why}')
        if d.derived:
            from photogram_ros.core.gsd import GsdSettings
            print(f'  from the GSD ({", ".join(d.derived)}): {GsdSettings(**d.gsd).summary()}')
        store = d.store
    try:
        res = export_map(store, a.out, a.crs, a.heights, a.dsm_res_m, a.ortho_res_m, products, origin,
                         min_pairs=a.min_pairs, contour_interval_m=a.contours_m, say=None if a.quiet else say_stderr,
                         damaged=rebuilt)
    except ProductsIncomplete as exc:   # a full disk: each product is whole or absent
        for k, v in exc.result.files.items():
            print(f'  {k}: {v}')
        print(f'photogram-ros export: products not written: {exc}', file=sys.stderr)
        return EXIT_EXPORT_FAILED
    print(f'{res.points} points, {res.keyframes} keyframes -> {a.out} ({res.crs_with_heights}, {a.heights} heights)')
    if res.classes:
        c = res.classes
        print(f'  classes: {c["ground"]} ground, {c["building"]} building ({c["buildings"]} buildings), '
              f'{c["unclassified"]} unclassified')
    hull = (res.dsm or {}).get('camera_hull')
    if hull:
        print(f"  DSM inside the camera centres' hull: {hull['valid'] * 100:.1f} % of the cells hold a height, "
              f"{hull['measured'] * 100:.1f} % measured by stereo ({hull.get('measured_one_pair', 0.0) * 100:.1f} % "
              f"by one pair only, where no confirmed cell is near), {hull['filled'] * 100:.1f} % interpolated "
              '(band 2 of dsm.tif: pairs, 0 interpolated)')
    foot = (res.dsm or {}).get('footprint')
    if foot:
        print(f"  over the cameras' footprint (the hull widened by a quarter of the flying height): "
              f"{foot['measured'] * 100:.1f} % measured by stereo, {foot.get('measured_one_pair', 0.0) * 100:.1f} % "
              f"by one pair only, {foot['valid'] * 100:.1f} % hold a height")
    check = (res.dsm or {}).get('one_pair_check')
    if hull and check and check.get('cells'):
        print(f"  of the interpolated cells {hull['filled_one_pair'] * 100:.1f} % of the hull were measured by one "
              f"stereo pair near confirmed cells: it differs from the interpolation by "
              f"{check['median_abs_dz_m']:.2f} m (median), {check['p90_abs_dz_m']:.2f} m (p90)")
    for k, v in res.files.items():
        print(f'  {k}: {v}')
    for n in res.notes:
        print(f'  note: {n}')
    return 0
