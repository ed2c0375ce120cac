"""Stepwise self-calibration: which of the candidate intrinsics a block's final adjustment refines (no ROS here).

In: the candidate intrinsics (names of core/bundle's `refine_intrinsics`: 'f', 'cx', 'cy', 'k1', 'k2', 'p1',
'p2', 'k3'), intrinsics always refined (`base`, usually none), and `evaluate(refine) -> Trial`: the block
adjusted with `refine` self-calibrated, from one and the same starting state and on one and the same set of
observations, returning the reprojection RMS (px) and, where known, the refined values, their sigmas and
correlations with the block's height, and the cameras' bowl against their geotag heights (`height_bowl`).
Out: a `Selection`: every trial in the order made, the intrinsics kept, and per candidate why (kept, or its
gain and why it was too small), as a dict for the report and one line of text.

The rule (greedy forward selection, best first, the way photogrammetric self-calibration adds additional
parameters): from `base`, each round tries every remaining candidate added to the kept set and takes the one
that lowers the reprojection RMS most; it is kept when that gain is at least `min_gain_fraction` of the
RMS before and `min_gain_px`, and the parameter is determined (it moved from its given value by at least
`min_sigmas` of its a-posteriori sigma, where the trial says); otherwise the selection stops. The correlation
with the block's height is reported, not used: with precise geotags holding the cameras a real lens's k1 correlates
with the ground's depth (-0.95 on the simulator's PPK flight) and is worth 22 % of the RMS, and left out it bends
the block by metres. A statistical test alone would
keep anything: with thousands of observations a gain of a thousandth of a pixel is significant, while a
parameter bought for that little can bend a flat nadir block of parallel lines (radial distortion against the
block's curvature). The thresholds are practical ones (`MIN_GAIN_FRACTION`): a parameter must buy a share of
the image residuals a lens model explains, not noise.

`height_bowl(xy_m, dz_m)`: the quadratic part of (camera height minus geotag height) over the block, its rise at
the block's radius and the scatter about it: how much a block domes against its geotags and how much their own
consistency allows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from photogram_ros.errors import ConfigError

INTRINSICS = ('f', 'cx', 'cy', 'k1', 'k2', 'p1', 'p2', 'k3')

# A candidate is kept when it lowers the reprojection RMS by at least this fraction of it (and MIN_GAIN_PX).
# Measured (bench/notes_dsm_shape.md): on brighton (18 DJI photos) k2 lowers it by 9 % (0.695 -> 0.633 px), k1
# after it by 0.4 % (-> 0.631 px) while doming the block 0.4 m deeper against the drone's altitudes; on the
# simulator (lens k1 -0.12) k1 lowers it by tens of percent. 2 % lies a factor 4-5 from both.
MIN_GAIN_FRACTION = 0.02
MIN_GAIN_PX = 0.005
# A candidate that pays is kept when it moved from its given value by at least this many a-posteriori sigmas.
MIN_SIGMAS = 3.0


@dataclass
class Trial:
    """One adjustment of the block with `refine` self-calibrated: its reprojection RMS (px, over the same
    observations for every trial), the refined values, their a-posteriori sigmas and correlations with the
    block's height (name -> value; empty when not computed), the cameras' bowl against their geotag heights at
    the block's radius (m, negative: a dome; None when not known) and the adjustment's status."""
    refine: tuple
    rms_px: float
    values: dict = field(default_factory=dict)
    moved: dict = field(default_factory=dict)      # name -> refined value minus its given value
    sigmas: dict = field(default_factory=dict)
    height_correlation: dict = field(default_factory=dict)
    bowl_m: float | None = None
    status: str = ''

    def to_dict(self) -> dict:
        out = {'refine': list(self.refine), 'rms_px': float(self.rms_px), 'values': dict(self.values)}
        if self.moved:
            out['moved'] = dict(self.moved)
        if self.sigmas:
            out['sigmas'] = dict(self.sigmas)
        if self.height_correlation:
            out['height_correlation'] = dict(self.height_correlation)
        if self.bowl_m is not None:
            out['bowl_m'] = float(self.bowl_m)
        if self.status:
            out['status'] = self.status
        return out


@dataclass
class Decision:
    """What became of one candidate: kept or not, its best gain (px and fraction of the RMS before) and why."""
    name: str
    kept: bool
    gain_px: float | None
    gain_fraction: float | None
    reason: str

    def to_dict(self) -> dict:
        return {'name': self.name, 'kept': self.kept, 'gain_px': self.gain_px, 'gain_fraction': self.gain_fraction,
                'reason': self.reason}


@dataclass
class Selection:
    """The stepwise self-calibration's outcome: the candidates, the kept intrinsics (base first, in the order
    added), every trial and one decision per candidate."""
    candidates: tuple
    kept: tuple
    trials: list
    decisions: list
    min_gain_fraction: float
    min_gain_px: float
    min_sigmas: float = MIN_SIGMAS
    base: tuple = ()

    def to_dict(self) -> dict:
        return {'method': 'stepwise', 'candidates': list(self.candidates), 'kept': list(self.kept),
                'min_gain_fraction': self.min_gain_fraction, 'min_gain_px': self.min_gain_px,
                'min_sigmas': self.min_sigmas, 'base': list(self.base),
                'decisions': [d.to_dict() for d in self.decisions], 'trials': [t.to_dict() for t in self.trials]}

    def text(self) -> str:
        """One line for the report's assumptions: what was tried, what each bought and what was kept."""
        first = self.trials[0] if self.trials else None
        parts = []
        for d in self.decisions:
            if d.gain_px is None:
                parts.append(f'{d.name}: {d.reason}')
            else:
                parts.append(f'{d.name} {"KEPT" if d.kept else "left out"}: it '
                             f'{"lowers" if d.gain_px >= 0 else "raises"} the reprojection RMS by '
                             f'{abs(d.gain_px):.4f} px ({100 * abs(d.gain_fraction):.2f} %; {d.reason})')
        bowls = [f'{"+".join(t.refine) or "none"} {t.bowl_m:+.2f} m' for t in self.trials if t.bowl_m is not None]
        base = ', '.join(self.base)
        return (f'self-calibration (stepwise from {", ".join(self.candidates)}'
                + (f'; {base} refined throughout' if base else '') + f'): kept {", ".join(self.kept) or "none"}; '
                + (f'with {base or "none"} refined {first.rms_px:.4f} px; ' if first is not None else '')
                + '; '.join(parts)
                + f' (a parameter is kept when it lowers the reprojection RMS by >= {100 * self.min_gain_fraction:g} '
                  f'% and >= {self.min_gain_px:g} px and moves by >= {self.min_sigmas:g} of its sigmas)'
                + (f'; the cameras\' bowl against their geotag heights at the block\'s radius per trial: '
                   f'{", ".join(bowls)}' if bowls else ''))


def select_stepwise(candidates, evaluate: Callable[[tuple], Trial], base: tuple = (),
                    min_gain_fraction: float = MIN_GAIN_FRACTION, min_gain_px: float = MIN_GAIN_PX,
                    min_sigmas: float = MIN_SIGMAS,
                    determine: Callable[[Trial], None] | None = None) -> Selection:
    """Greedy forward selection of `candidates` (see the module docstring); `evaluate(refine)` adjusts the block
    with `refine` (base plus the candidates so far plus one) from the same start and returns its Trial;
    `determine(trial)`, when given, fills in the trial's sigmas and height correlations (a covariance: asked
    only of a candidate that pays enough to be kept). Raises ConfigError on a name that is not an intrinsic, or
    on thresholds that are not positive."""
    candidates = tuple(dict.fromkeys(c for c in candidates if c not in base))
    bad = [c for c in (*candidates, *base) if c not in INTRINSICS]
    if bad:
        raise ConfigError(f'self-calibration: {bad} are not intrinsics; choose from {", ".join(INTRINSICS)}')
    if not (min_gain_fraction >= 0 and min_gain_px >= 0 and min_sigmas >= 0):
        raise ConfigError('self-calibration: the gain thresholds and min_sigmas must be >= 0')
    kept = tuple(base)
    current = evaluate(kept)
    trials = [current]
    decisions: dict[str, Decision] = {}
    remaining = list(candidates)
    while remaining:
        tried = [(c, evaluate(kept + (c,))) for c in remaining]
        trials += [t for _, t in tried]
        gains = {c: current.rms_px - t.rms_px for c, t in tried}
        for c, t in tried:
            g = gains[c]
            frac = g / current.rms_px if current.rms_px > 0 else 0.0
            decisions[c] = Decision(c, False, float(g), float(frac), '')
        order = sorted(tried, key=lambda ct: -gains[ct[0]] if np.isfinite(gains[ct[0]]) else np.inf)
        best, t = order[0]
        d = decisions[best]
        pays = d.gain_fraction >= min_gain_fraction and d.gain_px >= min_gain_px
        if pays and determine is not None and np.isfinite(t.rms_px) and t.status != 'failed':
            determine(t)
        sig, moved = t.sigmas.get(best), t.moved.get(best)
        if not np.isfinite(t.rms_px) or t.status == 'failed':
            d.reason = 'its adjustment failed'
        elif not pays:
            d.reason = f'below the threshold {100 * min_gain_fraction:g} % / {min_gain_px:g} px'
        elif sig is not None and moved is not None and abs(moved) < min_sigmas * sig:
            d.reason = f'not determined: moved {moved:+.4g}, under {min_sigmas:g} sigma ({sig:.3g})'
        else:
            d.kept = True
            d.reason = f'best of {", ".join(remaining)} at this step'
        if not d.kept:
            for c, _ in order[1:]:
                decisions[c].reason = f'less than {best}\'s gain at this step'
            break
        kept += (best,)
        current = t
        remaining.remove(best)
        for c in remaining:
            decisions.pop(c, None)
    for c in candidates:
        decisions.setdefault(c, Decision(c, False, None, None, 'not tried'))
    return Selection(candidates, kept, trials, [decisions[c] for c in candidates], float(min_gain_fraction),
                     float(min_gain_px), float(min_sigmas), tuple(base))


def height_bowl(xy_m, dz_m, radius_m: float | None = None) -> dict:
    """The bowl of `dz_m` (N,) (camera height minus geotag height, m) over the cameras' horizontal positions
    `xy_m` (N, 2): a quadratic surface fitted by least absolute deviations (iteratively reweighted), then by least
    squares over the cameras it does not reject. Returns its quadratic part's rise at `radius_m` from the
    cameras' centre along the mean curvature (`rise_m`; negative: the cameras dome against their geotags; radius
    default: the farthest camera), its curvatures (1/km), the scatter of dz about the surface (`scatter_m`: the
    RMS about it of the cameras within 5 robust sigmas, for 6 parameters): how consistent the geotag heights are
    relative to each other; and the rise's standard error from that scatter and the cameras' layout
    (`rise_sigma_m`, inf when the layout does not determine a quadratic). Needs 7 or more cameras: with fewer,
    {'n': N} only."""
    xy = np.asarray(xy_m, float).reshape(-1, 2)
    dz = np.asarray(dz_m, float).ravel()
    ok = np.all(np.isfinite(xy), axis=1) & np.isfinite(dz)
    xy, dz = xy[ok], dz[ok]
    n = len(dz)
    if n < 7:
        return {'n': n}
    e, nn = (xy - xy.mean(axis=0)).T
    r_max = float(np.max(np.hypot(e, nn)))
    radius = r_max if radius_m is None else float(radius_m)
    A = np.column_stack([np.ones(n), e, nn, e * e, e * nn, nn * nn])
    w = np.ones(n)
    for _ in range(5):
        coef = np.linalg.lstsq(A * w[:, None], dz * w, rcond=None)[0]
        w = 1.0 / np.sqrt(np.maximum(np.abs(dz - A @ coef), 0.005))
    # Least squares over the cameras within 5 robust sigmas of that fit (its median absolute residual, low by the
    # residuals it fits exactly): the surface and the scatter about it.
    res = dz - A @ coef
    keep = np.abs(res) <= 5.0 * max(1.4826 * float(np.median(np.abs(res))) * np.sqrt(n / (n - 6.0)), 1e-3)
    if keep.sum() >= 7:
        A, dz = A[keep], dz[keep]
        coef = np.linalg.lstsq(A, dz, rcond=None)[0]
    res = dz - A @ coef
    H = np.array([[2 * coef[3], coef[4]], [coef[4], 2 * coef[5]]])
    k = np.linalg.eigvalsh(H)
    scatter = float(np.sqrt(np.sum(res ** 2) / max(len(dz) - 6.0, 1.0)))
    # The rise's standard error from the cameras' layout: large where they do not span the block in both
    # directions (one or two lines), where the quadratic is not determined.
    g = np.array([0.0, 0.0, 0.0, 0.5, 0.0, 0.5]) * radius ** 2
    s = np.linalg.svd(A, compute_uv=False)
    if s[-1] <= 1e-9 * s[0]:
        rise_sigma = float('inf')
    else:
        rise_sigma = float(scatter * np.sqrt(g @ np.linalg.solve(A.T @ A, g)))
    return {'n': n, 'radius_m': radius, 'rise_m': float(0.5 * k.mean() * radius ** 2),
            'curvatures_per_km': [float(v) * 1e3 for v in k], 'scatter_m': float(scatter),
            'rise_sigma_m': rise_sigma}
