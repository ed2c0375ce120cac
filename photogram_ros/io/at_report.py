"""The aerial-triangulation report rendered: report.md, report.html (figures embedded) and report.json.

`write_report(rep, out_dir)` renders the figures that core/at_report.py `build_report` gathered, with
PNG figures drawn by photogram_ros.io.report like the flight report; `markdown(rep)` gives them as
plain Markdown text.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from photogram_ros.core.block_check import ok_summary
from photogram_ros.io.report import (Section, format_cell, histogram_png, md_table, series_png, trajectory_png,
                                     vectors_png)
from photogram_ros.io.report import write_report as write_sections


def _table(rows, header):
    out = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    out += ['| ' + ' | '.join(rows_i) + ' |' for rows_i in rows]
    return out


def _cm(v) -> str:
    return 'n/a' if v is None else f'{v * 100:.1f} cm'


def _rmse_line(r: dict) -> str:
    if not r.get('n'):
        return 'none'
    nv = f" (vertical over {r['n_vertical']} used with their heights)" if 'n_vertical' in r else ''
    return (f"n={r['n']}: X {_cm(r['x_m'])}, Y {_cm(r['y_m'])}, Z {_cm(r.get('z_m'))}; "
            f"horizontal {_cm(r['horizontal_m'])}, vertical {_cm(r.get('vertical_m'))}{nv}")


def _rms_text(rep: dict) -> str:
    v = rep['reprojection_rms_px']
    return 'none' if v is None else f'{v:.3f} px'


def ce90_text(c: dict | None) -> list[str]:
    """A sentence on CE90 / LE90 (core.evaluation.ce90_le90's figures); none without check points."""
    c = c or {}
    if not c.get('n'):
        return []
    warn = '' if c['circular'] else (f" (RMSEx / RMSEy = {c['rmse_x_over_y']:.2f} < 0.6: the circular formula "
                                     'understates it; see the empirical figure)')
    return [f"CE90 {_cm(c['ce90_m'])}, LE90 {_cm(c['le90_m'])} (from the RMSE{warn}); empirical 90th percentile: "
            f"CE90 {_cm(c['ce90_empirical_m'])}, LE90 {_cm(c['le90_empirical_m'])}. {c['method']}."]


def _gnss_text(rep: dict) -> list[str]:
    g = rep['gnss']
    L = [f"Residuals (adjusted antenna - fix): {_rmse_line(g['rmse'])}.",
         f"Estimated constant GNSS bias (E, N, U): {np.round(g['estimated_bias_enu_m'], 3).tolist()} m."]
    if 'spread_m' in g['rmse']:
        L.append(f"About their mean (a shift of the whole block is not strain): {_cm(g['rmse']['spread_m'])}.")
    w = g.get('without_gcps')
    if w and w.get('n'):
        ratio = g.get('strain_ratio')
        L.append(f"The same block adjusted without GCPs: {_rmse_line(w)}, about their mean {_cm(w.get('spread_m'))}"
                 + (f"; with the GCPs the spread is {ratio:.2f}x that (GCPs holding the block true against a "
                    "GNSS error that wanders raise it, GCPs with wrong coordinates too: see Control rows)"
                    if ratio is not None else '') + '.')
    return L


def _control_lines(rep: dict) -> list[str]:
    c = rep.get('control')
    if not c:
        return []
    n = c['row_fates']
    L = [f"{len(c['rows'])} control rows: " + ', '.join(f'{v} {k.replace("_", " ")}' for k, v in n.items() if v) + '.']
    L += [f'- {f}' for f in c['faults']]
    return L


def _control_rows(rep: dict) -> list[dict]:
    c = rep.get('control') or {}
    return [{'line': r['line'], 'image': r['image'], 'point': r['name'], 'fate': r['fate'],
             'residual px': r['residual_px'], 'residual m': r['residual_m'], 'why': r['reason']}
            for r in c.get('rows', [])]


def _point_rows(rep: dict) -> list[dict]:
    c = rep.get('control') or {}
    return [{'point': p['name'], 'role': p['role'], 'use': p['use'], 'rows': f"{p['usable_rows']}/{p['rows']}",
             'dH m': p['d_h_m'], 'dV m': p['d_v_m'], 'sigma H m': p['sigma_h_m'], 'sigma V m': p['sigma_v_m'],
             'horizontal': p['horizontal'], 'vertical': p['vertical'], 'why': p['reason']}
            for p in c.get('points', {}).values()]


def _tie_text(rep: dict) -> list[str]:
    pts = (rep.get('mtp') or {}).get('points') or []
    if not pts:
        return []
    L = [f"{len(pts)} manual tie points, adjusted as tie points measured by hand; residual = adjusted point "
         'reprojected minus the mark, px.']
    for p in pts:
        if p['rms_px'] is None:
            L.append(f"- {p['name']}: {p['note'] or 'no residual'}")
        else:
            L.append(f"- {p['name']}: {p['images']} photos, RMS {p['rms_px']:.2f} px, max {p['max_px']:.2f} px")
    return L


def _tie_rows(rep: dict) -> list[dict]:
    return [{'point': p['name'], 'image': r['image'], 'used': r['used'],
             'du px': None if r['residual_px'] is None else r['residual_px'][0],
             'dv px': None if r['residual_px'] is None else r['residual_px'][1],
             'residual px': r['residual_norm_px']}
            for p in (rep.get('mtp') or {}).get('points') or [] for r in p['photos']]


def verdict_lines(rep: dict) -> list[str]:
    """The block check's verdict (core/block_check.py) as the report's first lines."""
    v = rep.get('verdict')
    if not v:
        return []
    L = [f"**Verdict: {v['status'].upper()}**" + ('' if v['findings'] else f": {ok_summary(v.get('figures', {}))}"), '']
    for f in v['findings']:
        L.append(f"- {f['status'].upper()} ({f['check']}): {f['text']}")
    fig = v.get('figures', {})
    g, n = fig.get('gnss_fit', {}), fig.get('nadir', {})
    if 'rms_h_m' in g:
        L.append(f"- cameras against their GNSS after a similarity: {g['rms_h_m']:.2f} m H, {g['rms_v_m']:.2f} m V "
                 f"({g['normalised_rms']:.1f}x the GNSS noise of {g['noise_h_m']:.2f} m H / {g['noise_v_m']:.2f} m V)")
    if 'share_within_deg' in n:
        L.append(f"- {100 * n['share_within_deg']:.0f} % of the cameras within {n['deg']:g} degrees of nadir "
                 f"(median tilt {n['median_tilt_deg']:.1f} degrees)")
    elif 'note' in n:
        L.append(f"- nadir: {n['note']}")
    return L + ['']


def heights_text(rep: dict) -> str:
    """What the heights of poses.csv and sparse.ply / sparse.las are (`triangulate --heights`)."""
    crs = rep.get('crs_with_heights') or rep.get('crs') or 'the output CRS'
    if rep.get('heights') == 'orthometric':
        return (f'Heights of poses.csv (z) and sparse.ply / sparse.las: orthometric, above the EGM2008 geoid ({crs}; '
                'poses.csv\'s lat_deg, lon_deg, h_m are WGS84 with ellipsoidal heights).')
    return f'Heights of poses.csv and sparse.ply / sparse.las: WGS84 ellipsoidal ({crs}).'


def markdown(rep: dict) -> str:
    L = ['# Aerial triangulation report', ''] + verdict_lines(rep) + [
         f"Keyframes {rep['registered']}/{rep['keyframes']} oriented, {rep['points']} tie points, "
         f"{rep['observations']} observations; reprojection RMS {_rms_text(rep)}.",
         f"Frame: {rep['frame']}. Origin: {rep['origin']}.", heights_text(rep), '']
    if rep.get('convergence'):
        L += [rep['convergence']['text'] + '.', '']
    if 'gsd_m' in rep:
        L += [f"GSD {rep['gsd_m'] * 100:.2f} cm.", '']
    L += ['## GNSS', ''] + _gnss_text(rep) + ['']
    if rep.get('control'):
        L += ['## Control rows', ''] + _control_lines(rep) + [''] + md_table(_point_rows(rep)) + [''] \
            + md_table(_control_rows(rep)) + ['']
    for key, title in (('gcp', 'Ground control points'), ('check', 'Check points')):
        sec = rep[key]
        L += [f'## {title}', '', f"RMSE {_rmse_line(sec['rmse'])}."]
        if 'rmse_gsd' in sec:
            L += [f"In GSD: horizontal {sec['rmse_gsd']['horizontal']:.2f}, "
                  f"vertical {sec['rmse_gsd']['vertical']:.2f}."]
        L += ce90_text(sec.get('ce90_le90')) + [f'- {t}' for t in sec.get('redundancy', [])] + ['']
        if sec['points']:
            L += md_table(_residual_rows(sec['points'])) + ['']
    if _tie_rows(rep):
        L += ['## Manual tie points', ''] + _tie_text(rep) + [''] + md_table(_tie_rows(rep)) + ['']
    L += ['## Camera', '', f"{rep['camera']}", ''] + [t + '\n' for t in _focal_text(rep)]
    if rep.get('matching'):
        L += ['## Matching', ''] + _matching_text(rep) + ['']
    L += ['## Per image', '']
    L += _table([[p['image'], str(p['observations']), format_cell(p['reprojection_rms_px']),
                  '' if p['gnss_residual_enu_m'] is None else ', '.join(f'{v:.3f}' for v in p['gnss_residual_enu_m']),
                  p.get('note', '')]
                 for p in rep['per_image']], ['image', 'observations', 'RMS px', 'GNSS residual E, N, U m', 'note'])
    if rep['assumptions']:
        L += ['', '## Assumptions', ''] + [f'- {a}' for a in rep['assumptions']]
    return '\n'.join(L) + '\n'


def _residual_rows(points: list[dict]) -> list[dict]:
    out = []
    for p in points:
        r = p.get('residual_m')
        row = {'name': p['name'], 'dX cm': None if r is None else r[0] * 100,
               'dY cm': None if r is None else r[1] * 100,
               'dZ cm': None if r is None or p.get('use') == 'horizontal' else r[2] * 100, 'images': p['images']}
        if 'use' in p:
            row['use'] = p['use']
            row['why'] = p.get('reason', '')
        out.append(row)
    return out


def _self_cal_rows(rep: dict) -> list[dict]:
    sc = rep.get('self_calibration') or {}
    return [{'parameter': k, 'before': v.get('before'), 'after': v.get('after'), 'sigma': v.get('sigma'),
             'corr. with height': v.get('height_correlation')}
            for k, v in sc.items() if isinstance(v, dict) and 'before' in v]


def _selection_rows(sel: dict) -> list[dict]:
    return [{'parameter': d['name'], 'kept': 'yes' if d['kept'] else 'no', 'RMS gain px': d['gain_px'],
             'RMS gain %': None if d['gain_fraction'] is None else 100 * d['gain_fraction'], 'why': d['reason']}
            for d in sel['decisions']]


def _trial_rows(sel: dict) -> list[dict]:
    return [{'refined': ', '.join(t['refine']) or 'none', 'RMS px': t['rms_px'],
             'values': ', '.join(f'{k} {v:.5g}' for k, v in t['values'].items()),
             'bowl m': t.get('bowl_m')} for t in sel['trials']]


def _focal_text(rep: dict) -> list[str]:
    f = (rep.get('self_calibration') or {}).get('focal')
    if not f:
        return []
    if f.get('determined') is False:
        return [f"Focal length NOT DETERMINED: {f['reason']} (correlation with the block's height "
                f"{f['height_correlation']:+.3f}); its sigma is not shown."]
    return [f"Focal length determined {f['reason']} (correlation with the block's height "
            f"{f['height_correlation']:+.3f}, sigma {100 * f['sigma_relative']:.2f} % of f)."]


def _matching_text(rep: dict) -> list[str]:
    m = rep.get('matching')
    if not m:
        return []
    tl = m.get('track_lengths', {})
    longer = sum(v for k, v in tl.items() if int(k) >= 3)
    return [f"{m['photos']} photos, {m['features_median']:.0f} features each (median; fewest {m['features_min']}), "
            f"{m['pairs_verified']}/{m['pairs_tried']} candidate pairs verified ({m['pair_status']}), "
            f"{m['widened_photos']} photos matched with more candidates; {sum(tl.values())} tracks, {longer} through "
            f"3+ photos. Features {m['features_s']:.1f} s, matching {m['matching_s']:.1f} s."]


def _figures(rep: dict, out: Path) -> dict:
    """Draw the report's figures into out; returns caption -> PNG name per section key."""
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
        series_png(out / 'per_image_rms.png', idx, {'RMS px': [np.nan if p['reprojection_rms_px'] is None
                                                                else p['reprojection_rms_px'] for p in pim]},
                   'image (order of registration)', 'px', 'Reprojection RMS per image')
        figs['per_image'] = ('Reprojection RMS per image', 'per_image_rms.png')
    g = [(k, p['gnss_residual_enu_m']) for k, p in enumerate(pim) if p['gnss_residual_enu_m'] is not None]
    if g:
        k = np.array([a for a, _ in g])
        r = np.array([b for _, b in g])
        series_png(out / 'gnss_residuals.png', k, {'X (east)': r[:, 0], 'Y (north)': r[:, 1], 'Z (up)': r[:, 2]},
                   'image (order of registration)', 'm', 'GNSS residuals (adjusted antenna - fix)')
        figs['gnss'] = ('GNSS residuals per image, X/Y/Z', 'gnss_residuals.png')
    ctrl = [('GCP', p) for p in rep['gcp']['points'] if p.get('residual_m') is not None] + \
        [('check', p) for p in rep['check']['points']]
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
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = _figures(rep, out)
    rep['figure_files'] = {k: v[1] for k, v in figs.items()}

    def fig(*keys):
        return [figs[k] for k in keys if k in figs]
    summary = [f"Keyframes {rep['registered']}/{rep['keyframes']} oriented, {rep['points']} tie points, "
               f"{rep['observations']} observations; reprojection RMS {_rms_text(rep)}.",
               f"Frame: {rep['frame']}. Origin: {rep['origin']}.", heights_text(rep)]
    if rep.get('convergence'):
        summary.append(rep['convergence']['text'] + '.')
    if 'gsd_m' in rep:
        summary.append(f"GSD {rep['gsd_m'] * 100:.2f} cm.")
    sections = [Section('Summary', summary, figures=fig('reprojection')),
                Section('GNSS', _gnss_text(rep), figures=fig('gnss'))]
    if rep.get('control'):
        sections.append(Section('Control rows', _control_lines(rep),
                                tables=[('Control points against the GNSS-only block', _point_rows(rep)),
                                        ('Every control row and its fate', _control_rows(rep))]))
    for key, title in (('gcp', 'Ground control points'), ('check', 'Check points')):
        sec = rep[key]
        text = [f"RMSE {_rmse_line(sec['rmse'])}."]
        if 'rmse_gsd' in sec:
            text.append(f"In GSD: horizontal {sec['rmse_gsd']['horizontal']:.2f}, "
                        f"vertical {sec['rmse_gsd']['vertical']:.2f}.")
        text += ce90_text(sec.get('ce90_le90')) + [f'- {t}' for t in sec.get('redundancy', [])]
        rows = _residual_rows(sec['points'])
        sections.append(Section(title, text, tables=[('Residuals (adjusted - surveyed)', rows)] if rows else []))
    if _tie_rows(rep):
        sections.append(Section('Manual tie points', _tie_text(rep),
                                tables=[('Residual per photo (adjusted point reprojected - mark)', _tie_rows(rep))]))
    sections.append(Section('Plan view and control residuals', figures=fig('plan', 'control')))
    cam = Section('Camera', [f"{rep['camera']}"])
    sc_rows = _self_cal_rows(rep)
    if sc_rows:
        s0 = (rep.get('self_calibration') or {}).get('s0_px')
        cam.text.append('Self-calibrated intrinsics with sigma (a-posteriori, scaled by the variance of '
                        'unit weight' + (f' s0 = {s0:.3f} px' if s0 is not None else '') + ').')
        cam.tables.append(('Self-calibration', sc_rows))
    cam.text += _focal_text(rep)
    sel = rep.get('self_calibration_selection')
    if sel:
        cam.text.append(f"Stepwise self-calibration from {', '.join(sel['candidates'])}: kept "
                        f"{', '.join(sel['kept']) or 'none'}. A candidate is kept when it lowers the reprojection "
                        "RMS (every trial on the same observations, residuals capped at the outlier threshold) by "
                        f"at least {100 * sel['min_gain_fraction']:g} % and {sel['min_gain_px']:g} px and moves "
                        f"by at least {sel.get('min_sigmas', 3.0):g} of its sigmas; the bowl is the cameras' against their geotag heights at the block's radius "
                        "(negative: a dome).")
        cam.tables.append(('Stepwise self-calibration: candidates', _selection_rows(sel)))
        cam.tables.append(('Stepwise self-calibration: trials', _trial_rows(sel)))
    sections.append(cam)
    if rep.get('matching'):
        sections.append(Section('Matching', _matching_text(rep)))
    sections.append(Section('Per image', tables=[('Per-image statistics', [
        {'image': p['image'], 'observations': p['observations'], 'RMS px': p['reprojection_rms_px'],
         'note': p.get('note', ''),
         'GNSS dE m': None if p['gnss_residual_enu_m'] is None else p['gnss_residual_enu_m'][0],
         'GNSS dN m': None if p['gnss_residual_enu_m'] is None else p['gnss_residual_enu_m'][1],
         'GNSS dU m': None if p['gnss_residual_enu_m'] is None else p['gnss_residual_enu_m'][2]}
        for p in rep['per_image']])], figures=fig('per_image')))
    if rep['assumptions']:
        sections.append(Section('Assumptions', [f'- {a}' for a in rep['assumptions']]))
    paths = write_sections(out, 'Aerial triangulation report', sections, rep)
    return paths['md'], paths['json']
