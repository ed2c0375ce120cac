"""The end-of-flight report: from a map folder and its exports (and the truth, for simulator bags).

Everything is read back from disk (map folder, GeoTIFFs, LAS), so the report describes exactly what
a user receives and can be rebuilt after the flight. Figures:
- adjusted trajectory (CSV and GeoJSON, in the output CRS and WGS84, with omega-phi-kappa);
- check points: the tracker's detections the bundle adjuster kept in the map folder (else the markers found
  again in the keyframes), intersected from the adjusted poses as the live accuracy does, against their
  survey; with a control file, its GCPs' residuals apart (they constrained the adjustment);
- with ground truth: camera-centre errors, DSM (its measured and interpolated cells apart) and cloud
  against the true DEM, the DTM against it away from buildings, in metres and GSD;
- the DSM's measured / interpolated split inside the camera centres' hull, an overlap map (photos per
  DSM cell), check-point errors as arrows on the orthomosaic, the camera model;
- what went wrong and when (from /diagnostics), and timing per node;
- at the top, whether the flight mapped at all (`mapping_verdict`: a georeferenced keyframe, half of
  the keyframes oriented, half of the DSM's cells holding a height), how many keyframes the tracker
  took and how many were oriented, why the others were not (`keyframe_accounting`, from the nodes'
  counters: reasons that add up to the keyframes not oriented, the adjuster's in-flight reasons apart), and
  every node's worst /diagnostics level with its reasons (`node_health`).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np

from photogram_ros.core.at_report import redundancy_notes
from photogram_ros.core.control import ControlVettingOptions
from photogram_ros.core.evaluation import (MAX_INTERSECTION_DOP, ce90_le90, detect_targets, intersect_targets,
                                           surface_errors, trajectory_errors)
from photogram_ros.core.geodesy import LocalFrame, crs_to_geodetic, geodetic_to_crs
from photogram_ros.io.at_report import ce90_text
from photogram_ros.io import flight_inputs
from photogram_ros.io.flight_overview import (calibration_rows, capture_section, dsm_preview_png, gnss_section,
                                             place_labels, product_heights)
from photogram_ros.io.flight_verdict import (dsm_footprint_cover, dsm_one_pair_evidence, dsm_valid_share,
                                             keyframe_accounting, mapping_verdict, not_oriented_text)
from photogram_ros.io.map_store import CAMERA_FINAL, MapStore
from photogram_ros.io.tf_bag import write_trajectory_mcap
from photogram_ros.io.report import Section, histogram_png, trajectory_png, write_report
from photogram_ros.io.trajectory import TRAJECTORY_COLUMNS, write_trajectory_csv


def _target_figures(res, gsd_m: float | None) -> dict:
    rm = res.rmse()
    out = {'rmse': rm, 'points': res.table(), 'not_seen': res.missing, 'weak': res.weak}
    if gsd_m and rm['count']:
        out['rmse_gsd'] = {'horizontal': rm['horizontal_m'] / gsd_m, 'vertical': rm['z_m'] / gsd_m}
    return out


def weak_text(weak: list[dict]) -> str:
    """The targets intersected too weakly to count (core.evaluation.intersect_targets), in words."""
    def dop(v):
        return 'unfixed' if v is None else f'{v:.1f}'
    names = ', '.join(f"{w['name']} ({w['views']} images, DOP {dop(w['dop_h'])} H / {dop(w['dop_v'])} V)" for w in weak)
    return (f'Not counted (their images fix them too weakly, a dilution of precision above '
            f'{MAX_INTERSECTION_DOP:g}: too few images, too close together): {names}.')


def target_observations(store: MapStore, kfs: list[dict], surveyed: dict) -> tuple[dict, float, str]:
    """The detections of the surveyed targets (marker id -> (name, xyz)) in the map folder's keyframes `kfs`:
    ({marker id: [(keyframe index, (u, v))]}, the largest pixel residual a detection may have, where they come
    from). The bundle adjuster's own (control_points.json: the tracker's detections it intersected the live
    check points and GCPs from, by the same method) when the folder holds them, so the report's figures are
    the ones the ground station showed; else the markers found again in the saved keyframe images."""
    doc = store.control_points()
    if isinstance((doc or {}).get('detections'), dict):
        index = {int(k['stamp_ns']): i for i, k in enumerate(kfs)}
        by_name = {name: [(index[int(s)], np.array([u, v], float)) for s, u, v in dets if int(s) in index]
                   for name, dets in doc['detections'].items()}
        max_px = float(doc.get('max_row_residual_px') or ControlVettingOptions().max_row_residual_px)
        return ({m: by_name.get(name, []) for m, (name, _) in surveyed.items()}, max_px,
                'found by the tracker in flight (the detections the bundle adjuster intersected them from)')
    obs: dict = {m: [] for m in surveyed}
    for i, kf in enumerate(kfs):
        img = cv2.imread(str(kf['image_path']), cv2.IMREAD_GRAYSCALE)
        for d in (detect_targets(img) if img is not None else []):
            if d.marker_id in obs:
                obs[d.marker_id].append((i, d.center_uv))
    return obs, ControlVettingOptions().max_row_residual_px, 'found in the saved keyframe images'


def write_trajectory(out: Path, keyframes: list[dict], origin: LocalFrame, crs: str) -> dict:
    """Adjusted keyframe poses as CSV (CRS + WGS84 + omega-phi-kappa, io/trajectory.py), GeoJSON and a ROS 2
    recording of their frame tree (the rosbag2 folder trajectory/, its trajectory.mcap: /tf, /tf_static, map/path;
    io/tf_bag.py)."""
    if not keyframes:
        return {}
    bag = out / 'trajectory'
    if (bag / 'metadata.yaml').exists() or (bag / 'trajectory.mcap').exists():
        shutil.rmtree(bag)      # the recording of an earlier report in this folder
    write_trajectory_mcap(bag, [k['stamp_ns'] for k in keyframes], [k['map_T_cam'] for k in keyframes])
    t = write_trajectory_csv(out / 'trajectory.csv', TRAJECTORY_COLUMNS,
                             [Path(k['image_path']).name for k in keyframes],
                             np.array([k['map_T_cam'] for k in keyframes]), origin, crs,
                             [k['stamp_ns'] for k in keyframes])
    C, lat, lon, h = t['centres_map'], t['lat_deg'], t['lon_deg'], t['h_m']
    geo = {'type': 'FeatureCollection', 'features': [
        {'type': 'Feature', 'geometry': {'type': 'LineString',
                                         'coordinates': [[float(lon[k]), float(lat[k]), float(h[k])]
                                                         for k in range(len(C))]},
         'properties': {'name': 'adjusted keyframe trajectory', 'heights': 'WGS84 ellipsoidal'}}]}
    (out / 'trajectory.geojson').write_text(json.dumps(geo))
    return {'easting': t['easting_m'], 'northing': t['northing_m'], 'centres_map': C}


def near_discontinuity(dem, x_m, y_m, slope: float = 1.0, radius_m: float = 1.0) -> np.ndarray:
    """True where a point lies within `radius_m` of terrain steeper than `slope` (walls, roof edges)."""
    gy, gx = np.gradient(dem.data.astype(np.float64), dem.res_m)
    steep = (np.hypot(gx, gy) > slope).astype(np.uint8)
    k = 2 * int(np.ceil(radius_m / dem.res_m)) + 1
    steep = cv2.dilate(steep, np.ones((k, k), np.uint8)) > 0
    i = np.clip(np.round((np.asarray(x_m) - dem.x0_m) / dem.res_m).astype(int), 0, dem.shape[1] - 1)
    j = np.clip(np.round((np.asarray(y_m) - dem.y0_m) / dem.res_m).astype(int), 0, dem.shape[0] - 1)
    return steep[j, i]


def near_buildings(dem, x_m, y_m, radius_m: float = 2.0, min_height_m: float = 3.0,
                   window_m: float = 20.0) -> np.ndarray:
    """True where a point lies within `radius_m` of a building of the true DEM: cells standing more than
    `min_height_m` above the DEM's morphological opening with a `window_m` disk (a roof narrower than
    the disk; the simulator's hills and its 2.5 m embankment stay below that height)."""
    z = dem.data.astype(np.float32)
    k = max(int(round(window_m / dem.res_m)) | 1, 3)
    opened = cv2.morphologyEx(z, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)),
                              borderType=cv2.BORDER_REPLICATE)
    roof = (z - opened > min_height_m).astype(np.uint8)
    r = 2 * int(np.ceil(radius_m / dem.res_m)) + 1
    near = cv2.dilate(roof, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (r, r))) > 0
    i = np.clip(np.round((np.asarray(x_m) - dem.x0_m) / dem.res_m).astype(int), 0, dem.shape[1] - 1)
    j = np.clip(np.round((np.asarray(y_m) - dem.y0_m) / dem.res_m).astype(int), 0, dem.shape[0] - 1)
    return near[j, i]


def _raster_cells_enu(path, crs: str, to_enu, band: int = 1):
    """(ENU (N, 3) of a GeoTIFF's cells holding a value, band 2 at those cells or None, cell size)."""
    import rasterio
    with rasterio.open(path) as ds:
        z = ds.read(band).astype(float)
        nod = ds.nodata
        ok = np.isfinite(z) & (z != nod if nod is not None else True)
        rows, cols = np.nonzero(ok)
        xs, ys = rasterio.transform.xy(ds.transform, rows, cols)
        second = ds.read(2)[rows, cols] if ds.count >= 2 else None
        res = float(ds.res[0])
    lat, lon, h = crs_to_geodetic(np.asarray(xs), np.asarray(ys), z[rows, cols], crs)
    return to_enu(lat, lon, h), second, res


def overlap_png(path: Path, dsm_path, kfs: list[dict], cam, origin: LocalFrame, crs: str,
                max_cells: int = 250) -> dict:
    """Photos (keyframes) whose image holds each DSM cell, on a grid of at most `max_cells` cells a side
    sampled from dsm.tif's heights, as a map; returns {'median_photos', 'share_2_or_more',
    'share_5_or_more'} over the sampled cells with a height ({} without a DSM or camera)."""
    import rasterio
    if not dsm_path or not Path(dsm_path).exists() or cam is None or not kfs:
        return {}
    with rasterio.open(dsm_path) as ds:
        step = max(1, int(np.ceil(max(ds.width, ds.height) / max_cells)))
        z = ds.read(1)[::step, ::step].astype(float)
        ok = np.isfinite(z) & (z != ds.nodata if ds.nodata is not None else True)
        rows, cols = np.nonzero(ok)
        xs, ys = rasterio.transform.xy(ds.transform, rows * step, cols * step)
        b = ds.bounds
    if not rows.size:
        return {}
    lat, lon, h = crs_to_geodetic(np.asarray(xs), np.asarray(ys), z[rows, cols], crs)
    P = origin.geodetic_to_enu(lat, lon, h)
    count = np.zeros(rows.size, np.int32)
    for kf in kfs:
        R, C = kf['map_T_cam'][:3, :3], kf['map_T_cam'][:3, 3]
        uv, front = cam.project((P - C) @ R)
        count += front & cam.in_image(uv)
    grid = np.full(z.shape, np.nan)
    grid[rows, cols] = count
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 6), dpi=100)
    im = ax.imshow(grid, extent=(b.left, b.right, b.bottom, b.top), cmap='viridis', interpolation='nearest',
                   vmin=0, vmax=max(int(count.max()), 1))
    fig.colorbar(im, ax=ax, label='photos seeing the cell')
    _save_map_figure(fig, ax, f'Overlap: photos per DSM cell ({crs})', path)
    return {'median_photos': float(np.median(count)), 'share_2_or_more': float(np.mean(count >= 2)),
            'share_5_or_more': float(np.mean(count >= 5))}


def _save_map_figure(fig, ax, title: str, path: Path) -> None:
    """A map figure (axes in CRS metres, equal scale, full coordinates) titled and written to `path`."""
    import matplotlib.pyplot as plt
    ax.set_aspect('equal')
    ax.ticklabel_format(useOffset=False, style='plain')
    ax.tick_params(labelsize=7)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def check_point_arrows_png(path: Path, ortho_tif, points: list, title: str, placed: list | None = None) -> Path:
    """Check-point errors as arrows on the orthomosaic: points [(name, easting, northing, dE, dN, dZ)] in
    metres; the arrows are scaled so the longest spans a tenth of the map, its scale printed. The labels are
    placed where they overlap no other label or point (io/flight_overview.place_labels; their display boxes
    appended to `placed` when given)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 6), dpi=100)
    extent = None
    if ortho_tif is not None and Path(ortho_tif).exists():
        import rasterio
        with rasterio.open(ortho_tif) as ds:
            step = max(1, int(max(ds.width, ds.height) / 1500))
            img = ds.read(out_shape=(ds.count, ds.height // step, ds.width // step))
            b = ds.bounds
        extent = (b.left, b.right, b.bottom, b.top)
        ax.imshow(np.moveaxis(img[:3], 0, -1), extent=extent)
    e = np.array([p[1] for p in points], float)
    n = np.array([p[2] for p in points], float)
    d = np.array([[p[3], p[4]] for p in points], float).reshape(-1, 2)
    span = (extent[1] - extent[0]) if extent else max(np.ptp(e), np.ptp(n), 1.0)
    longest = max(float(np.hypot(d[:, 0], d[:, 1]).max()) if len(d) else 0.0, 1e-6)
    scale = 0.1 * span / longest
    ax.quiver(e, n, d[:, 0] * scale, d[:, 1] * scale, angles='xy', scale_units='xy', scale=1, color='#ee3377',
              width=0.004)
    ax.plot(e, n, 'k^', ms=5)
    ax.set_aspect('equal')
    ax.ticklabel_format(useOffset=False, style='plain')
    ax.tick_params(labelsize=7)
    ax.set_title(f'{title} (arrows x{scale:.0f})')
    fig.tight_layout()
    fig.canvas.draw()       # the axes' final place: the labels are placed in display space
    boxes = place_labels(fig, ax, list(zip(e, n)), [f'{name} {np.hypot(de, dn) * 100:.1f} cm, dZ {dz * 100:+.1f} cm'
                                                      for name, _, _, de, dn, dz in points],
                         colour='white' if extent else 'black')
    if placed is not None:
        placed += boxes
    fig.savefig(path)
    plt.close(fig)
    return path


LEVEL_NAMES = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}
def node_health(diagnostics: dict) -> list[dict]:
    """Every node's worst /diagnostics level during the run, with the reasons it gave at that level."""
    rows = []
    for node, d in sorted((diagnostics or {}).items()):
        level = int(d.get('level', 0))
        levels = d.get('problem_levels', {})
        texts = list(dict.fromkeys(p[1] for p in d.get('problems', [])))
        # Reasons at the worst level; without recorded levels (an older log) every problem.
        reasons = [t for t in texts if levels.get(t, level) == level] if level else []
        rows.append({'node': node, 'worst_level': LEVEL_NAMES.get(level, str(level)),
                     'problems': len(texts), 'reasons': reasons[:5]})
    return rows


def shed_in_flight(stereo: dict, mapper: dict) -> dict:
    """What the nodes shed in flight to keep the pose chain's pace (their /diagnostics counters), the non-zero
    ones by what they mean."""
    named = (('keyframes whose stereo pairs were shed', stereo.get('keyframes_shed')),
             ('stereo pairs shed for lag', stereo.get('pairs_shed_late')),
             ('ortho batches deferred', mapper.get('ortho_batches_deferred')))
    return {k: v for k, v in named if isinstance(v, (int, float)) and not isinstance(v, bool) and v}


def input_faults(tracker: dict, mavlink: dict) -> dict:
    """The input faults the nodes counted on /diagnostics (frames dropped for a stamp that repeated or went back,
    autopilot link silences, the autopilot's clock going back), the non-zero ones by name."""
    named = (('frames_dropped_stamp_back', tracker.get('stamps_back')),
             ('frames_dropped_stamp_repeated', tracker.get('stamps_repeated')),
             ('link_silences', mavlink.get('link_silences')),
             ('link_longest_silence_s', mavlink.get('link_longest_silence_s')),
             ('link_clock_back', mavlink.get('link_clock_back')))
    return {k: v for k, v in named if isinstance(v, (int, float)) and not isinstance(v, bool) and v}


def _health_sections(figures: dict, kfs, files: dict, run: dict, diagnostics: dict | None, georeferenced: bool):
    """The verdict and the nodes' health, for the top of the report (also into `figures`)."""
    def values(name):
        return next((d for n, d in (diagnostics or {}).items() if n.endswith(name)), {}).get('values', {})
    unusable = values('tracker_node').get('unusable_frames')
    acc = keyframe_accounting((run or {}).get('counts', {}), len(kfs) if georeferenced else 0,
                              values('bundle_node').get('status'),
                              unusable if isinstance(unusable, (int, float)) else None)
    bundle = values('bundle_node')
    verdict = mapping_verdict(acc, georeferenced, dsm_valid_share(files.get('dsm')), bool(files),
                              (run or {}).get('products_error'), dsm_one_pair_evidence(files.get('dsm')),
                              {'status': bundle.get('final_verdict'), 'summary': bundle.get('final_verdict_summary')},
                              dsm_footprint_cover(files.get('dsm')))
    # The flight as a whole is a row of its own: at ERROR when it did not map, whatever the nodes said.
    level = 'ERROR' if not verdict['mapped'] else 'WARN' if verdict['warnings'] else 'OK'
    health = [{'node': 'replay', 'worst_level': level, 'problems': len(verdict['failures'] + verdict['warnings']),
               'reasons': verdict['failures'] + verdict['warnings']}] + node_health(diagnostics)
    figures.update(acc)
    figures['mapping'] = verdict
    figures['health'] = health
    if verdict['mapped']:
        share = verdict['dsm_valid_share']
        text = [f"Mapped: {acc['keyframes_oriented']} of {acc['keyframes_taken']} keyframes oriented"
                + (f", {share * 100:.0f} % of the DSM's cells over the mapped area hold a height measured by stereo."
                   if share is not None else '.')] + [f'WARNING: {w}.' for w in verdict['warnings']]
    else:
        text = ['MAPPING FAILED: ' + '; '.join(verdict['failures']) + '.']
    if acc['keyframes_not_oriented']:
        text.append(f"Keyframes (the nodes' counters): {acc['keyframes_taken']} taken, {acc['keyframes_oriented']} "
                    f"oriented, {not_oriented_text(acc)}.")
    shed = shed_in_flight(values('stereo_node'), values('map_node'))
    figures['shed_in_flight'] = shed
    if shed:
        text.append('Shed in flight (the pose chain first; export --densify matches the shed pairs again from the '
                    'stored keyframes): ' + ', '.join(f'{k} {v:g}' for k, v in shed.items()) + '.')
    faults = input_faults(values('tracker_node'), values('mavlink_node'))
    figures['input_faults'] = faults
    if faults:
        text.append('Input faults: ' + '; '.join(f'{k.replace("_", " ")}: {v}' for k, v in faults.items()) + '.')
    resumed = (run or {}).get('resumed')
    if resumed and resumed.get('keyframes'):
        text.append(f"Resumed map: {resumed['keyframes']} keyframes taken before the restart ({resumed['posed']} "
                    f"oriented then, {resumed['still_unposed']} without a pose, not oriented).")
    bad = [h for h in health[1:] if h['worst_level'] != 'OK']
    text.append(f'{len(bad)} of {len(health) - 1} nodes reported WARN or ERROR on /diagnostics'
                + (': ' + ', '.join(f"{h['node']} {h['worst_level']}" for h in bad) if bad else '') + '.'
                if len(health) > 1 else 'No /diagnostics were recorded.')
    verdict_sec = Section('Verdict', text)
    sec = Section('Health of the nodes (worst /diagnostics level during the run)')
    sec.tables.append(('Worst level and its reasons', [
        {'node': h['node'], 'worst level': h['worst_level'], 'reasons': '; '.join(h['reasons']).replace('|', '/')}
        for h in health]))
    return [verdict_sec, sec]


def _settings_lines(run: dict) -> list[str]:
    """The GSD-derived settings, the DSM's valid share and the pairs the final matching lost, in words."""
    lines = []
    if run.get('gsd'):
        from photogram_ros.core.gsd import GsdSettings
        derived = run.get('gsd_derived') or []
        lines.append('Settings from the camera: ' + GsdSettings(**run['gsd']).summary()
                     + (f" (derived: {', '.join(derived)}; the others as set)." if derived else ' (all as set).'))
    dsm = run.get('dsm') or {}
    if 'valid_share' in dsm:
        lines.append(f"DSM: {dsm['valid_share'] * 100:.1f} % of its raster's cells (the rectangle around the map; "
                     "the verdict counts the mapped area) hold a height "
                     f"(cell {dsm.get('res_m', 0):g} m, spread limit {dsm.get('max_spread_m', 0):g} m).")
    hull = dsm.get('camera_hull')
    if hull:
        ortho = (run.get('ortho') or {}).get('camera_hull')
        lines.append(f"Inside the convex hull of the camera centres {hull['valid'] * 100:.1f} % of the DSM's cells "
                     f"hold a height: {hull['measured'] * 100:.1f} % measured by stereo, {hull['filled'] * 100:.1f} % "
                     "interpolated from the heights around them (band 2 of dsm.tif: the stereo pairs that measured "
                     "the cell, 0 where interpolated)"
                     + (f"; the orthomosaic holds a colour in {ortho['valid'] * 100:.1f} % of its cells there."
                        if ortho else '.'))
    foot = dsm.get('footprint')
    if foot:
        lines.append(f"Over the cameras' footprint (the camera centres' hull widened by a quarter of the flying "
                     f"height: what the oriented photos saw) {foot['measured'] * 100:.1f} % of the DSM's cells were "
                     f"measured by stereo, {foot.get('measured_one_pair', 0.0) * 100:.1f} % of it by one pair only "
                     "(unconfirmed: band 2 = 1, kept where no confirmed cell is near and it agrees with its "
                     f"neighbours); {foot['valid'] * 100:.1f} % hold a height.")
    dtm = run.get('dtm')
    if dtm:
        lines.append(f"DTM (dtm.tif, bare ground): {dtm['ground_cells_share'] * 100:.1f} % of its cells hold ground "
                     f"points ({dtm['ground_points']} points classified ground), the rest interpolated under "
                     "buildings, vegetation and unmeasured cells.")
    failed = run.get('densify_pairs_failed') or []
    if failed:
        lines.append(f'{len(failed)} stereo pair(s) failed in the final matching and were skipped '
                     f'(one bad pair costs one pair): {"; ".join(str(f) for f in failed[:5])}'
                     + (' ...' if len(failed) > 5 else '') + '.')
    return lines


def _truth_frame_for(truth, stamp_ns):
    return truth.frame_by_stamp(stamp_ns, tol_ns=5_000_000)


def build_report(out_dir: str | Path, map_dir: str | Path | MapStore, crs: str, files: dict, truth=None,
                 control=None, run: dict | None = None, diagnostics: dict | None = None) -> dict:
    """Write report.md/.html/.json into out_dir; returns the figures dictionary.

    map_dir: the map folder, or a MapStore already open on it.
    control: the flight's core.control.ControlSet (check points and GCPs listed apart); without it the
    truth's targets of a simulator bag are all check points. run: timing and counts of the replay.
    diagnostics: node -> {'problems': [...], 'values': {...}}.
    """
    out = Path(out_dir)
    store = map_dir if isinstance(map_dir, MapStore) else MapStore(map_dir)
    origin = store.origin
    cam = store.load_camera()
    kfs = store.keyframes()
    figures: dict = {'crs': crs, 'keyframes': len(kfs), 'files': {k: str(v) for k, v in files.items()},
                     'run': run or {}}
    sections = []
    s = Section('Summary')
    if run:
        s.text.append(f"{run.get('frames', 0)} frames, {len(kfs)} keyframes, {run.get('map_points', 0)} map points; "
                      f"{run.get('bag_s', 0):.1f} s of flight processed in {run.get('wall_s', 0):.1f} s "
                      f"(real-time factor {run.get('real_time_factor', 0):.2f}).")
        if run.get('products_from'):
            extra = (f" ({run['densify_pairs']} pairs matched again in {run['densify_s']:.1f} s)"
                     if 'densify_s' in run else '')
            s.text.append(f"Clouds, DSM and orthomosaic from the {run['products_from']}{extra}.")
        s.text += _settings_lines(run)
    s.text.append(f'Coordinates in {crs}, heights above the WGS84 ellipsoid unless stated'
                  + ('; the products\' heights (cloud, DSM, DTM) are orthometric, above the EGM2008 geoid '
                     '(--heights orthometric).' if (run or {}).get('heights') == 'orthometric' else '.'))
    sections.append(s)
    georeferenced = origin is not None and bool(kfs) and cam is not None
    sections[:0] = _health_sections(figures, kfs, files, run, diagnostics, georeferenced)
    if not georeferenced:
        sections.append(Section('No map', ['The map folder holds no georeferenced keyframes: nothing to report.']))
        if diagnostics:
            sections.append(_problems_section(diagnostics, figures))
        write_report(out, 'photogram_ros flight report', sections, figures)
        return figures
    traj = write_trajectory(out, kfs, origin, crs)
    Ts = np.array([k['map_T_cam'] for k in kfs])
    sections.append(capture_section(out, kfs, cam, origin, files, run or {}, traj, figures))
    if dsm_preview_png(out / 'dsm.png', files.get('dsm'), crs, product_heights(out)):
        sections.append(Section('DSM', ['The digital surface model (dsm.tif) over its hillshade.'],
                                figures=[('DSM heights', 'dsm.png')]))

    # Targets: the tracker's detections kept in the map folder (else found in the keyframes), intersected from
    # the adjusted poses. With a control file its check points are the check points and its GCPs are listed
    # apart (the adjustment used them); without one every target of the truth is a check point (nothing constrained the block to them).
    checks_surveyed, gcps_surveyed = {}, {}
    if control is not None:
        for t, c in zip(control.targets, control.in_map(origin)):
            (checks_surveyed if t.role == 'check' else gcps_surveyed)[t.marker_id] = (t.name, c.map_xyz)
    elif truth is not None:
        # Truth is in its own ENU; the map may be anchored elsewhere: go through ECEF.
        for t in truth.targets:
            checks_surveyed[t.marker_id] = (t.name, origin.ecef_to_enu(truth.origin.enu_to_ecef(t.center_enu)))
    surveyed = {**gcps_surveyed, **checks_surveyed}
    observations, max_px, found_by = target_observations(store, kfs, surveyed) if surveyed else ({}, 0.0, '')
    gsd = truth.gsd_m if truth is not None else None
    checks = intersect_targets(cam, Ts, observations, checks_surveyed, max_px) if checks_surveyed else None
    intro = (f'Targets {found_by}, intersected from the adjusted cameras (never used in the adjustment), against '
             'their surveyed coordinates' + (f' ({control.source}).' if control is not None else '.'))
    sec = Section('Check points', [intro])
    if checks is not None:
        figures['check_points'] = _target_figures(checks, gsd)
        figures['check_points']['detections'] = found_by
        figures['check_points']['ce90_le90'] = ce90_le90(checks.residuals)
        sec.tables.append(('Residuals (estimated - surveyed), m', checks.table()))
        sec.tables.append(('RMSE, m', [figures['check_points']['rmse']]))
        sec.text += ce90_text(figures['check_points']['ce90_le90'])
        if checks.missing:
            sec.text.append(f'Not measured (seen in fewer than two keyframes, or detections that agree on no point): '
                            f'{", ".join(checks.missing)}.')
        if checks.weak:
            sec.text.append(weak_text(checks.weak))
    elif control is not None:
        sec.text.append(f'{control.source} names no check point (CHK* or --check): the accuracy of this map is '
                        'not measured.')
    else:
        sec.text.append('No surveyed targets given (use --gcp targets.txt).')
    sections.append(sec)
    if gcps_surveyed:
        sections.append(_gcp_section(intersect_targets(cam, Ts, observations, gcps_surveyed, max_px), gsd,
                                     len(gcps_surveyed), diagnostics, figures))

    if truth is not None:
        sections.append(_truth_section(out, truth, origin, crs, kfs, files, figures))

    # Figures over the orthomosaic.
    tracks = {'adjusted keyframes': np.column_stack([traj['easting'], traj['northing']])}
    tg = []
    for m, (name, xyz) in surveyed.items():
        lat, lon, h = origin.enu_to_geodetic(np.asarray(xyz, float))
        e, n, _ = geodetic_to_crs(lat, lon, h, crs)
        tg.append((name, float(e), float(n)))
    trajectory_png(out / 'trajectory.png', files.get('ortho'), tracks, tg, f'Adjusted trajectory and targets ({crs})')
    sections.append(Section('Trajectory over the orthomosaic', figures=[('Keyframe camera centres', 'trajectory.png')]))
    if checks is not None and len(checks.names):
        at = {name: xyz for name, xyz in checks_surveyed.values()}
        arrows = []
        for name, r in zip(checks.names, checks.residuals):
            lat, lon, h = origin.enu_to_geodetic(np.asarray(at[name], float))
            e, n, _ = geodetic_to_crs(lat, lon, h, crs)
            arrows.append((name, float(e), float(n), float(r[0]), float(r[1]), float(r[2])))
        check_point_arrows_png(out / 'check_points.png', files.get('ortho'), arrows,
                               'Check-point errors (estimated - surveyed)')
        sections.append(Section('Check-point errors on the map', figures=[('Horizontal error of each check point '
                                                                            '(arrow), vertical in the label',
                                                                            'check_points.png')]))
    sections.append(gnss_section(out, kfs, origin, flight_inputs.keyframe_fixes(store.root), figures))
    row = {k: v for k, v in calibration_rows(None, cam)[0].items() if k != 'camera'}
    final = store.camera_name() == CAMERA_FINAL
    row['source'] = 'final adjustment' if final else 'input calibration'
    figures['camera'] = row
    before = flight_inputs.input_camera(store.root)
    rows = calibration_rows(before, cam)
    figures['calibration'] = rows
    sections.append(Section('Camera', ['The camera model the products were made with (the map folder\'s '
                                       'camera.json): ' + ('the one the final adjustment adjusted the poses with '
                                                           '(its self-calibration when it refined the intrinsics).'
                                                           if final else 'the calibration the flight started with.')]
                            + ([] if before is not None else ['The calibration the flight started with was not kept '
                                                              '(no camera_input.json): before and after cannot be '
                                                              'compared.']),
                            tables=[('Calibration before and after: intrinsics (pixels) and distortion (OpenCV model)',
                                     rows)]))
    overlap = overlap_png(out / 'overlap.png', files.get('dsm'), kfs, cam, origin, crs)
    if overlap:
        figures['overlap'] = overlap
        sections.append(Section('Overlap', [f"Photos seeing each DSM cell: median {overlap['median_photos']:.0f}; "
                                            f"{overlap['share_2_or_more'] * 100:.1f} % of the cells are in 2 or more "
                                            f"photos, {overlap['share_5_or_more'] * 100:.1f} % in 5 or more."],
                                figures=[('Photos per DSM cell', 'overlap.png')]))

    sections.append(parameters_section(run or {}, figures))
    if diagnostics:
        sections.append(_problems_section(diagnostics, figures))
    write_report(out, 'photogram_ros flight report', sections, figures)
    return figures


def parameters_section(run: dict, figures: dict) -> Section:
    """The processing parameters the run was given, as OpenDroneMap's report lists its options: each node's
    parameters from the run's parameters file (run['params_file'], a ROS 2 parameters YAML) and what the command
    set over them (run['parameter_overrides'], role -> {name: value}); also figures['parameters']."""
    import yaml
    path = run.get('params_file')
    overrides = run.get('parameter_overrides') or {}
    sec = Section('Parameters')
    rows = []
    if path:
        try:
            doc = yaml.safe_load(Path(path).read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            doc = {}
            sec.text.append(f'The parameters file {path} could not be read again for this report: {exc}.')
        for node, body in sorted(doc.items()):
            params = (body or {}).get('ros__parameters', {}) if isinstance(body, dict) else {}
            rows += [{'node': node, 'parameter': k, 'value': json.dumps(v), 'from': 'file'}
                     for k, v in sorted(params.items())]
        sec.text.insert(0, f'Parameters file: {path}.')
    else:
        sec.text.append('The run did not record its parameters file: the parameters are the command\'s defaults '
                        'and its options (see Software).')
    rows += [{'node': role, 'parameter': k, 'value': json.dumps(v, default=str), 'from': 'command'}
             for role, vals in sorted(overrides.items()) for k, v in sorted((vals or {}).items())]
    if run.get('heights'):
        rows.append({'node': 'products', 'parameter': '--heights', 'value': json.dumps(run['heights']),
                     'from': 'command'})
    figures['parameters'] = {'file': path, 'rows': rows}
    if rows:
        sec.tables.append(('Parameters (value from the file, or set by the command over it)', rows))
    return sec


def _gcp_section(gcps, gsd: float | None, n_surveyed: int, diagnostics: dict | None, figures: dict) -> Section:
    """GCP residuals as the fit they are, with what the bundle node made of each GCP in flight (used in full,
    horizontally only, not used: core/control_live.py) and the control faults it reported."""
    bundle = next((d for n, d in (diagnostics or {}).items() if n.endswith('bundle_node')), {})
    vals = bundle.get('values', {})
    names = lambda k: [n for n in str(vals.get(k, '')).split(',') if n]  # noqa: E731
    use = {**{n: 'horizontal only' for n in names('gcps_horizontal_only_names')},
           **{n: 'not used' for n in names('gcps_rejected_names')}}
    fig = figures['gcp_residuals'] = _target_figures(gcps, gsd)
    rows = [{**r, 'use': use.get(r['name'], 'full')} for r in gcps.table()]
    for r in rows:
        if r['use'] != 'full':
            r['dz_m'] = None    # its height was not used: the residual there is the file's placeholder
    fig['points'] = rows
    full = np.array([[r['dx_m'], r['dy_m'], r['dz_m']] for r in rows if r['use'] == 'full']).reshape(-1, 3)
    fit = [r for r in rows if r['use'] != 'not used']
    h = np.array([[r['dx_m'], r['dy_m']] for r in fit]).reshape(-1, 2)
    fig['rmse'] = {'horizontal_m': float(np.sqrt(np.mean(np.sum(h ** 2, axis=1)))) if len(h) else None,
                   'z_m': float(np.sqrt(np.mean(full[:, 2] ** 2))) if len(full) else None,
                   'count': len(fit), 'count_vertical': len(full)}
    if 'rmse_gsd' in fig:   # over the same GCPs as the RMSE
        fig['rmse_gsd'] = {'horizontal': fig['rmse']['horizontal_m'] / gsd if fig['rmse']['horizontal_m'] is not None
                           else None, 'vertical': fig['rmse']['z_m'] / gsd if fig['rmse']['z_m'] is not None else None}
    used = vals.get('gcps_used')
    if used is not None:
        used = fig['used_by_adjuster'] = int(float(used))
    fig['redundancy'] = redundancy_notes([{'name': r['name'], 'images': r['views'],
                                           'residual_m': [r['dx_m'], r['dy_m'], r['dz_m']]} for r in fit])
    sec = Section('GCP residuals', [
        'Ground control points constrained the adjustment: their residuals (intersected from the adjusted '
        'cameras minus surveyed) show how well the block fits them, not its accuracy (see the check points).'
        + (f' The adjuster used {used} of {n_surveyed} GCPs.' if used is not None else '')]
        + [f'{t}.' for t in fig['redundancy'][1:]])
    sec.tables.append(('Residuals (estimated - surveyed), m; the height of a GCP used horizontally only is not '
                       'shown', rows))
    sec.tables.append(('RMSE over the GCPs used (vertical: over those used in height), m', [fig['rmse']]))
    if gcps.missing:
        sec.text.append(f'Not measured (seen in fewer than two keyframes, or detections that agree on no point): '
                        f'{", ".join(gcps.missing)}.')
    if gcps.weak:
        sec.text.append(weak_text(gcps.weak))
    faults = [p[1][len('control: '):] for p in bundle.get('problems', []) if str(p[1]).startswith('control: ')]
    fig['faults'] = list(dict.fromkeys(faults))
    if fig['faults']:
        sec.text.append('The control file, checked in flight against the block as the GNSS placed it:')
        sec.text += [f'- {f}' for f in fig['faults']]
    return sec


def _problems_section(diagnostics: dict, figures: dict) -> Section:
    rows, problems = [], []
    for node, d in sorted(diagnostics.items()):
        vals = d.get('values', {})
        rows += [{'node': node, 'figure': k, 'value': vals[k]} for k in sorted(vals)
                 if k.endswith(('_ms', '_s', '_hz', 'fps', '_per_s', 'per_pair'))]
        problems += [{'node': node, 't_s': p[0], 'problem': p[1]} for p in d.get('problems', [])]
    figures['nodes'] = diagnostics
    sec = Section('What happened', [f'{len(problems)} problems reported on /diagnostics.'])
    sec.tables.append(('Problems (time from the start of the replay)', problems[:200]))
    sec.tables.append(('Timing per node (last values on /diagnostics)', rows))
    return sec


def _truth_section(out: Path, truth, origin: LocalFrame, crs: str, kfs, files, figures) -> Section:
    sec = Section('Against the simulator\'s ground truth', [f'GSD {truth.gsd_m * 100:.1f} cm.'])
    to_truth = lambda p: truth.origin.ecef_to_enu(origin.enu_to_ecef(p))  # noqa: E731
    est, true = [], []
    for kf in kfs:
        f = _truth_frame_for(truth, kf['stamp_ns'])
        if f is not None:
            est.append(to_truth(kf['map_T_cam'][:3, 3]))
            true.append(f.map_T_cam[:3, 3])
    tr = trajectory_errors(np.array(est).reshape(-1, 3), np.array(true).reshape(-1, 3))
    figures['trajectory_vs_truth'] = tr
    sec.tables.append(('Keyframe camera centres against truth, m', [tr]))
    dsm_path = files.get('dsm')
    if dsm_path and Path(dsm_path).exists():
        enu, pairs, res = _raster_cells_enu(dsm_path, crs, truth.origin.geodetic_to_enu)
        dz = enu[:, 2] - truth.dem.sample(enu[:, 0], enu[:, 1])
        err = surface_errors(dz, truth.gsd_m)
        figures['dsm_vs_truth'] = err
        smooth = ~near_discontinuity(truth.dem, enu[:, 0], enu[:, 1])
        figures['dsm_vs_truth_away_from_walls'] = surface_errors(dz[smooth], truth.gsd_m)
        sec.tables.append(('DSM against the true DEM', [err]))
        sec.tables.append(('DSM against the true DEM, cells more than 1 m from walls and roof edges (where a '
                           'cell straddles a height step its error is the step)',
                           [figures['dsm_vs_truth_away_from_walls']]))
        if pairs is not None:
            measured = pairs >= 1
            figures['dsm_vs_truth_measured'] = surface_errors(dz[measured], truth.gsd_m)
            if (~measured).any():
                figures['dsm_vs_truth_filled'] = surface_errors(dz[~measured], truth.gsd_m)
            sec.tables.append(('DSM against the true DEM: cells stereo measured / cells interpolated',
                               [figures['dsm_vs_truth_measured']] + ([figures['dsm_vs_truth_filled']]
                                                                     if 'dsm_vs_truth_filled' in figures else [])))
        histogram_png(out / 'dsm_error_hist.png', dz, 'DSM - true height, m', 'DSM height errors')
        sec.figures.append(('DSM height errors', 'dsm_error_hist.png'))
        # Completeness over the area the survey lines imaged (the truth's camera footprints' core).
        C = np.array([f.map_T_cam[:3, 3] for f in truth.frames])
        inside = ((enu[:, 0] > C[:, 0].min()) & (enu[:, 0] < C[:, 0].max()) &
                  (enu[:, 1] > C[:, 1].min()) & (enu[:, 1] < C[:, 1].max()))
        figures['dsm_cell_m'] = res
        area = (C[:, 0].max() - C[:, 0].min()) * (C[:, 1].max() - C[:, 1].min())
        figures['dsm_completeness'] = float(min(inside.sum() * res * res / max(area, 1e-9), 1.0))
        sec.text.append(f"DSM completeness over the flown area: {figures['dsm_completeness'] * 100:.1f} %.")
        if pairs is not None:
            figures['dsm_measured_completeness'] = float(min(np.sum(inside & (pairs >= 1)) * res * res
                                                             / max(area, 1e-9), 1.0))
            sec.text.append(f"Of it measured by stereo (not interpolated): "
                            f"{figures['dsm_measured_completeness'] * 100:.1f} % of the flown area.")
    dtm_path = files.get('dtm')
    if dtm_path and Path(dtm_path).exists():
        enu, _, _ = _raster_cells_enu(dtm_path, crs, truth.origin.geodetic_to_enu)
        dz = enu[:, 2] - truth.dem.sample(enu[:, 0], enu[:, 1])
        away = ~near_buildings(truth.dem, enu[:, 0], enu[:, 1])
        figures['dtm_vs_truth_away_from_buildings'] = surface_errors(dz[away], truth.gsd_m)
        sec.tables.append(('DTM against the true ground, cells more than 2 m from buildings',
                           [figures['dtm_vs_truth_away_from_buildings']]))
    las = files.get('las')
    if las and Path(las).exists():
        import laspy
        pc = laspy.read(las)
        lat, lon, h = crs_to_geodetic(np.asarray(pc.x), np.asarray(pc.y), np.asarray(pc.z), crs)
        enu = truth.origin.geodetic_to_enu(lat, lon, h)
        dz = enu[:, 2] - truth.dem.sample(enu[:, 0], enu[:, 1])
        err = surface_errors(dz, truth.gsd_m)
        figures['cloud_vs_truth'] = err
        smooth = ~near_discontinuity(truth.dem, enu[:, 0], enu[:, 1])
        figures['cloud_vs_truth_away_from_walls'] = surface_errors(dz[smooth], truth.gsd_m)
        figures['cloud_completeness'] = _cloud_completeness(enu, truth, figures.get('dsm_cell_m', 2 * truth.gsd_m))
        sec.text.append(f"Dense cloud completeness (cells of {figures.get('dsm_cell_m', 2 * truth.gsd_m):.2f} m over "
                        f"the flown area holding at least one point): {figures['cloud_completeness'] * 100:.1f} %.")
        sec.tables.append(('Dense cloud against the true DEM', [err]))
        sec.tables.append(('Dense cloud against the true DEM, away from walls', [figures['cloud_vs_truth_away_from_walls']]))
        histogram_png(out / 'cloud_error_hist.png', dz, 'cloud - true height, m', 'Dense cloud height errors')
        sec.figures.append(('Dense cloud height errors', 'cloud_error_hist.png'))
    return sec


def _cloud_completeness(enu: np.ndarray, truth, cell_m: float) -> float:
    """Share of the flown area's cells (the truth cameras' bounding box) that hold at least one cloud point.

    Unlike the DSM's completeness this counts no interpolated cell: it is what stereo actually measured.
    """
    C = np.array([f.map_T_cam[:3, 3] for f in truth.frames])
    lo, hi = C[:, :2].min(axis=0), C[:, :2].max(axis=0)
    shape = np.maximum(np.ceil((hi - lo) / cell_m).astype(int), 1)
    ij = np.floor((enu[:, :2] - lo) / cell_m).astype(int)
    keep = np.all((ij >= 0) & (ij < shape), axis=1)
    hit = np.zeros(shape, bool)
    hit[ij[keep, 0], ij[keep, 1]] = True
    return float(hit.mean())
