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


# |correlation| of the focal length with the block's height above which f is reported as not
# determined: the adjustment can trade one for the other (a flat nadir block without GCP heights).
F_UNDETERMINED_CORRELATION = 0.9


def intrinsics_sigma(at, refine: tuple) -> dict:
    """A-posteriori sigmas of the self-calibrated intrinsics at the adjusted block.

    The full adjustment of IncrementalAT does not ask for covariances, so this evaluates them at its
    result: the same problem (every registered keyframe and point, GNSS and GCP priors), zero
    iterations, covariance on. Returns name -> sigma (px for f, cx, cy; unitless for k1..k3),
    's0_px' (a-posteriori sigma of unit weight) and 'height_correlation' (name -> correlation with the
    block's height: mean camera height minus mean tie-point height), or {} when the block has no datum
    or nothing to adjust.
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
    corr = res.intrinsics_height_correlation()
    if corr:
        sig['height_correlation'] = corr
    return sig


NADIR_TILT_DEG = 5.0            # a block whose cameras (95 %) are within this of nadir is near-nadir
LOOSE_GNSS_SIGMA_V_M = 0.5      # camera heights from a GNSS this loose do not hold the block's depth
MIN_GCP_HEIGHTS = 3


def focal_determination(at, sig: dict) -> dict:
    """Whether the block determines a self-calibrated focal length, and why (the report's figures).

    A near-nadir block flown at one height images the ground at the scale f / depth: the focal length
    and the ground's depth trade off, held only by the cameras' small tilts and, through the depth, by
    GCPs with surveyed heights or tight (RTK) camera heights. Not determined: near-nadir, fewer than
    3 GCPs with heights and GNSS heights looser than 0.5 m (the small sigma of the covariance assumes
    a perfect camera model: real blocks move f by 15-20 % there), or a correlation of f with the
    block's height of 0.9 or more with a sigma above 0.1 % of f. Near-nadir without GCP heights but
    with RTK heights: weakly determined. Returns {} when f was not refined.
    """
    c = sig.get('height_correlation', {}).get('f')
    if c is None or 'f' not in sig:
        return {}
    kids = [k for k in at.registered if at.kfs[k].map_T_cam is not None]
    axis_z = np.array([at.kfs[k].map_T_cam[2, 2] for k in kids])
    tilt = np.degrees(np.arccos(np.clip(-axis_z, -1.0, 1.0)))
    tilt95 = float(np.percentile(tilt, 95)) if len(tilt) else float('nan')
    sv = [float(np.sqrt(at.kfs[k].fix_cov[2, 2])) for k in kids if at.kfs[k].fix_cov is not None]
    sigma_v = float(np.median(sv)) if sv else float('inf')
    gcps = int(at.control_summary().get('gcps_used', 0))
    nadir = tilt95 < NADIR_TILT_DEG and gcps < MIN_GCP_HEIGHTS
    rel = sig['f'] / max(float(at.camera.fx), 1e-9)
    out = {'height_correlation': float(c), 'sigma_relative': float(rel), 'tilt_p95_deg': tilt95,
           'gnss_sigma_v_m': sigma_v, 'gcps_with_heights': gcps}
    if nadir and sigma_v >= LOOSE_GNSS_SIGMA_V_M:
        out.update(determined=False, reason=f'a near-nadir block (95 % of the cameras within {tilt95:.1f} deg of '
                   f'nadir) without GCP heights ({gcps} used) and with loose GNSS heights (sigma {sigma_v:.1f} m)')
    elif abs(c) >= F_UNDETERMINED_CORRELATION and rel >= 1e-3:
        out.update(determined=False, reason=f'its correlation with the block\'s height is {c:+.3f} with a sigma of '
                   f'{100 * rel:.2f} % of f')
    elif nadir:
        out.update(determined=True, weak=True, reason=f'weakly: a near-nadir block (tilts within {tilt95:.1f} deg) '
                   'without GCP heights, held by the camera heights and the small tilts (the sigma assumes a '
                   'perfect camera model)')
    else:
        out.update(determined=True, reason='oblique views or GCP heights hold the depth')
    return out
