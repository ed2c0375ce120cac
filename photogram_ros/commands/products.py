"""The survey products of a flight's map folder, shared by `replay`, `run` (when it stops) and `export`.

Dense matching from the final adjustment (io/densify.py) uses the parameter file's stereo_node and
map_node sections, so the same stereo, pair choice and fusion as in flight. Offline, without ROS: the
sections are read into the core parameter sets the nodes' parameters are made of (core/stereo.py
StereoParams, core/pairs.py PairCriteria, core/fusion.py FusionConfig), whose names and values are
checked here; the nodes' own names (topics, rates, the map folder) are the nodes' to check.
"""

from __future__ import annotations


def _core_params(cls, section: dict, where: str):
    """`cls` validated from the names of a node's section that it declares."""
    from photogram_ros.params import fields_of, from_dict
    names = {f.name for f in fields_of(cls)}
    return from_dict(cls, {k: v for k, v in section.items() if k in names}, where)


def parse_origin(text: str):
    """'LAT,LON,H' (degrees, metres) of a command's --origin -> LocalFrame; a ConfigError naming the option."""
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.errors import ConfigError
    try:
        lat, lon, h = (float(v) for v in text.split(','))
    except ValueError as exc:
        raise ConfigError(f'--origin must be LAT,LON,H in degrees and metres, not {text!r}') from exc
    return LocalFrame(lat, lon, h)


def check_output_crs(crs: str) -> None:
    """A GeodesyError now, before any replay or flight, unless `crs` is a projected CRS PROJ knows
    (the products need metric easting/northing)."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    from photogram_ros.errors import GeodesyError
    try:
        c = CRS.from_user_input(crs)
    except CRSError as exc:
        raise GeodesyError(f'unknown output CRS {crs!r} ({exc}); name one as EPSG:XXXX, e.g. EPSG:32632 '
                           '(UTM 32N) or EPSG:2056 (Swiss LV95)') from exc
    if not c.is_projected:
        raise GeodesyError(f'{crs} ({c.name}) is not a projected CRS: rasters and clouds need metric '
                           'easting/northing (e.g. the UTM zone EPSG:326xx, or a national grid such as EPSG:2056)')


def _products_from(end: dict | None, matched_again: bool) -> tuple[str, list]:
    """What the report says the products come from, and a note when the final adjustment is missing."""
    if end is not None and end.get('final_adjustment') == 'unknown':   # run --separate: bundle_node's own exit
        return ('final adjustment (map_final; bundle_node adjusts at its own exit, not checked with --separate)'
                if matched_again else 'in-flight map (map)'), []
    if end is not None and end.get('final_adjustment') not in ('done', None):
        why = end.get('reason') or end['final_adjustment']
        what = 'in-flight poses' + (', matched again (map_final)' if matched_again else ' (map)')
        if end['final_adjustment'] == 'failed':
            return f'{what}: the final adjustment failed ({why})', [
                f'the final adjustment failed ({why}): the products come from the in-flight poses']
        return f'{what}: no final adjustment ({why})', []
    return ('final adjustment (map_final)' if matched_again else 'in-flight map (map)'), []


def densify_with_params(map_dir, out_dir, params_file: str | None, progress=True):
    """io/densify.densify_map of `map_dir` (a folder or an open MapStore) with the file's parameters.
    progress: True (lines on stderr: keyframes matched, percent, ETA), False, or a say(text) function."""
    from photogram_ros.io.progress import Progress, say_stderr, sayer
    from photogram_ros.core.fusion import FusionConfig
    from photogram_ros.core.pairs import PairCriteria
    from photogram_ros.core.stereo import StereoParams
    from photogram_ros.io.densify import densify_map
    from photogram_ros.params import load_params_file

    sections = load_params_file(params_file) if params_file else {}
    stereo_section, map_section = sections.get('stereo_node', {}), sections.get('map_node', {})
    stereo = _core_params(StereoParams, stereo_section, f'{params_file} stereo_node')
    criteria = _core_params(PairCriteria, stereo_section, f'{params_file} stereo_node')
    fusion = _core_params(FusionConfig, map_section, f'{params_file} map_node')

    matching = Progress('export: dense matching', None, 'keyframes', sayer(progress, say_stderr))
    return densify_map(map_dir, out_dir, stereo, criteria, fusion, matching.callback())


def export_products(map_dir, out, params_file: str | None, crs: str = '', live_map: bool = False,
                    heights: str = 'ellipsoidal', min_pairs: int = 2, progress=False, run: dict | None = None,
                    **report) -> dict:
    """Matched again from the final adjustment (unless live_map), exported in `crs` (UTM of the origin
    by default), with the flight report (`run` and `report`: build_report's run, truth, control,
    diagnostics). progress: True (lines on stdout: the dense matching's keyframes, each product), False,
    or a say(text) function. Returns {'files', 'notes', 'crs', 'figures', 'points'}."""
    from photogram_ros.io.progress import sayer
    from pathlib import Path

    from photogram_ros.core.geodesy import utm_epsg
    from photogram_ros.errors import PhotogramError, StorageError
    from photogram_ros.io.densify import GROUND_ASSUMED
    from photogram_ros.io.export import export_map
    from photogram_ros.io.flight_report import build_report
    from photogram_ros.io.map_store import MapStore

    if crs:
        check_output_crs(crs)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    run = dict(run or {})
    run['heights'] = heights   # the report states and lists it (the same option in run, replay and export)
    store = MapStore(map_dir)    # opened once: densify reads it, export and the report read the products' map
    end = store.flight_end()
    if end is not None:
        run.setdefault('final_adjustment', end.get('final_adjustment'))
    if store.origin is None or not store.keyframes():
        notes = ['the map has no georeferenced keyframes (no camera frames, or no GNSS fix good enough): no exports']
        figures = build_report(out, store, crs or 'EPSG:4326', {}, run=run, **report)
        return {'files': {}, 'notes': notes, 'crs': crs, 'figures': figures, 'points': 0}
    crs = crs or f'EPSG:{utm_epsg(store.origin.lat_deg, store.origin.lon_deg)}'
    products, notes = store, []
    if not live_map:
        try:
            d = densify_with_params(store, out / 'map_final', params_file, progress=sayer(progress))
            products = d.store
            run.update(densify_s=round(d.seconds, 2), densify_pairs=d.pairs_done, densify_stereo_s=round(d.stereo_s, 2),
                       densify_pairs_skipped=dict(d.pairs_skipped), gsd=d.gsd, gsd_derived=d.derived,
                       densify_ground_m=round(d.ground_m, 3), densify_ground_from=d.ground_from)
            if d.ground_from == GROUND_ASSUMED:
                notes.append(f'the dense matching searched around a ground {GROUND_ASSUMED} (the in-flight map fused '
                             'too little and the map folder kept no tie points\' height): pairs whose ground lies '
                             'further down found no depth')
            if d.pairs_failed:
                run['densify_pairs_failed'] = d.pairs_failed
                notes.append(f'{d.pairs_skipped.get("failed", 0)} pair(s) could not be matched from the final poses '
                             f'and were skipped (first: {d.pairs_failed[0]})')
        except StorageError:   # a full disk: exporting next would fail the same way
            raise
        except PhotogramError as exc:
            notes.append(f'products from the in-flight map: dense matching from the final poses failed ({exc})')
    source, source_notes = _products_from(end, products is not store)
    run['products_from'] = source
    notes += source_notes
    try:
        try:
            ex = export_map(products, out, crs, heights, min_pairs=min_pairs, say=sayer(progress))
        except StorageError:
            raise
        except PhotogramError as exc:   # nothing to export (no cell seen by min_pairs pairs): still a report
            run['products_error'] = str(exc)
            figures = build_report(out, products, crs, {}, run=run, **report)
            return {'files': {}, 'notes': notes + [f'no products: {exc}'], 'crs': crs, 'figures': figures,
                    'points': 0}
        files = {k: str(v) for k, v in ex.files.items()}
        run['map_points'] = ex.points
        run['dsm'] = ex.dsm
        run['dtm'] = ex.dtm
        run['ortho'] = ex.ortho
        figures = build_report(out, products, crs, files, run=run, **report)
    except StorageError:
        raise
    except OSError as exc:   # a full disk, a folder gone: what to do about it, not a traceback
        raise StorageError(f'the products could not be written to {out} ({exc.strerror or exc}); the map is '
                           f'safe in {map_dir if not isinstance(map_dir, MapStore) else map_dir.root}: free space '
                           'and run photogram-ros export MAPDIR --densify', exc.errno) from exc
    return {'files': files, 'notes': notes + ex.notes, 'crs': crs, 'figures': figures, 'points': ex.points}
