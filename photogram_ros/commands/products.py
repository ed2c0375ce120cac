"""The survey products of a flight's map folder, shared by `replay`, `run` (when it stops) and `export`.

Dense matching from the final adjustment (io/densify.py) uses the parameter file's stereo_node and
map_node sections, so the same stereo, pair choice and fusion as in flight.
"""

from __future__ import annotations

import sys


def densify_with_params(map_dir, out_dir, params_file: str | None, progress: bool = True):
    from photogram_ros.core.fusion import FusionConfig
    from photogram_ros.core.pairs import PairCriteria
    from photogram_ros.io.densify import densify_map
    from photogram_ros.nodes.map_node import MapParams
    from photogram_ros.nodes.stereo_node import StereoNodeParams
    from photogram_ros.params import from_dict, load_params_file

    sections = load_params_file(params_file) if params_file else {}
    sp = from_dict(StereoNodeParams, sections.get('stereo_node', {}), f'{params_file} stereo_node')
    mp = from_dict(MapParams, sections.get('map_node', {}), f'{params_file} map_node')
    criteria = PairCriteria(sp.target_baseline_ratio, sp.min_baseline_ratio, sp.max_baseline_ratio, sp.min_overlap,
                            sp.max_pairs_along, sp.max_pairs_across, sp.max_axis_angle_deg)
    fusion = FusionConfig(mp.cell_m, mp.tile_cells, mp.max_tiles_in_memory, mp.k_sigma, mp.min_tolerance_m,
                          mp.min_confidence)

    def report(done, total):
        if progress and (done == total or done % 25 == 0):
            print(f'\rdense matching from the final adjustment: {done}/{total} keyframes', end='',
                  file=sys.stderr, flush=True)
            if done == total:
                print(file=sys.stderr)

    return densify_map(map_dir, out_dir, sp, criteria, sp.relief_m, fusion, report)


def export_products(map_dir, out, params_file: str | None, crs: str = '', live_map: bool = False,
                    heights: str = 'ellipsoidal', min_pairs: int = 2, progress: bool = False, run: dict | None = None,
                    **report) -> dict:
    """Matched again from the final adjustment (unless live_map), exported in `crs` (UTM of the origin
    by default), with the flight report (`run` and `report`: build_report's run, truth, control,
    diagnostics). Returns {'files', 'notes', 'crs', 'figures', 'points'}."""
    from pathlib import Path

    from photogram_ros.core.geodesy import utm_epsg
    from photogram_ros.errors import PhotogramError
    from photogram_ros.io.export import export_map
    from photogram_ros.io.flight_report import build_report
    from photogram_ros.io.map_store import MapStore

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    run = dict(run or {})
    store = MapStore(map_dir)
    if store.origin is None or not store.keyframes():
        notes = ['the map has no georeferenced keyframes (no camera frames, or no GNSS fix good enough): no exports']
        figures = build_report(out, map_dir, crs or 'EPSG:4326', {}, run=run, **report)
        return {'files': {}, 'notes': notes, 'crs': crs, 'figures': figures, 'points': 0}
    crs = crs or f'EPSG:{utm_epsg(store.origin.lat_deg, store.origin.lon_deg)}'
    products_map, notes = Path(map_dir), []
    if not live_map:
        try:
            d = densify_with_params(map_dir, out / 'map_final', params_file, progress=progress)
            products_map = d.map_dir
            run.update(products_from='final adjustment (map_final)', densify_s=round(d.seconds, 2),
                       densify_pairs=d.pairs_done)
        except PhotogramError as exc:
            notes.append(f'products from the in-flight map: dense matching from the final poses failed ({exc})')
    run.setdefault('products_from', 'in-flight map (map)')
    ex = export_map(products_map, out, crs, heights, min_pairs=min_pairs)
    files = {k: str(v) for k, v in ex.files.items()}
    run['map_points'] = ex.points
    figures = build_report(out, products_map, crs, files, run=run, **report)
    return {'files': files, 'notes': notes + ex.notes, 'crs': crs, 'figures': figures, 'points': ex.points}
