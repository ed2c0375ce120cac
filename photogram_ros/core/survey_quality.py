"""Is the survey good enough? Live accuracy figures and the go / no-go verdict against the user's limits.

- `fix_class(fix)`: what a keyframe's GNSS fix was, from the NavSatFix status and its horizontal sigma
  (the keyframe fix carries no MAVLink fix type: RTK float and fixed are both GBAS, and a fixed
  solution is the one at centimetre level): 'rtk_fixed', 'rtk_float', 'dgps', '3d', 'none'.
- `rmse(residuals)`: horizontal and vertical RMSE with the count, NaN without residuals.
- `go_no_go(figures, limits)`: each check against its limit; the verdict is NO-GO when a measured figure
  fails, WAIT while a figure it needs is provisional (accuracy from a block not georeferenced for good) or
  not measured yet (fewer check points than asked), GO when every figure is measured and passes. The
  largest gap is over every gap kind the map lists (coverage, not oriented, forward overlap). The adjuster's
  check of the block's shape (core/block_check.py) counts too: FAILED after the final adjustment is NO-GO,
  in flight WAIT (the final adjustment may mend it); its warning is a warning.
No ROS here; bundle_node computes the figures, the ground station the verdict.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from photogram_ros.core.gnss_fix import STATUS_FIX, STATUS_GBAS_FIX, STATUS_SBAS_FIX
from photogram_ros.params import param

FIX_CLASSES = ('rtk_fixed', 'rtk_float', 'dgps', '3d', 'none')
RTK_FIXED_MAX_SIGMA_M = 0.05   # an RTK-fixed receiver reports 1-3 cm; float 0.1-0.5 m
GO, NO_GO, WAIT = 'GO', 'NO-GO', 'WAIT'


def fix_class(fix) -> str:
    """A core.gnss_fix.GnssFix (or None) -> one of FIX_CLASSES."""
    if fix is None or fix.status < STATUS_FIX:
        return 'none'
    if fix.status >= STATUS_GBAS_FIX:
        return 'rtk_fixed' if fix.horizontal_sigma_m <= RTK_FIXED_MAX_SIGMA_M else 'rtk_float'
    return 'dgps' if fix.status == STATUS_SBAS_FIX else '3d'


def rmse(residuals_m) -> dict:
    """(N, 3) residuals (E, N, U), m -> {'horizontal_m', 'vertical_m', 'count'}."""
    r = np.asarray(residuals_m, float).reshape(-1, 3)
    if not len(r):
        return {'horizontal_m': math.nan, 'vertical_m': math.nan, 'count': 0}
    return {'horizontal_m': float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1)))),
            'vertical_m': float(np.sqrt(np.mean(r[:, 2] ** 2))), 'count': int(len(r))}


@dataclass
class QualityLimits:
    """The go / no-go line: what the user accepts (0 or an empty limit turns its check off)."""
    max_check_rmse_h_m: float = param(0.05, 'Check points: largest horizontal RMSE, m (0: not checked)',
                                      min=0.0, max=1e4)
    max_check_rmse_v_m: float = param(0.0, 'Check points: largest vertical RMSE, m (0: not checked)',
                                      min=0.0, max=1e4)
    min_check_points: int = param(1, 'Check points that must be measured before the RMSE counts', min=0, max=10000)
    min_coverage: float = param(0.98, 'Smallest share of the passed survey area seen twice and by a stereo pair '
                                      '(0: not checked)', min=0.0, max=1.0)
    max_gap_m2: float = param(25.0, 'Largest coverage gap accepted, m^2 (0: any gap fails)', min=0.0, max=1e9)
    min_rtk_fixed_share: float = param(0.0, 'Smallest share of keyframes with an RTK fixed solution (0: not '
                                            'checked)', min=0.0, max=1.0)
    nogo_confidence: float = param(0.95, 'Check points: NO-GO only when the RMSE exceeds its limit at this '
                                         'confidence (the chi-square bound of an RMSE over so few points); between '
                                         'the limit and that bound: WAIT. 0: NO-GO on the estimate alone',
                                   min=0.0, max=0.999)


# How far a figure can be trusted (the `status` of each check).
MEASURED, PROVISIONAL, NOT_MEASURED = 'measured', 'provisional', 'not measured'
GEOREF_FINAL, GEOREF_PROVISIONAL, GEOREF_NONE, GEOREF_UNKNOWN = 'final', 'provisional', 'none', 'unknown'
# Which adjustment the accuracy figures come from: the in-flight block (window adjustments since the last full
# one) or the whole block adjusted after its last keyframe (the final adjustment).
BLOCK_IN_FLIGHT, BLOCK_ADJUSTED = 'in_flight', 'adjusted'
BLOCK_CHECK_STATUSES = ('ok', 'warning', 'failed')   # core/block_check.py BlockVerdict.status
BLOCK_CHECK_NAME = "the adjuster's check of the block"   # the go / no-go's check of it


def _check(name: str, value, limit: float, ok_when: str, status: str = MEASURED, why: str = '') -> dict:
    """One figure against its limit. state: GO / NO_GO for a measured figure, WAIT otherwise."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        status, value = NOT_MEASURED, None
    ok = None if value is None else (value <= limit if ok_when == 'max' else value >= limit)
    state = WAIT if status != MEASURED else GO if ok else NO_GO
    return {'name': name, 'value': value, 'limit': limit, 'op': '<=' if ok_when == 'max' else '>=',
            'status': status, 'why': why, 'passes': ok, 'state': state}


def rmse_lower_bound(rmse_m: float, count: int, axes: int, confidence: float) -> float:
    """One-sided lower confidence bound of an RMSE over `count` points with `axes` error components each
    (2 horizontal, 1 vertical): the true RMSE is above it with probability `confidence`, taking the
    errors as normal (sum of squares ~ sigma^2 chi-square with count * axes degrees of freedom)."""
    from scipy.stats import chi2
    dof = max(int(count) * axes, 1)
    return float(rmse_m * math.sqrt(dof / chi2.ppf(confidence, dof))) if confidence > 0 else float(rmse_m)


def largest_gap(gaps) -> tuple[float, str]:
    """[{'kind', 'area_m2', 'min_views'}, ...] (every kind the map lists) -> (largest area m^2, what it is);
    (0, '') without a gap."""
    best = max(gaps or [], key=lambda g: float(g.get('area_m2') or 0.0), default=None)
    if best is None:
        return 0.0, ''
    views = best.get('min_views')
    seen = f', seen by {views} keyframes of other lines' if best.get('kind') == 'forward_overlap' and views else ''
    return float(best.get('area_m2') or 0.0), f"{best.get('kind')} gap{seen}"


def go_no_go(figures: dict, limits: QualityLimits) -> dict:
    """The verdict on what is known so far.

    figures (each optional):
      'check_rmse' {'horizontal_m', 'vertical_m', 'count'}: the check points' RMSE;
      'georeference': the state of the block the accuracy figures come from: GEOREF_FINAL (georeferenced
        for good), GEOREF_PROVISIONAL (on a first straight line: the roll about it is not known yet),
        GEOREF_NONE or GEOREF_UNKNOWN (the station has not heard); only GEOREF_FINAL figures are judged;
      'block': BLOCK_IN_FLIGHT or BLOCK_ADJUSTED (the adjustment the check points come from); a check that
        is not GO on the in-flight block says so in its reason (the final adjustment may move it);
      'coverage_share'; 'gaps' [{'kind', 'area_m2'}] every gap the map lists, whatever its kind
        (coverage, not_oriented, forward_overlap); else 'largest_gap_m2';
      'fix_share' {class: share};
      'low_forward_overlap' [{'overlap', 'area_m2'}]: consecutive keyframes of a line overlapping less than
        the target (the ground between them seen, else it is a forward_overlap gap): a warning each;
      'block_check' {'status': one of BLOCK_CHECK_STATUSES, 'summary'}: the adjuster's last check of the block
        (folded, far from its GNSS, not converged): failed is NO-GO from the block adjusted after its last
        keyframe ('block' BLOCK_ADJUSTED), WAIT from the in-flight block; a warning is a warning.
    -> {'verdict', 'checks': [{'name', 'value', 'limit', 'op', 'status', 'why', 'passes', 'state'}],
        'reasons': [...], 'warnings': [...]}: NO-GO when a measured figure fails its limit; else WAIT while
        a figure is provisional or not measured (the reason says which); else GO. Warnings do not change it.
    """
    checks = []
    cp = figures.get('check_rmse') or {}
    n_cp = int(cp.get('count') or 0)
    need = max(limits.min_check_points, 1)
    geo = figures.get('georeference', GEOREF_FINAL)
    if n_cp < need:
        acc_status, acc_why = NOT_MEASURED, f'{n_cp} of {need} check points measured'
    elif geo != GEOREF_FINAL:
        acc_status = PROVISIONAL
        acc_why = {GEOREF_PROVISIONAL: 'the block is georeferenced provisionally (first line)',
                   GEOREF_NONE: 'the block is not georeferenced yet'}.get(
            geo, 'the block\'s georeference is not known to the station')
    else:
        acc_status, acc_why = MEASURED, ''
    for axis, limit, axes in (('horizontal', limits.max_check_rmse_h_m, 2), ('vertical', limits.max_check_rmse_v_m, 1)):
        if limit <= 0:
            continue
        v = cp.get(f'{axis}_m') if n_cp else None
        c = _check(f'check points {axis} RMSE (m)', v, limit, 'max', acc_status, acc_why)
        if c['state'] == NO_GO and limits.nogo_confidence > 0:
            low = rmse_lower_bound(v, n_cp, axes, limits.nogo_confidence)
            c['lower_bound'] = low
            if low <= limit:
                c['state'] = WAIT
                c['why'] = (f'above the limit, but {n_cp} check points cannot tell at '
                            f'{100 * limits.nogo_confidence:.0f} % (lower bound {_fmt(low)})')
        if c['status'] == MEASURED and c['state'] != GO and figures.get('block') == BLOCK_IN_FLIGHT:
            c['why'] = '; '.join(w for w in (c['why'], 'from the in-flight block, before its final adjustment')
                                 if w)
        checks.append(c)
    if limits.min_coverage > 0:
        checks.append(_check('coverage', figures.get('coverage_share'), limits.min_coverage, 'min'))
    if 'gaps' in figures:
        area, why = largest_gap(figures['gaps'])
    else:
        area, why = figures.get('largest_gap_m2'), ''
    checks.append(_check('largest gap, any kind (m²)', area, limits.max_gap_m2, 'max', MEASURED, why))
    if limits.min_rtk_fixed_share > 0:
        share = (figures.get('fix_share') or {}).get('rtk_fixed')
        checks.append(_check('keyframes RTK fixed', share, limits.min_rtk_fixed_share, 'min'))
    block_check = figures.get('block_check') or {}
    if block_check.get('status') == 'failed':
        final = figures.get('block') == BLOCK_ADJUSTED
        checks.append({'name': BLOCK_CHECK_NAME, 'value': 'failed', 'limit': 'ok', 'op': '==',
                       'status': MEASURED if final else PROVISIONAL, 'passes': False, 'state': NO_GO if final else WAIT,
                       'why': block_check.get('summary', '') + ('' if final else ' (the in-flight block, before its '
                                                                'final adjustment)')})
    states = [c['state'] for c in checks]
    verdict = NO_GO if NO_GO in states else WAIT if WAIT in states else GO
    warnings = ([f"the adjuster's check of the block: {block_check.get('summary', '')}"]
                if block_check.get('status') == 'warning' else []) + [f"forward overlap {100 * w['overlap']:.0f} % between two keyframes of a line, below the target"
                + (f": {w['area_m2']:.0f} m² between them" if w.get('area_m2') is not None else '')
                for w in figures.get('low_forward_overlap') or []]
    return {'verdict': verdict, 'checks': checks, 'reasons': [reason(c) for c in checks if c['state'] != GO],
            'warnings': warnings}


def reason(c: dict) -> str:
    """A check that is not GO, in words: 'check points horizontal RMSE (m): 6.08 (<= 0.05), provisional: ...'."""
    if c['value'] is None:
        return f"{c['name']}: not measured yet" + (f" ({c['why']})" if c['why'] else '')
    if isinstance(c['value'], str):     # a check's outcome in words (the block check): its reason
        return f"{c['name']}: {c['value']}" + (f": {c['why']}" if c['why'] else '')
    text = f"{c['name']}: {_fmt(c['value'])} ({c['op']} {_fmt(c['limit'])})"
    if c['status'] == PROVISIONAL:
        return text + f", provisional: {c['why']}"
    return text + (f", {c['why']}" if c['why'] else '')
def _fmt(v: float) -> str:
    return f'{v:.0f}' if abs(v) >= 100 else f'{v:.3g}'
