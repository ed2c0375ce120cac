"""Aerial-triangulation accuracy report: reprojection, GNSS, GCP and check-point residuals.

`build_report(at)` gathers every figure into one dict (written as report.json); `markdown(report)`
renders the same figures for people. Residuals are adjusted minus reference in the `map` ENU frame
(X = east, Y = north, Z = up, metres); check points are intersected from the adjusted cameras and
never took part in the adjustment.
"""

from __future__ import annotations

import json
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


def _per_image(at) -> list[dict]:
    gres = at.gnss_residuals()
    out = []
    for k in at.registered:
        kf = at.kfs[k]
        m = kf.active & np.array([int(t) in at.points for t in kf.track_ids])
        if m.any():
            X = np.array([at.points[int(t)] for t in kf.track_ids[m]])
            e = at._reprojection_px(kf.map_T_cam, X, kf.uv[m])
            rms = float(np.sqrt(np.mean(e ** 2)))
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
    per_image = _per_image(at)
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
                gcps.append({'name': name, 'residual_m': r.tolist(), 'images': len(Ts)})
        else:
            hit = at.intersect_target(name)
            if hit is not None:
                X, n, rms = hit
                checks.append({'name': name, 'residual_m': (X - c.map_xyz).tolist(), 'images': n,
                               'reprojection_rms_px': rms})
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
        'per_image': per_image,
        'assumptions': list(assumptions or []),
    }
    if gsd_m:
        rep['gsd_m'] = gsd_m
        ck = rep['check']['rmse']
        if ck.get('n'):
            rep['check']['rmse_gsd'] = {'horizontal': ck['horizontal_m'] / gsd_m, 'vertical': ck['vertical_m'] / gsd_m}
    return rep


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


def write_report(rep: dict, out_dir) -> tuple[Path, Path]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / 'report.md', out / 'report.json'
    md.write_text(markdown(rep))
    js.write_text(json.dumps(rep, indent=1, default=float))
    return md, js
