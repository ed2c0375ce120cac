"""Aerial-triangulation accuracy figures: reprojection, GNSS, GCP and check-point residuals.

`build_report(at)` gathers every figure of an adjusted IncrementalAT into one dict (written as
report.json; rendered as Markdown and HTML by photogram_ros/io/at_report.py), `intrinsics_sigma`
the a-posteriori sigmas of self-calibrated intrinsics. Residuals are adjusted minus reference in
the `map` ENU frame (X = east, Y = north, Z = up, metres); check points are intersected from the
adjusted cameras and never took part in the adjustment.
"""

from __future__ import annotations

import numpy as np

from photogram_ros.core.bundle import BundleOptions, bundle_adjust


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
            e = at.reprojection_px(kf.map_T_cam, X, kf.uv[m])
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
        tid = at.target_track(name)
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
    's0_px' (a-posteriori sigma of unit weight), or {} when the block has no datum or nothing to adjust.
    """
    kids, tracks = list(at.registered), list(at.points)
    if not refine or not kids or not tracks:
        return {}
    prob = at.problem(kids, [], tracks)
    if prob is None:
        return {}
    res = bundle_adjust(prob, BundleOptions(loss=at.opt.loss, loss_scale_px=at.opt.loss_scale_px,
                                            max_iterations=0, refine_intrinsics=tuple(refine),
                                            compute_covariance=True))
    sig = res.intrinsics_sigma()
    if sig and res.variance_factor is not None:
        sig['s0_px'] = float(np.sqrt(res.variance_factor))
    return sig
