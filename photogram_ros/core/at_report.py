"""Aerial-triangulation accuracy report: reprojection, GNSS, GCP and check-point residuals.

`build_report(at)` gathers every figure into one dict (written as report.json); `write_report`
renders it as report.md and report.html with figures (PNG, drawn by photogram_ros.io.report like the
flight report), and `markdown(report)` as plain Markdown text. Residuals are adjusted minus reference in the `map` ENU frame
(X = east, Y = north, Z = up, metres); check points are intersected from the adjusted cameras and
never took part in the adjustment.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def rmse_xyz(res: np.ndarray) -> dict:
    r = np.asarray(res, float).reshape(-1, 3)
    if not len(r):
        return {'n': 0}
    return {'n': int(len(r)), 'x_m': float(np.sqrt(np.mean(r[:, 0] ** 2))),
            'y_m': float(np.sqrt(np.mean(r[:, 1] ** 2))), 'z_m': float(np.sqrt(np.mean(r[:, 2] ** 2))),
            'horizontal_m': float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1)))),
            'vertical_m': float(np.sqrt(np.mean(r[:, 2] ** 2))),
            'total_m': float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))}


def _per_image(at, residuals: list | None = None) -> list[dict]:
    """Per-image statistics; appends each observation's reprojection error (px) to `residuals`."""
    gres = at.gnss_residuals()
    out = []
    for k in at.registered:
        kf = at.kfs[k]
        m = kf.active & np.array([int(t) in at.points for t in kf.track_ids])
        if m.any():
            X = np.array([at.points[int(t)] for t in kf.track_ids[m]])
            e = at._reprojection_px(kf.map_T_cam, X, kf.uv[m])
            rms = float(np.sqrt(np.mean(e ** 2)))
            if residuals is not None:
                residuals.append(e)
        else:
            rms = float('nan')
        g = gres.get(k)
        out.append({'image': kf.name, 'stamp_ns': kf.stamp_ns, 'observations': int(m.sum()),
                    'reprojection_rms_px': rms,
                    'gnss_residual_enu_m': None if g is None else [float(v) for v in g],
                    'position_map_m': [float(v) for v in kf.map_T_cam[:3, 3]]})
    return out


def build_report(at, assumptions: list[str] | None = None, gsd_m: float | None = None) -> dict:
    """Every figure of the report from an adjusted IncrementalAT."""
    errs: list = []
    per_image = _per_image(at, errs)
    errs = np.concatenate(errs) if errs else np.zeros(0)
    errs = errs[np.isfinite(errs)]
    rms_all = [p['reprojection_rms_px'] for p in per_image if np.isfinite(p['reprojection_rms_px'])]
    nobs = [p['observations'] for p in per_image]
    gres = np.array([p['gnss_residual_enu_m'] for p in per_image if p['gnss_residual_enu_m'] is not None])
    gcps, checks = [], []
    for name, c in at.control.items():
        tid = at._target_ids.get(name)
        if c.role == 'gcp' and at.opt.use_gcps:
            if tid is not None and tid in at.points:
                r = at.points[tid] - c.map_xyz
                Ts, uv = at.observations_of(tid)
                gcps.append({'name': name, 'residual_m': r.tolist(), 'images': len(Ts),
                             'surveyed_map_m': c.map_xyz.tolist()})
        else:
            hit = at.intersect_target(name)
            if hit is not None:
                X, n, rms = hit
                checks.append({'name': name, 'residual_m': (X - c.map_xyz).tolist(), 'images': n,
                               'reprojection_rms_px': rms, 'surveyed_map_m': c.map_xyz.tolist()})
    # Per-observation RMS over the whole block (per-image values weighted by their counts).
    total_rms = float(np.sqrt(np.sum(np.square(rms_all) * np.array(nobs)[np.isfinite(
        [p['reprojection_rms_px'] for p in per_image])]) / max(sum(nobs), 1))) if rms_all else float('nan')
    rep = {
        'format': 'photogram_ros aerial triangulation report v1',
        'origin': at.origin.to_dict() if at.origin is not None else None,
        'frame': 'map: ENU at origin (x east, y north, z up), m; heights ellipsoidal',
        'georeferenced': bool(at.georeferenced),
        'keyframes': len(at.kfs), 'registered': len(at.registered), 'points': len(at.points),
        'observations': int(sum(nobs)),
        'camera': {'width': at.camera.width, 'height': at.camera.height, 'fx': at.camera.fx, 'fy': at.camera.fy,
                   'cx': at.camera.cx, 'cy': at.camera.cy, 'dist': list(at.camera.dist)},
        'reprojection_rms_px': total_rms,
        'gnss': {'rmse': rmse_xyz(gres), 'estimated_bias_enu_m': at.gnss_bias_enu.tolist()},
        'gcp': {'points': gcps, 'rmse': rmse_xyz(np.array([g['residual_m'] for g in gcps]))},
        'check': {'points': checks, 'rmse': rmse_xyz(np.array([c['residual_m'] for c in checks]))},
        'reprojection_histogram': _histogram(errs),
        'per_image': per_image,
        'assumptions': list(assumptions or []),
    }
    if gsd_m:
        rep['gsd_m'] = gsd_m
        ck = rep['check']['rmse']
        if ck.get('n'):
            rep['check']['rmse_gsd'] = {'horizontal': ck['horizontal_m'] / gsd_m, 'vertical': ck['vertical_m'] / gsd_m}
    return rep


def _histogram(v: np.ndarray, bins: int = 50) -> dict:
    """Counts of the reprojection-error histogram figure (0.5-99.5 percentile range, clipped)."""
    if not len(v):
        return {'n': 0, 'edges_px': [], 'counts': []}
    lo, hi = np.percentile(v, [0.5, 99.5])
    counts, edges = np.histogram(np.clip(v, lo, hi), bins=bins)
    return {'n': int(len(v)), 'median_px': float(np.median(v)), 'p95_px': float(np.percentile(v, 95)),
            'edges_px': edges.tolist(), 'counts': counts.tolist()}


def intrinsics_sigma(at, refine: tuple) -> dict:
    """A-posteriori sigmas of the self-calibrated intrinsics at the adjusted block.

    The full adjustment of IncrementalAT does not ask for covariances, so this evaluates them at its
    result: the same problem (every registered keyframe and point, GNSS and GCP priors), zero
    iterations, covariance on. Returns name -> sigma (px for f, cx, cy; unitless for k1..k3) and
    's0_px' (a-posteriori sigma of unit weight), or {} when the block has no datum.
    """
    from photogram_ros.core.bundle import BundleOptions, BundleProblem, bundle_adjust
    kids = list(at.registered)
    tracks = np.asarray(list(at.points), dtype=np.int64)
    tracks = tracks[at.points.contains_many(tracks)].tolist() if len(tracks) else []
    if not refine or not kids or not tracks:
        return {}
    slot, kid, oi = at._gather(tracks, kids)
    col = {k: j for j, k in enumerate(kids)}
    fixed = np.zeros(len(kids), bool)
    if not at.georeferenced:
        fixed[:2] = True
    gk = [j for j, k in enumerate(kids) if at.georeferenced and at.kfs[k].fix_enu is not None]
    pri = [(s, at.control[at.target_name(t)]) for s, t in enumerate(tracks)
           if t < 0 and not at._is_check(t)] if at.georeferenced else []
    prob = BundleProblem(
        camera=at.camera, map_T_cams=np.array([at.kfs[k].map_T_cam for k in kids]),
        points_map=at.points.get_many(tracks).reshape(-1, 3),
        obs_cam=np.array([col[int(k)] for k in kid], dtype=np.int64), obs_pt=slot,
        obs_uv=np.array([at.kfs[int(k)].uv[i] for k, i in zip(kid, oi)]).reshape(-1, 2),
        fixed_cams=fixed,
        gnss_cam=np.array(gk, int) if gk else None,
        gnss_pos_map=np.array([at._gnss_target(at.kfs[kids[j]]) for j in gk]).reshape(-1, 3),
        gnss_cov_map=np.array([at.kfs[kids[j]].fix_cov for j in gk]).reshape(-1, 3, 3),
        lever_arm_cam_m=at.lever,
        point_priors_idx=np.array([s for s, _ in pri], int) if pri else None,
        point_priors_map=np.array([c.map_xyz for _, c in pri]).reshape(-1, 3),
        point_priors_sigma_m=np.array([c.sigma_m for _, c in pri]).reshape(-1, 3))
    res = bundle_adjust(prob, BundleOptions(loss=at.opt.loss, loss_scale_px=at.opt.loss_scale_px,
                                            max_iterations=0, refine_intrinsics=tuple(refine),
                                            compute_covariance=True))
    sig = res.intrinsics_sigma()
    if sig and res.variance_factor is not None:
        sig['s0_px'] = float(np.sqrt(res.variance_factor))
    return sig


def _table(rows, header):
    out = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    out += ['| ' + ' | '.join(rows_i) + ' |' for rows_i in rows]
    return out


def _rmse_line(r: dict) -> str:
    if not r.get('n'):
        return 'none'
    return (f"n={r['n']}: X {r['x_m'] * 100:.1f} cm, Y {r['y_m'] * 100:.1f} cm, Z {r['z_m'] * 100:.1f} cm; "
            f"horizontal {r['horizontal_m'] * 100:.1f} cm, vertical {r['vertical_m'] * 100:.1f} cm")


def markdown(rep: dict) -> str:
    L = ['# Aerial triangulation report', '',
         f"Keyframes {rep['registered']}/{rep['keyframes']} oriented, {rep['points']} tie points, "
         f"{rep['observations']} observations; reprojection RMS {rep['reprojection_rms_px']:.3f} px.",
         f"Frame: {rep['frame']}. Origin: {rep['origin']}.", '']
    if 'gsd_m' in rep:
        L += [f"GSD {rep['gsd_m'] * 100:.2f} cm.", '']
    L += ['## GNSS', '', f"Residuals (adjusted antenna - fix): {_rmse_line(rep['gnss']['rmse'])}.",
          f"Estimated constant GNSS bias (E, N, U): {np.round(rep['gnss']['estimated_bias_enu_m'], 3).tolist()} m.", '']
    for key, title in (('gcp', 'Ground control points'), ('check', 'Check points')):
        sec = rep[key]
        L += [f'## {title}', '', f"RMSE {_rmse_line(sec['rmse'])}."]
        if 'rmse_gsd' in sec:
            L += [f"In GSD: horizontal {sec['rmse_gsd']['horizontal']:.2f}, vertical {sec['rmse_gsd']['vertical']:.2f}."]
        L += ['']
        if sec['points']:
            L += _table([[p['name'], *(f'{v * 100:.1f}' for v in p['residual_m']), str(p['images'])]
                         for p in sec['points']], ['name', 'dX cm', 'dY cm', 'dZ cm', 'images']) + ['']
    L += ['## Camera', '', f"{rep['camera']}", '', '## Per image', '']
    L += _table([[p['image'], str(p['observations']), f"{p['reprojection_rms_px']:.3f}",
                  '' if p['gnss_residual_enu_m'] is None else ', '.join(f'{v:.3f}' for v in p['gnss_residual_enu_m'])]
                 for p in rep['per_image']], ['image', 'observations', 'RMS px', 'GNSS residual E, N, U m'])
    if rep['assumptions']:
        L += ['', '## Assumptions', ''] + [f'- {a}' for a in rep['assumptions']]
    return '\n'.join(L) + '\n'


def _self_cal_rows(rep: dict) -> list[dict]:
    sc = rep.get('self_calibration') or {}
    return [{'parameter': k, 'before': v.get('before'), 'after': v.get('after'), 'sigma': v.get('sigma')}
            for k, v in sc.items() if isinstance(v, dict)]


def _figures(rep: dict, out: Path) -> dict:
    """Draw the report's figures into out; returns caption -> PNG name per section key."""
    from photogram_ros.io.report import histogram_png, series_png, trajectory_png, vectors_png
    figs = {}
    h = rep['reprojection_histogram']
    if h['n']:
        edges = np.asarray(h['edges_px'])
        histogram_png(out / 'reprojection_hist.png', np.repeat((edges[:-1] + edges[1:]) / 2, h['counts']),
                      'reprojection error (px)', 'Reprojection errors, all observations', bins=len(h['counts']))
        figs['reprojection'] = ('Reprojection error histogram', 'reprojection_hist.png')
    pim = rep['per_image']
    idx = np.arange(len(pim))
    if pim:
        series_png(out / 'per_image_rms.png', idx, {'RMS px': [p['reprojection_rms_px'] for p in pim]},
                   'image (order of registration)', 'px', 'Reprojection RMS per image')
        figs['per_image'] = ('Reprojection RMS per image', 'per_image_rms.png')
    g = [(k, p['gnss_residual_enu_m']) for k, p in enumerate(pim) if p['gnss_residual_enu_m'] is not None]
    if g:
        k = np.array([a for a, _ in g])
        r = np.array([b for _, b in g])
        series_png(out / 'gnss_residuals.png', k, {'X (east)': r[:, 0], 'Y (north)': r[:, 1], 'Z (up)': r[:, 2]},
                   'image (order of registration)', 'm', 'GNSS residuals (adjusted antenna - fix)')
        figs['gnss'] = ('GNSS residuals per image, X/Y/Z', 'gnss_residuals.png')
    ctrl = [('GCP', p) for p in rep['gcp']['points']] + [('check', p) for p in rep['check']['points']]
    if pim:
        xy = np.array([p['position_map_m'][:2] for p in pim])
        targets = [(f"{p['name']} ({kind})", p['surveyed_map_m'][0], p['surveyed_map_m'][1]) for kind, p in ctrl]
        trajectory_png(out / 'plan.png', None, {'camera centres': xy}, targets,
                       'Camera centres, GCPs and check points (map ENU, m)')
        figs['plan'] = ('Plan view: camera centres and control', 'plan.png')
    if ctrl:
        vectors_png(out / 'control_residuals.png',
                    [(p['name'], kind, *p['surveyed_map_m'][:2], *p['residual_m']) for kind, p in ctrl],
                    'GCP and check-point residuals (arrows: horizontal, labels: dZ)')
        figs['control'] = ('GCP and check-point residual vectors', 'control_residuals.png')
    return figs


def write_report(rep: dict, out_dir) -> tuple[Path, Path]:
    """report.md, report.html (figures embedded), the PNGs and report.json (every figure's numbers)."""
    from photogram_ros.io.report import Section
    from photogram_ros.io.report import write_report as write_sections
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = _figures(rep, out)
    rep['figure_files'] = {k: v[1] for k, v in figs.items()}

    def fig(*keys):
        return [figs[k] for k in keys if k in figs]
    summary = [f"Keyframes {rep['registered']}/{rep['keyframes']} oriented, {rep['points']} tie points, "
               f"{rep['observations']} observations; reprojection RMS {rep['reprojection_rms_px']:.3f} px.",
               f"Frame: {rep['frame']}. Origin: {rep['origin']}."]
    if 'gsd_m' in rep:
        summary.append(f"GSD {rep['gsd_m'] * 100:.2f} cm.")
    sections = [Section('Summary', summary, figures=fig('reprojection')),
                Section('GNSS', [f"Residuals (adjusted antenna - fix): {_rmse_line(rep['gnss']['rmse'])}.",
                                 f"Estimated constant GNSS bias (E, N, U): "
                                 f"{np.round(rep['gnss']['estimated_bias_enu_m'], 3).tolist()} m."],
                        figures=fig('gnss'))]
    for key, title in (('gcp', 'Ground control points'), ('check', 'Check points')):
        sec = rep[key]
        text = [f"RMSE {_rmse_line(sec['rmse'])}."]
        if 'rmse_gsd' in sec:
            text.append(f"In GSD: horizontal {sec['rmse_gsd']['horizontal']:.2f}, "
                        f"vertical {sec['rmse_gsd']['vertical']:.2f}.")
        rows = [{'name': p['name'], 'dX cm': p['residual_m'][0] * 100, 'dY cm': p['residual_m'][1] * 100,
                 'dZ cm': p['residual_m'][2] * 100, 'images': p['images']} for p in sec['points']]
        sections.append(Section(title, text, tables=[('Residuals (adjusted - surveyed)', rows)] if rows else []))
    sections.append(Section('Plan view and control residuals', figures=fig('plan', 'control')))
    cam = Section('Camera', [f"{rep['camera']}"])
    sc_rows = _self_cal_rows(rep)
    if sc_rows:
        s0 = (rep.get('self_calibration') or {}).get('s0_px')
        cam.text.append('Self-calibrated intrinsics with sigma (a-posteriori, scaled by the variance of '
                        'unit weight' + (f' s0 = {s0:.3f} px' if s0 is not None else '') + ').')
        cam.tables.append(('Self-calibration', sc_rows))
    sections.append(cam)
    sections.append(Section('Per image', tables=[('Per-image statistics', [
        {'image': p['image'], 'observations': p['observations'], 'RMS px': p['reprojection_rms_px'],
         'GNSS dE m': None if p['gnss_residual_enu_m'] is None else p['gnss_residual_enu_m'][0],
         'GNSS dN m': None if p['gnss_residual_enu_m'] is None else p['gnss_residual_enu_m'][1],
         'GNSS dU m': None if p['gnss_residual_enu_m'] is None else p['gnss_residual_enu_m'][2]}
        for p in rep['per_image']])], figures=fig('per_image')))
    if rep['assumptions']:
        sections.append(Section('Assumptions', [f'- {a}' for a in rep['assumptions']]))
    paths = write_sections(out, 'Aerial triangulation report', sections, rep)
    return paths['md'], paths['json']
