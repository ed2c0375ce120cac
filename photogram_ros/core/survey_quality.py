"""Is the survey good enough? Live accuracy figures and the go / no-go verdict against the user's limits.

- `fix_class(fix)`: what a keyframe's GNSS fix was, from the NavSatFix status and its horizontal sigma
  (the keyframe fix carries no MAVLink fix type: RTK float and fixed are both GBAS, and a fixed
  solution is the one at centimetre level): 'rtk_fixed', 'rtk_float', 'dgps', '3d', 'none'.
- `rmse(residuals)`: horizontal and vertical RMSE with the count, NaN without residuals.
- `go_no_go(figures, limits)`: each check against its limit; the verdict is GO when all pass, NO-GO
  when one fails, WAIT while a figure it needs is not measured yet (no check point seen so far).
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


def _check(name: str, value, limit: float, ok_when: str) -> dict:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return {'name': name, 'value': None, 'limit': limit, 'state': WAIT}
    ok = value <= limit if ok_when == 'max' else value >= limit
    return {'name': name, 'value': value, 'limit': limit, 'state': GO if ok else NO_GO}


def go_no_go(figures: dict, limits: QualityLimits) -> dict:
    """figures: 'check_rmse' ({'horizontal_m', 'vertical_m', 'count'}), 'coverage_share', 'largest_gap_m2',
    'fix_share' ({class: share}) as far as known -> {'verdict', 'checks': [...], 'reasons': [...]}."""
    checks = []
    cp = figures.get('check_rmse') or {}
    enough = cp.get('count', 0) >= max(limits.min_check_points, 1)
    if limits.max_check_rmse_h_m > 0:
        checks.append(_check('check points horizontal RMSE (m)', cp.get('horizontal_m') if enough else None,
                             limits.max_check_rmse_h_m, 'max'))
    if limits.max_check_rmse_v_m > 0:
        checks.append(_check('check points vertical RMSE (m)', cp.get('vertical_m') if enough else None,
                             limits.max_check_rmse_v_m, 'max'))
    if limits.min_coverage > 0:
        checks.append(_check('coverage', figures.get('coverage_share'), limits.min_coverage, 'min'))
    checks.append(_check('largest gap (m²)', figures.get('largest_gap_m2'), limits.max_gap_m2, 'max'))
    if limits.min_rtk_fixed_share > 0:
        share = (figures.get('fix_share') or {}).get('rtk_fixed')
        checks.append(_check('keyframes RTK fixed', share, limits.min_rtk_fixed_share, 'min'))
    states = [c['state'] for c in checks]
    verdict = NO_GO if NO_GO in states else WAIT if WAIT in states else GO
    reasons = [f"{c['name']}: {'not measured yet' if c['value'] is None else _fmt(c['value'])} "
               f"({'<=' if c['name'].startswith(('check', 'largest')) else '>='} {_fmt(c['limit'])})"
               for c in checks if c['state'] != GO]
    return {'verdict': verdict, 'checks': checks, 'reasons': reasons}


def _fmt(v: float) -> str:
    return f'{v:.3g}'
