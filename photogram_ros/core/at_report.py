"""Aerial-triangulation accuracy figures: reprojection, GNSS, GCP and check-point residuals.

`build_report(at)` gathers every figure of an adjusted IncrementalAT into one dict (written as
report.json; rendered as Markdown and HTML by photogram_ros/io/at_report.py), `intrinsics_sigma`
the a-posteriori sigmas of self-calibrated intrinsics. Residuals are adjusted minus reference in
the `map` ENU frame (X = east, Y = north, Z = up, metres); check points are intersected from the
adjusted cameras and never took part in the adjustment. Manual tie points (MTPs) have no reference:
each one's residual per photo is its adjusted point reprojected minus where it was marked (pixels).
"""

from __future__ import annotations

import numpy as np

from photogram_ros.core.at_geometry import intersect_point, reprojection_residuals_px
from photogram_ros.core.bundle import BundleOptions, bundle_adjust
from photogram_ros.core.evaluation import ce90_le90


def rmse_xyz(res: np.ndarray) -> dict:
    r = np.asarray(res, float).reshape(-1, 3)
    if not len(r):
        return {'n': 0}
    return {'n': int(len(r)), 'x_m': float(np.sqrt(np.mean(r[:, 0] ** 2))),
            'y_m': float(np.sqrt(np.mean(r[:, 1] ** 2))), 'z_m': float(np.sqrt(np.mean(r[:, 2] ** 2))),
            'horizontal_m': float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1)))),
            'vertical_m': float(np.sqrt(np.mean(r[:, 2] ** 2))),
            'total_m': float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))}


def gnss_figures(residuals_enu_m) -> dict:
    """RMSE of GNSS residuals (N, 3) and `spread_m`, their RMS about their mean: a shift of the whole
    block (a GCP moving it onto the survey) is not strain; a bent block (GCPs fighting the GNSS) is."""
    r = np.asarray(residuals_enu_m, float).reshape(-1, 3)
    out = rmse_xyz(r)
    if len(r):
        out['spread_m'] = float(np.sqrt(np.mean(np.sum((r - r.mean(axis=0)) ** 2, axis=1))))
        out['mean_enu_m'] = r.mean(axis=0).tolist()
    return out


def _per_image(at, residuals: list | None = None) -> list[dict]:
    """Per-image statistics; appends each observation's reprojection error (px) to `residuals`. A photo
    without a finite residual has none (None) and says why; points behind its camera are counted."""
    gres = at.gnss_residuals()
    out = []
    for k in at.block.oriented():
        kf = at.block.keyframe(k)
        m = kf.active & np.array([at.block.has_point(int(t)) for t in kf.track_ids], bool)
        rms, note, behind = None, '', 0
        if m.any():
            X = np.array([at.block.point(int(t)) for t in kf.track_ids[m]])
            e = at.reprojection_px(kf.map_T_cam, X, kf.uv[m])
            fin = np.isfinite(e)
            behind = int((~fin).sum())
            if fin.any():
                rms = float(np.sqrt(np.mean(e[fin] ** 2)))
                if residuals is not None:
                    residuals.append(e[fin])
            if behind:
                note = f'{behind} of its tie points are behind the camera (left out of its RMS)'
        else:
            note = ('none of its observations is active on a tie point (all rejected as outliers, or its points '
                    'were not triangulated)')
        if rms is None and m.any():
            note = f'all {behind} of its tie points are behind the camera: its pose is wrong'
        g = gres.get(k)
        row = {'image': kf.name, 'stamp_ns': kf.stamp_ns, 'observations': int(m.sum()) - behind,
               'reprojection_rms_px': rms,
               'gnss_residual_enu_m': None if g is None else [float(v) for v in g],
               'position_map_m': [float(v) for v in kf.map_T_cam[:3, 3]]}
        if note:
            row['note'] = note
        out.append(row)
    return out


def _rmse_gcps(gcps: list[dict]) -> dict:
    """RMSE over the used GCPs, the vertical over those used with their heights only."""
    used = [g for g in gcps if g.get('residual_m') is not None]
    if not used:
        return {'n': 0}
    r = np.array([g['residual_m'] for g in used], float)
    full = np.array([g['use'] != 'horizontal' for g in used])
    out = rmse_xyz(r)
    if not full.all():
        rv = rmse_xyz(r[full]) if full.any() else {}
        out.update(n_vertical=int(full.sum()), z_m=rv.get('z_m'), vertical_m=rv.get('vertical_m'),
                   total_m=rv.get('total_m') if full.all() else None)
    return out


def redundancy_notes(gcps: list[dict]) -> list[str]:
    """What GCP residuals can show (fit, not accuracy; nothing with one GCP or two rays); gcps: dicts with
    name, residual_m (None: not measured) and images."""
    used = [g for g in gcps if g.get('residual_m') is not None]
    out = ['GCP residuals show how well the block was fitted to the GCPs, not its accuracy: the check points '
           'are the accuracy']
    if len(used) == 1:
        out.append(f"one GCP ({used[0]['name']}): the block is fitted to it, so its residual shows nothing about "
                   'the survey or the block')
    for g in used:
        if g['images'] <= 2 and len(used) > 1:
            out.append(f"{g['name']} is in {g['images']} photos: its residual shows next to nothing (two rays pass "
                       'through its prior)')
    return out


def _check_points(at, vetting) -> list[dict]:
    """Check points intersected from the adjusted cameras: from the rows the vetting kept (by photo name),
    else from every observation of the target."""
    out = []
    poses = at.block.poses_by_name()
    for name, c in at.block.control_points().items():
        if vetting is not None:
            p = vetting.points.get(name)
            if p is None or p.role != 'check':
                continue
            rows = [f.row for f in vetting.rows if f.fate == 'used' and f.row.name == name and f.row.image in poses]
            hit = (intersect_point(at.block.camera, np.array([poses[r.image] for r in rows]),
                                   np.array([r.uv for r in rows], float)) if len(rows) >= 2 else None)
        elif c.role == 'gcp' and at.opt.use_gcps:
            continue
        else:
            hit = at.intersect_target(name)
        if hit is not None:
            X, n, rms = hit
            out.append({'name': name, 'residual_m': (X - c.map_xyz).tolist(), 'images': n,
                        'reprojection_rms_px': rms, 'surveyed_map_m': c.map_xyz.tolist()})
    return out


def _gcp_points(at, vetting) -> list[dict]:
    """Each GCP: `residual_m` and `reprojection_rms_px` of the point intersected from the adjusted cameras
    (as a check point), `adjusted_point_residual_m` and `adjusted_point_reprojection_rms_px` of the
    adjusted point (held near its survey by its prior): rays that disagree with the survey show as the
    latter RMS, in px, and as the former residual, in m."""
    gcps = []
    uses = {n: p.use for n, p in vetting.points.items()} if vetting is not None else {}
    for name, c in at.block.control_points().items():
        if uses.get(name) == 'unused':
            p = vetting.points[name]
            gcps.append({'name': name, 'use': 'unused', 'reason': p.reason, 'residual_m': None, 'images': 0,
                         'surveyed_map_m': c.map_xyz.tolist()})
            continue
        if c.role != 'gcp' or not at.opt.use_gcps:
            continue
        use = uses.get(name, 'full')
        tid = at.target_track(name)
        hit = None
        if tid is not None and at.block.has_point(tid):
            Ts, uv = at.observations_of(tid)
            hit = intersect_point(at.block.camera, np.array(Ts), uv) if len(Ts) >= 2 else None
        if hit is not None:
            # Intersected from the adjusted cameras, as a check point: the adjusted point itself sits on its
            # prior even when its rays disagree with it (a robust loss gives up on them), a 0.0 cm lie.
            X, n, rms = hit
            X_adj = np.asarray(at.block.point(tid), float)
            r_adj = reprojection_residuals_px(at.block.camera, np.array(Ts), uv, X_adj)
            g = {'name': name, 'use': use, 'residual_m': (X - c.map_xyz).tolist(), 'images': n,
                 'reprojection_rms_px': rms, 'adjusted_point_residual_m': (X_adj - c.map_xyz).tolist(),
                 'adjusted_point_reprojection_rms_px': float(np.sqrt(np.mean(np.sum(r_adj ** 2, axis=1)))),
                 'surveyed_map_m': c.map_xyz.tolist()}
            if use == 'horizontal':
                g['reason'] = vetting.points[name].reason
        else:
            g = {'name': name, 'use': 'unused', 'residual_m': None, 'images': 0, 'surveyed_map_m': c.map_xyz.tolist(),
                 'reason': 'not observed in any oriented photo' if tid is None else
                           'not triangulated: fewer than two of its observations survived'}
        gcps.append(g)
    return gcps


def tie_points(at) -> list[dict]:
    """Each manual tie point: its adjusted point (map ENU, m; None when it has none), and per photo where
    it was marked, the reprojection residual (adjusted point projected minus the mark, px), whether the
    observation took part in the adjustment, and the RMS over its photos."""
    out = []
    names = set(at.block.oriented_names())
    for name in at.block.tie_names():
        tid = at.target_track(name)
        if tid is None:
            continue
        X = np.asarray(at.block.point(tid), float) if at.block.has_point(tid) else None
        photos = []
        for kf in at.block.keyframes():
            i = kf.index(tid)
            if i is None:
                continue
            row = {'image': kf.name, 'uv_px': [float(v) for v in kf.uv[i]], 'oriented': kf.name in names,
                   'used': bool(kf.active[i]) and kf.name in names, 'residual_px': None, 'residual_norm_px': None}
            if X is not None and kf.map_T_cam is not None:
                T = kf.map_T_cam
                pc = (X - T[:3, 3]) @ T[:3, :3]
                if pc[2] > 1e-9:
                    d = at.block.camera.normalized_to_pixel((pc[:2] / pc[2])[None])[0] - kf.uv[i]
                    row['residual_px'] = [float(v) for v in d]
                    row['residual_norm_px'] = float(np.hypot(*d))
            photos.append(row)
        e = np.array([p['residual_norm_px'] for p in photos if p['used'] and p['residual_norm_px'] is not None])
        out.append({'name': name, 'point_map_m': None if X is None else X.tolist(),
                    'images': sum(p['used'] for p in photos), 'rms_px': float(np.sqrt(np.mean(e ** 2))) if len(e)
                    else None, 'max_px': float(e.max()) if len(e) else None, 'photos': photos,
                    'note': '' if X is not None else 'not triangulated: fewer than two of its photos were oriented'})
    return out


def build_report(at, assumptions: list[str] | None = None, gsd_m: float | None = None, vetting=None,
                 gnss_without_gcps: dict | None = None) -> dict:
    """Every figure of the report from an adjusted IncrementalAT.

    vetting: core/control.py ControlVetting of the control rows (their fates, the GCPs' uses; check
    points are then intersected from the rows it kept); gnss_without_gcps: the GNSS residual RMSE of the
    same block adjusted without GCPs (how much the GCPs strain it)."""
    errs: list = []
    per_image = _per_image(at, errs)
    errs = np.concatenate(errs) if errs else np.zeros(0)
    errs = errs[np.isfinite(errs)]
    nobs = [p['observations'] for p in per_image]
    gres = np.array([p['gnss_residual_enu_m'] for p in per_image if p['gnss_residual_enu_m'] is not None])
    gcps, checks = _gcp_points(at, vetting), _check_points(at, vetting)
    # Per-observation RMS over the whole block (per-image values weighted by their counts).
    total_rms = float(np.sqrt(np.mean(errs ** 2))) if len(errs) else None
    rep = {
        'format': 'photogram_ros aerial triangulation report v1',
        'origin': at.origin.to_dict() if at.origin is not None else None,
        'frame': 'map: ENU at origin (x east, y north, z up), m; heights ellipsoidal',
        'georeferenced': bool(at.georeferenced),
        'keyframes': at.block.n_keyframes, 'registered': at.block.n_oriented, 'points': at.block.n_points,
        'observations': int(sum(nobs)),
        'camera': {'width': at.block.camera.width, 'height': at.block.camera.height, 'fx': at.block.camera.fx, 'fy': at.block.camera.fy,
                   'cx': at.block.camera.cx, 'cy': at.block.camera.cy, 'dist': list(at.block.camera.dist)},
        'reprojection_rms_px': total_rms,
        'gnss': {'rmse': gnss_figures(gres), 'estimated_bias_enu_m': at.datum.bias_enu.tolist()},
        'gcp': {'points': gcps, 'rmse': _rmse_gcps(gcps), 'redundancy': redundancy_notes(gcps) if gcps else []},
        'check': {'points': checks, 'rmse': rmse_xyz(np.array([c['residual_m'] for c in checks])),
                  'ce90_le90': ce90_le90(np.array([c['residual_m'] for c in checks]))},
        'mtp': {'points': tie_points(at)},
        'reprojection_histogram': _histogram(errs),
        'per_image': per_image,
        'assumptions': list(assumptions or []),
    }
    sel = getattr(at, 'self_calibration', None)
    if sel is not None:
        # The stepwise self-calibration: every trial, what each candidate bought and what was kept.
        rep['self_calibration_selection'] = sel.to_dict()
        rep['assumptions'].append(sel.text())
    if vetting is not None:
        rep['control'] = vetting.to_dict()
    if gnss_without_gcps is not None:
        w = gnss_without_gcps.get('spread_m')
        rep['gnss']['without_gcps'] = gnss_without_gcps
        t = rep['gnss']['rmse'].get('spread_m')
        if w and t is not None:
            rep['gnss']['strain_ratio'] = t / w
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
    iterations, covariance on; with the GNSS bias free beside the intrinsics when the block estimated it (a
    flat nadir block trades the bias's height for the focal length, which a sigma with the bias held hides).
    Returns name -> sigma (px for f, cx, cy; unitless for k1..k3), 's0_px' (a-posteriori sigma of unit
    weight) and 'height_correlation' (name -> correlation with the block's height: mean camera height minus
    mean tie-point height), or {} when the block has no datum or nothing to adjust.
    """
    kids, tracks = at.block.oriented(), at.block.point_ids()
    if not refine or not kids or not tracks:
        return {}
    prob = at.problem(kids, [], tracks)
    if prob is None:
        return {}
    res = bundle_adjust(prob, BundleOptions(loss=at.opt.loss, loss_scale_px=at.opt.loss_scale_px,
                                            max_iterations=0, refine_intrinsics=tuple(refine),
                                            compute_covariance=True, gnss_bias_free=at.datum.bias_estimated))
    sig = res.intrinsics_sigma()
    if sig and res.variance_factor is not None:
        sig['s0_px'] = float(np.sqrt(res.variance_factor))
    corr = res.intrinsics_height_correlation()
    if corr:
        sig['height_correlation'] = corr
    return sig


def undetermined_focal(at, refine: tuple) -> dict:
    """focal_determination of the adjusted block `at` when it refined f and does not determine it (else {}): what
    `--self-calibrate auto` holds f for (io/aerial_triangulation.py adjusts the block again with f at its given
    value)."""
    if 'f' not in refine:
        return {}
    focal = focal_determination(at, intrinsics_sigma(at, refine))
    return focal if focal.get('determined') is False else {}


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
    kids = [k for k in at.block.oriented() if at.block.keyframe(k).map_T_cam is not None]
    axis_z = np.array([at.block.keyframe(k).map_T_cam[2, 2] for k in kids])
    tilt = np.degrees(np.arccos(np.clip(-axis_z, -1.0, 1.0)))
    tilt95 = float(np.percentile(tilt, 95)) if len(tilt) else float('nan')
    sv = [float(np.sqrt(at.block.keyframe(k).fix_cov[2, 2])) for k in kids if at.block.keyframe(k).fix_cov is not None]
    sigma_v = float(np.median(sv)) if sv else float('inf')
    gcps = int(at.control_summary().get('gcps_used', 0))
    nadir = tilt95 < NADIR_TILT_DEG and gcps < MIN_GCP_HEIGHTS
    rel = sig['f'] / max(float(at.block.camera.fx), 1e-9)
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


CONVERGED_MOVE_M = 0.01        # more iterations moving no camera by more than this (and ...)
CONVERGED_DECREASE = 1e-3      # ... lowering the cost by less than this fraction) do not matter


def convergence(at, status: str, more_iterations: int = 5) -> dict | None:
    """How far from converged an adjustment that stopped at its iteration limit is: `more_iterations`
    further iterations from its result (not applied), their relative cost decrease (the first one's: the
    stopped adjustment's next step) and the largest camera move; None when it converged."""
    if status != 'max_iterations' or not at.block.n_oriented:
        return None
    kids = at.block.oriented()
    prob = at.problem(kids, [], at.block.point_ids())
    if prob is None:
        return None
    res = bundle_adjust(prob, BundleOptions(loss=at.opt.loss, loss_scale_px=at.opt.loss_scale_px,
                                            max_iterations=more_iterations))
    c0 = float(res.initial_cost)
    hist = [c0] + [float(c) for c in res.cost_history]
    first = (hist[0] - hist[1]) / hist[0] if len(hist) > 1 and hist[0] > 0 else 0.0
    total = (hist[0] - hist[-1]) / hist[0] if hist[0] > 0 else 0.0
    move = float(np.max(np.linalg.norm(np.asarray(res.map_T_cams)[:, :3, 3] - prob.map_T_cams[:, :3, 3], axis=1)))
    matters = bool(move > CONVERGED_MOVE_M or total > CONVERGED_DECREASE)
    return {'status': status, 'next_relative_cost_decrease': first, 'relative_cost_decrease_more': total,
            'more_iterations': more_iterations, 'max_camera_move_m': move, 'matters': matters,
            'text': (f'the final adjustment stopped at its iteration limit; {more_iterations} more iterations would '
                     f'lower the cost by {100 * total:.3g} % (the next one by {100 * first:.3g} %) and move no camera '
                     f'by more than {100 * move:.2f} cm: ' + ('that MATTERS, the figures are not final' if matters
                                                               else 'that does not matter'))}
