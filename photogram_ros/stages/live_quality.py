"""The live accuracy of the block in flight (map/control_points): the surveyed targets seen so far intersected from
the adjusted cameras against their surveys, as the flight report intersects them (core/evaluation.py
intersect_targets), with the fix classes of the keyframes and the GNSS bias; for stages/adjustment.py.
"""

from __future__ import annotations

import numpy as np

from photogram_ros.core.at_report import redundancy_notes
from photogram_ros.core.evaluation import ce90_le90, intersect_targets
from photogram_ros.core.survey_quality import BLOCK_ADJUSTED, BLOCK_IN_FLIGHT, rmse


def live_quality(at, control, live, fix_classes: dict, adjusted_whole: bool, max_row_residual_px: float,
                 block_check: dict | None = None) -> dict:
    """The live accuracy figures of the adjuster `at` (core/incremental.py IncrementalAT, or None before the
    camera came) with the flight's control (core/control.py ControlSet, or None) as `live` (core/control_live.py
    LiveControl) vets it; fix_classes: keyframes per fix class; adjusted_whole: the block has had its final
    adjustment; block_check: the adjuster's last check of the block ({'status', 'summary'}, core/block_check.py),
    None before its first."""
    n = sum(fix_classes.values())
    out = {'keyframes': n, 'fix_share': {c: (v / n if n else None) for c, v in fix_classes.items()},
           'georeference': ('none' if at is None or not at.georeferenced else
                            'provisional' if at.georef_provisional else 'final'),
           'block': BLOCK_ADJUSTED if adjusted_whole else BLOCK_IN_FLIGHT,
           'check_points': [], 'gcps': [], 'check_rmse': None, 'gcp_rmse': None, 'gnss_bias_enu_m': None,
           'max_row_residual_px': max_row_residual_px, 'block_check': block_check}
    if control is not None and at is not None and at.origin is not None:
        out['check_points'], out['check_points_weak'] = target_rows(at, control, live, 'check', max_row_residual_px)
        out['gcps'], out['gcps_weak'] = target_rows(at, control, live, 'gcp', max_row_residual_px)
        checks = [r['residual_enu_m'] for r in out['check_points']]
        out['check_rmse'] = rmse(checks)
        out['check_ce90_le90'] = ce90_le90(checks)
        out['gcp_rmse'] = gcp_rmse(out['gcps'])
        out['gcp_redundancy'] = redundancy_notes([{'name': r['name'], 'images': r['images'],
                                                   'residual_m': r['residual_enu_m']} for r in out['gcps']])
        if len(out['gcps']) >= 3 and at.datum.bias_estimated:
            out['gnss_bias_enu_m'] = [float(v) for v in at.datum.bias_enu]
        for k in ('check_rmse', 'gcp_rmse'):
            if not out[k]['count']:
                out[k] = {'horizontal_m': None, 'vertical_m': None, 'count': 0}
        out['control'] = live.to_dict()
        out['detections'] = detections(at, control, live)
    return out


def target_rows(at, control, live, role: str, max_row_residual_px: float) -> tuple[list[dict], list[dict]]:
    """Surveyed targets of one role seen so far, intersected from the adjusted cameras over the oriented
    keyframes that saw them (core.evaluation.intersect_targets, as the flight report does; a GCP too, not
    its adjusted point, which its own prior holds); residual = estimate - survey, map ENU, m. The
    detections are those `detections` hands out, which the report intersects again by the same method.
    Returns (rows, weak): weak lists those intersected too weakly to count ({'name', 'views', 'dop_h',
    'dop_v'})."""
    registered = set(at.block.oriented())
    if role == 'gcp' and not at.georeferenced:
        return [], []
    targets, obs, surveyed = {}, {}, {}
    for t in control.targets:
        cp, use = live.surveyed.get(t.name), live.use_of(t.name)
        if cp is None or t.role != role or (role == 'gcp' and use not in ('full', 'horizontal')):
            continue
        targets[t.name], surveyed[t.name] = (t, use), (t.name, cp.map_xyz)
        obs[t.name] = live.observations(t.name, registered)
    kids = sorted({k for o in obs.values() for k, _ in o})
    col = {k: j for j, k in enumerate(kids)}
    res = intersect_targets(at.block.camera, np.array([at.block.keyframe(k).map_T_cam for k in kids]).reshape(-1, 4, 4),
                            {n: [(col[k], uv) for k, uv in o] for n, o in obs.items()}, surveyed, max_row_residual_px)
    rows = []
    for name, r, n_images, rms_px in zip(res.names, res.residuals, res.n_views, res.rms_px):
        t, use = targets[name]
        rows.append({'name': t.name, 'marker_id': t.marker_id, 'lat_deg': t.lat_deg, 'lon_deg': t.lon_deg,
                     'h_m': t.h_m, 'residual_enu_m': [float(v) for v in r], 'images': int(n_images),
                     'rms_px': None if not np.isfinite(rms_px) else float(rms_px), 'use': use})
    return rows, res.weak


def detections(at, control, live) -> dict:
    """{target name: [[stamp_ns, u, v], ...]} of every surveyed target in the oriented keyframes (the
    detections vetting did not reject), whatever its use: the map folder keeps them and the flight report
    intersects them as the live accuracy does (a GCP left out too, to show how far off it is)."""
    registered = set(at.block.oriented())
    out = {}
    for t in control.targets:
        obs = live.observations(t.name, registered)
        if obs:
            out[t.name] = [[int(at.block.keyframe(k).stamp_ns), float(uv[0]), float(uv[1])] for k, uv in obs]
    return out


def gcp_rmse(gcps: list[dict]) -> dict:
    """GCP residual RMSE; the vertical over the GCPs used in height only (None without one): the height
    of a GCP used horizontally is not the survey's, its residual there means nothing."""
    out = rmse([r['residual_enu_m'] for r in gcps])
    full = rmse([r['residual_enu_m'] for r in gcps if r['use'] == 'full'])
    out['count_vertical'] = full['count']
    out['vertical_m'] = full['vertical_m'] if full['count'] else None
    return out


def control_diagnostics(diag, at, control, live) -> None:
    """The flight's control on /diagnostics: the adjuster's and the vetting's summaries (no 'nan' before a GCP has
    a residual), the check points seen, the GCPs used horizontally only or rejected, and the GNSS bias."""
    if control is None:
        return
    for k, v in {**at.control_summary(), **live.summary()}.items():
        if not (isinstance(v, float) and not np.isfinite(v)):
            diag.set(k, v)
    diag.set('checks_seen', sum(live.use_of(n) == 'check' for n in control.check_names))
    for use in ('horizontal', 'unused'):
        names = [t.name for t in control.targets if t.role == 'gcp' and live.use_of(t.name) == use]
        diag.set(f'gcps_{"horizontal_only" if use == "horizontal" else "rejected"}_names', ','.join(names))
    diag.set('gnss_bias_enu_m', ' '.join(f'{v:.3f}' for v in at.datum.bias_enu))


def quality_diagnostics(diag, q: dict) -> None:
    """The live quality document's figures on /diagnostics: each fix class's share, the check points measured and
    their RMSE."""
    for c, v in q['fix_share'].items():
        if v is not None:
            diag.set(f'keyframes_{c}_share', float(v))
    cr = q['check_rmse']
    if cr is not None:
        diag.set('checks_measured', cr['count'])
        if cr['count']:
            diag.set('check_rmse_h_m', float(cr['horizontal_m']))
            diag.set('check_rmse_v_m', float(cr['vertical_m']))
