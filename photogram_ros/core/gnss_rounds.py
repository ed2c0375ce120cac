"""The GNSS rounds of the block's adjustments: the fix gate in flight, the flight's GNSS noise (a variance-component
estimate, fixes beyond it rejected), the levelling of a block whose heights wander, and the full adjustments with the
GNSS bias (and the tilt of the fixes' heights) as unknowns until the bias settles, with the "auto" tilt's F-test.

`GnssRounds` estimates the datum (core/gnss_datum.py) through the block's adjustments (core/at_problem.py) and keeps
what its last rounds found: `noise` (the noise estimate), `settle` (how the bias rounds ended) and `tilt_test`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from photogram_ros.core.at_geometry import reprojection_errors_px
from photogram_ros.core.at_problem import ProblemOptions, StepReport, adjust
from photogram_ros.core.at_store import Keyframe
from photogram_ros.core.at_two_view import TwoViewOptions
from photogram_ros.core.gnss_datum import PRECISE_FIX_RATIO
from photogram_ros.core.part_options import check, declared
from photogram_ros.core.rotations import R_from_rotvec, make_T
from photogram_ros.params import param

# How far the mean optical axis of a nadir flight may lie from the vertical (1 sigma, degrees): a gimbal
# held at nadir, or a camera fixed to look down, over a whole flight.
NADIR_PRIOR_DEG = 2.0
# The "auto" tilt's F-test level. With 5 GCPs (2 degrees of freedom left) its quantile is 9.0 (19.0 at 95 %); the
# simulator's sample flight gives F 1.3 at most over six flights whose fixes lean 2 mm/m or less, and 11.0 for one
# whose fixes lean 10 mm/m (bench/gnss_tilt.py).
TILT_TEST_LEVEL = 0.90
# The fix gate judges a new fix about the block's offset from its last this many fixes at least as precise (a block
# drifts along a flight), when at least GATE_OFFSET_MIN of them are there.
GATE_OFFSET_FIXES = 10
GATE_OFFSET_MIN = 3


def clipped_sigma(x: np.ndarray, k: float = 3.5, rounds: int = 5) -> float:
    """Standard deviation (about zero) of the residuals `x` without those beyond `k` of it, from the median
    absolute deviation on: glitches drop out, the spread of an error that wanders (a bimodal or flat
    distribution, whose median absolute deviation is far below its spread) stays in."""
    x = np.asarray(x, float).ravel()
    sig = 1.4826 * float(np.median(np.abs(x)))
    for _ in range(rounds):
        keep = np.abs(x) <= k * max(sig, 1e-9)
        new = float(np.sqrt(np.mean(x[keep] ** 2))) if keep.any() else sig
        if abs(new - sig) <= 1e-3 * max(sig, 1e-9):
            break
        sig = new
    return sig


def flight_plane_sigma(fixes_enu: np.ndarray) -> float:
    """The fixes' vertical noise about the flight's plane (m): the robust scatter (`clipped_sigma`) of their
    heights about the plane fitted to them over their horizontal positions (least absolute deviations),
    corrected for its 3 parameters. A mapping flight holds its altitude, so a level flight's barometric heights
    (a consumer geotag: metres off absolutely, centimetres from photo to photo) give centimetres here, which
    their stated sigma does not say; their offset and tilt are the datum's. A flight over relief it follows,
    or heights that wander, give more; a wander shaped like a bowl over the block does not show here."""
    X = np.asarray(fixes_enu, float).reshape(-1, 3)
    A = np.column_stack([np.ones(len(X)), X[:, 0] - X[:, 0].mean(), X[:, 1] - X[:, 1].mean()])
    w = np.ones(len(X))
    for _ in range(4):
        coef = np.linalg.lstsq(A * w[:, None], X[:, 2] * w, rcond=None)[0]
        w = 1.0 / np.sqrt(np.maximum(np.abs(X[:, 2] - A @ coef), 0.01))
    r = X[:, 2] - A @ coef
    return float(np.sqrt(len(X) / max(len(X) - 3.0, 1.0)) * clipped_sigma(r - np.median(r)))

@dataclass(frozen=True)
class GnssRoundsOptions:
    """The options of the GNSS rounds (`GnssRounds`): the fix gate, the noise estimate, levelling, the bias and
    tilt rounds."""
    max_reprojection_px: float = declared(ProblemOptions, 'max_reprojection_px')
    loss: str = declared(ProblemOptions, 'loss')
    loss_scale_px: float = declared(ProblemOptions, 'loss_scale_px')
    window_iterations: int = param(15, 'solver iterations of a window update', min=1, max=1000)
    full_iterations: int = declared(ProblemOptions, 'full_iterations')
    assume_nadir: bool = declared(TwoViewOptions, 'assume_nadir')
    gnss_tilt: str = param('never', 'with the GNSS bias, a tilt of the fixes\' heights across the block (2 more '
                                    'unknowns), where the GCPs used in height spread over it in both directions '
                                    '(gnss_tilt_min_spread): fixes that lean by several mm/m (a strip flown on a '
                                    'float fix, a wandering fix) would otherwise turn the block. "always"; "auto": '
                                    'the final adjustment keeps it when it lowers the GCPs\' height residuals '
                                    'significantly (an F-test at 90 %, 4 GCPs or more); "never" (the default: with 5 '
                                    'GCPs, a lean of 2 mm/m or less is estimated no better than it is left, '
                                    'bench/gnss_tilt.py)')
    gnss_tilt_min_spread: float = param(0.3, 'the tilt is estimated when, along every horizontal direction, the GCPs '
                                             'used in height spread (RMS about their centre) by at least this '
                                             'fraction of the fixes\' spread: GCPs on one line never', min=0.0,
                                        max=10.0)
    bias_iterations: int = param(10, 'full adjustments with the GNSS bias as unknowns, at most (the outliers each '
                                     'removes can move the bias of the next; settled when it moves under 1 mm)',
                                 min=0, max=1000)
    gnss_noise_min_keyframes: int = param(8, 'oriented keyframes with a fix the GNSS noise estimate needs',
                                          min=4, max=100000)
    gnss_tighten: bool = param(False, 'the GNSS noise estimate may also weight the fixes tighter than they state '
                                      '(a consumer geotag states metres): horizontally by their residuals about '
                                      'the block, vertically by their heights\' scatter about the flight\'s plane')
    gnss_tighten_floor_m: float = param(0.05, 'a tightened GNSS sigma is at least this, m', min=0.001, max=100.0)
    gnss_gate_m: float = param(1.0, 'a keyframe oriented from the block\'s tie points whose fix lies further than '
                                    'this (and 2 x gnss_outlier_sigma of its sigma) from it keeps its fix out, m',
                               min=0.0, max=1e6)
    gnss_outlier_sigma: float = param(5.0, 'a fix whose residual exceeds this many estimated sigmas (and 3 stated '
                                           'sigmas) is not used', min=2.0, max=1000.0)

    def __post_init__(self):
        check(self)


class GnssRounds:
    """The GNSS rounds of `block` (core/at_block.py) on its datum `datum` through its adjustments `adjustment`, for
    the options `opt`."""

    def __init__(self, block, datum, adjustment, opt: GnssRoundsOptions):
        self.block, self.datum, self.adjustment, self.opt = block, datum, adjustment, opt
        # The last noise estimate (`estimate_noise`): stated and estimated sigmas, scale factors, rejected fixes.
        self.noise: dict = {}
        # How the last bias estimate ended: {'settled': its last step under 1 mm, 'rounds': adjustments, 'last_step_m'}.
        self.settle: dict = {}
        # The "auto" tilt's test at the last final adjustment: {'gcps', 'rss_bias_m2', 'rss_tilt_m2', 'f', 'f_crit',
        # 'kept'} (empty when not made).
        self.tilt_test: dict = {}

    def noise_estimate(self) -> dict:
        """The last GNSS noise estimate (`estimate_noise`), a copy; empty when none was made."""
        return dict(self.noise)

    def gate_fix(self, kf: Keyframe) -> bool:
        """A new keyframe oriented from the block's tie points, whose fix lies far beyond its sigma
        (and `gnss_gate_m`) from where the block puts it, keeps its fix out of the adjustment when the
        photos contradict the fix (a glitched geotag: weighted as stated it would drag the block after it).
        Far from the resection alone is not enough: a pose the window's tie points hold loosely (the first
        photo of a line) can be metres off where its fix is right, and a keyframe without its fix carries
        that error on to the next one, each registered from the last, so the block would leave its GNSS
        for good. A far fix is therefore tried in the window adjustment (`_fix_trial`, nothing written):
        it stays in when the adjusted camera comes within the gate of it without its tie points' errors
        growing. Far is judged about where the block's other fixes at least as precise as this one put the block
        (`_precise_offset`): a block that drifted off its GNSS as a whole (a third of its fixes FLOAT and a metre
        off) says nothing about one fix, and an RTK-fixed fix is never refused where a FLOAT one would be kept.
        True when rejected."""
        if kf.fix_enu is None or kf.map_T_cam is None:
            return False
        others = [k for k in self.block.registered if k != kf.kid and k not in self.datum.rejected]
        offset = self._precise_offset(kf, others[-GATE_OFFSET_FIXES:], self.datum.residuals)
        if not self._fix_far(kf, kf.map_T_cam, offset):
            return False
        if self._fix_trial(kf):
            return False
        self.datum.rejected.add(kf.kid)
        return True

    def _fix_far(self, kf: Keyframe, map_T_cam: np.ndarray, about_m=None) -> bool:
        """The antenna of a camera at `map_T_cam` lies further from kf's fix (plus `about_m`, ENU m, when
        given) than the gate: on some axis beyond 2 x gnss_outlier_sigma of the fix's sigma (scaled by
        the estimated noise) and gnss_gate_m."""
        d = self.datum.antenna_residual(kf, map_T_cam) - (0.0 if about_m is None else np.asarray(about_m, float))
        sig = np.sqrt(np.diag(self.datum.fix_cov_used(kf)))
        return bool((np.abs(d) > np.maximum(self.opt.gnss_outlier_sigma * 2.0 * sig, self.opt.gnss_gate_m)).any())

    def _precise_offset(self, kf: Keyframe, kids: list[int], residuals, min_count: int = GATE_OFFSET_MIN
                        ) -> np.ndarray | None:
        """Where the block sits off its GNSS as the fixes of keyframes `kids` at least as precise as kf's say (their
        stated sigma within PRECISE_FIX_RATIO of kf's): their median residual (`residuals(kids)` -> {kid: ENU m});
        None when fewer than `min_count` of them have a fix."""
        own = float(np.sqrt(np.trace(np.asarray(kf.fix_cov, float).reshape(3, 3))))
        kids = [k for k in kids if self.block.kfs[k].fix_enu is not None and float(np.sqrt(np.trace(
            np.asarray(self.block.kfs[k].fix_cov, float).reshape(3, 3)))) <= PRECISE_FIX_RATIO * own]
        r = list(residuals(kids).values())
        return np.median(r, axis=0) if r and len(r) >= min_count else None

    def _fix_trial(self, kf: Keyframe) -> bool:
        """The window adjustment of keyframe kf with its fix in, solved without writing anything back: True
        when the photos agree with the fix: kf's adjusted antenna comes within the gate (`_fix_far`) of its
        fix as the window's other fixes at least as precise lie from theirs (`_precise_offset`: a block that is not
        yet self-calibrated can sit off its GNSS by a common amount, which says nothing about one geotag), and
        the median reprojection error of kf's observations stays within max(2 x, + 1 px) of the
        resection's and within max_reprojection_px."""
        sel = self.adjustment.window_selection()
        b = self.adjustment.build(sel.free_kfs, sel.fixed_kfs, sel.track_ids)
        if b.prob is None or kf.kid not in b.kids:
            return False
        prob = b.prob
        j = b.kids.index(kf.kid)
        mine = np.asarray(prob.obs_cam) == j
        if not mine.any():
            return False
        res = adjust(prob, self.opt.loss, self.opt.loss_scale_px, self.opt.window_iterations)
        if res.status == 'failed':
            return False
        T = np.asarray(res.map_T_cams)
        at = {b.kids[i]: T[i] for i in b.gnss_cams if i != j}
        about = self._precise_offset(kf, list(at), lambda kids: {
            k: self.datum.antenna_residual(self.block.kfs[k], at[k]) for k in kids}, min_count=1)
        before = reprojection_errors_px(self.block.camera, np.asarray(prob.map_T_cams)[prob.obs_cam[mine]],
                                         np.asarray(prob.points_map)[prob.obs_pt[mine]], prob.obs_uv[mine])
        after = reprojection_errors_px(self.block.camera, T[prob.obs_cam[mine]],
                                        np.asarray(res.points_map)[prob.obs_pt[mine]], prob.obs_uv[mine])
        med0, med1 = float(np.nanmedian(before)), float(np.nanmedian(after))
        return (not self._fix_far(kf, T[j], about) and np.isfinite(med1)
                and med1 <= min(max(2.0 * med0, med0 + 1.0), self.opt.max_reprojection_px))

    def _flight_plane_sigma(self, kids: list[int]) -> float:
        """`flight_plane_sigma` of the fixes of keyframes `kids`."""
        return flight_plane_sigma(np.array([self.block.kfs[k].fix_enu for k in kids]))

    def level_block(self, kids: list[int]) -> dict | None:
        """The block's tilt, from the fixes' heights and from the cameras looking down, each as good as
        it is: the slope of the fixes' heights across the block (what the GNSS says of the tilt) has the
        uncertainty of their vertical scatter about a block that looks down (`clipped_sigma`, at least 2 cm) over
        their horizontal spread, as many independent heights as their correlation from photo to photo leaves; the mean optical axis of a nadir flight is vertical
        within `NADIR_PRIOR_DEG`. Their weighted mean is the tilt kept: the block is turned to it about
        its cameras' centre and the rest of the fixes' slope taken out of their heights (`gnss_slope`).

        Only with `assume_nadir`, a block whose mean axis looks down, and fewer than 3 GCPs (which fix the
        tilt themselves). Returns {'gnss_tilt_deg', 'kept_tilt_deg', 'turned_deg',
        'scatter_v_m'} when the block was turned by more than 0.05 degrees, else None."""
        if not self.opt.assume_nadir or self.block.n_gcps() >= 3 or len(kids) < self.opt.gnss_noise_min_keyframes:
            return None
        axes = np.array([self.block.kfs[k].map_T_cam[:3, 2] for k in self.block.registered])
        m = axes.mean(axis=0)
        m = m / np.linalg.norm(m)
        if m[2] > -0.1:
            return None     # cameras that look at or above the horizon: not a block that looks down
        if not self.datum.slope.any():
            fixes = np.array([self.block.kfs[k].fix_enu[:2] - self.datum.bias_enu[:2] for k in kids])
            self.datum.slope_centre = fixes.mean(axis=0)
        b = m[:2] / -m[2]                       # the block's slope (dz/dE, dz/dN) as its cameras look
        dz, x = self.datum.raw_height_residuals(kids)
        g = b - self.datum.slope                 # the slope the fixes' own heights give the block
        # The fixes' heights about a block that looks down: their residuals with the block's slope out.
        lev = dz - x @ b
        n = len(lev)
        scatter = clipped_sigma(lev - np.median(lev)) * np.sqrt(n / max(n - 3.0, 1.0))
        sig_v = max(scatter, 0.02)
        xc = x - x.mean(axis=0)
        # Heights that wander are correlated from photo to photo: about the slope they give the block, their
        # lag-one correlation in flight order makes fewer independent heights, (1 - rho) / (1 + rho) of them.
        fit = dz - x @ self.datum.slope
        fit = (fit - fit.mean())[np.argsort(kids)]
        rho = float(np.clip(np.sum(fit[1:] * fit[:-1]) / max(float(np.sum(fit ** 2)), 1e-12), 0.0, 0.95))
        info_g = xc.T @ xc / sig_v ** 2 * (1.0 - rho) / (1.0 + rho)
        info_p = np.eye(2) / np.tan(np.radians(NADIR_PRIOR_DEG)) ** 2
        p = np.linalg.solve(info_g + info_p, info_g @ g)
        m_new = np.append(p, -1.0) / np.linalg.norm(np.append(p, -1.0))
        axis = np.cross(m, m_new)
        turn = float(np.arctan2(np.linalg.norm(axis), float(m @ m_new)))
        out = {'gnss_tilt_deg': float(np.degrees(np.arctan(np.linalg.norm(g)))),
               'kept_tilt_deg': float(np.degrees(np.arctan(np.linalg.norm(p)))),
               'turned_deg': float(np.degrees(turn)), 'scatter_v_m': float(scatter), 'correlation': rho}
        if np.degrees(turn) < 0.05:
            return None
        R = R_from_rotvec(axis / np.linalg.norm(axis) * turn)
        c0 = np.mean([self.block.kfs[k].map_T_cam[:3, 3] for k in self.block.registered], axis=0)
        for k in self.block.registered:
            T = np.array(self.block.kfs[k].map_T_cam, float)
            self.block.kfs[k].map_T_cam = make_T(R @ T[:3, :3], R @ (T[:3, 3] - c0) + c0)
        ids, P = self.block.points.arrays()
        if len(ids):
            self.block.points.set_many(ids, (np.asarray(P) - c0) @ R.T + c0)
        self.datum.slope = p - g
        return out

    def noise_factors_hv(self, residuals: dict) -> np.ndarray:
        """How poor the fixes are against what they state: factors (horizontal, vertical) on their stated sigmas,
        from their `residuals` ({kid: ENU m}, GnssDatum.residuals) about the block as it stands. Each fix's residual
        over its own stated sigma (fixes of mixed quality, RTK fixed beside float photos, each count by what they
        state), robust (`clipped_sigma` about the median), corrected for the 7 datum parameters the fixes also
        carry; the vertical one against the fixes' own heights, their trend across the block included
        (`raw_height_residuals`). Nothing is changed."""
        kids = list(residuals)
        R = np.array([residuals[k] for k in kids]).reshape(-1, 3)
        s_hv = self.datum.stated_sigmas_hv(kids)
        n = len(kids)
        redundancy = np.sqrt(3.0 * n / max(3.0 * n - 7.0, 1.0))
        h = (R[:, :2] - np.median(R[:, :2], axis=0)) / s_hv[:, :1]
        dz, _ = self.datum.raw_height_residuals(kids)
        v = (dz - np.median(dz)) / s_hv[:, 1]
        return redundancy * np.array([clipped_sigma(h.ravel()), clipped_sigma(v)])

    def estimate_noise(self, iterations: int | None = None, refine_intrinsics: tuple = ()) -> dict:
        """The flight's GNSS noise from the residuals of the fixes (a variance-component estimate,
        horizontal and vertical apart, robust: median absolute deviations about the median, corrected
        for the 7 datum parameters the fixes also carry; the vertical one against the fixes' own heights,
        their trend across the block included). Where it exceeds the stated sigmas by half again, the
        fixes are weighted by it and the block adjusted again, and the block's tilt is taken from the
        fixes' heights and from its cameras looking down, each by its weight (`level_block`), until both
        settle; then a fix beyond `gnss_outlier_sigma` estimated sigmas (and 3 stated sigmas) is not used
        (at most a fifth of them) and the block adjusted once more. Returns (and keeps in `gnss_noise`) the
        stated and estimated sigmas (m), the scale factors, the names of the rejected fixes and, when the
        block was levelled, `level` (the tilt the fixes' heights gave it and the one kept, degrees).

        refine_intrinsics: the intrinsics the block's adjustments self-calibrate (e.g. ('f', 'k1', 'k2')),
        refined again in every adjustment here: intrinsics fitted under the fixes' stated weights absorb
        what the poorer fixes pull (geotags late along the track move the focal length, and with it the
        ground's depth), and held afterwards they would keep that error."""
        iters = iterations or self.opt.full_iterations
        refine = tuple(refine_intrinsics)
        out = {}
        level = None
        for rnd in range(6):
            # Every fix, those kept out in flight too (a robust estimate: a few glitches do not move it, and
            # a gate that kept out the far end of a wandering height would hide how poor the heights are).
            r = self.datum.residuals()
            if len(r) < self.opt.gnss_noise_min_keyframes or not self.block.georeferenced:
                if self.datum.rejected:
                    self.noise = {**self.noise,
                                       'rejected': [self.block.kfs[k].name for k in sorted(self.datum.rejected)]}
                return self.noise
            kids = list(r)
            # Reported in metres on the fixes' RMS stated sigma (`stated`; the estimate is the factor times it).
            stated = np.sqrt(np.mean(self.datum.stated_sigmas_hv(kids) ** 2, axis=0))
            n = len(kids)
            factor = self.noise_factors_hv(r)
            est = factor * stated
            used = self.datum.sigma_scale_hv
            want = np.where(factor > 1.5, factor, 1.0)
            want = np.maximum(want, 1.0)
            if self.opt.gnss_tighten and n >= self.opt.gnss_noise_min_keyframes:
                # Fixes better than they state (a consumer geotag states metres): horizontally as the block's
                # residuals say (a block cannot bend to follow its fixes sideways, its 7 datum parameters
                # taken into account above); vertically as the heights' scatter about the flight's plane says
                # (a block bends to its heights: its residuals would say what its bending left). Never looser
                # than stated.
                better = np.maximum([est[0], self._flight_plane_sigma(kids)], self.opt.gnss_tighten_floor_m)
                tight = better < stated / 1.5
                want[tight] = np.minimum(better[tight] / stated[tight], 1.0)
            out = {'stated_h_m': float(stated[0]), 'stated_v_m': float(stated[1]), 'estimated_h_m': float(est[0]),
                   'estimated_v_m': float(est[1]), 'scale_h': float(want[0]), 'scale_v': float(want[1]),
                   'used_h_m': float(stated[0] * want[0]), 'used_v_m': float(stated[1] * want[1]), 'n': n}
            if level is not None:
                out['level'] = level
            settled = bool(np.all(np.abs(want - used) <= 0.1 * used))
            turned = self.level_block(kids) if rnd < 5 else None
            if turned is not None:
                level = {**turned, 'turned_deg': turned['turned_deg'] + (level or {}).get('turned_deg', 0.0)}
                out['level'] = level
            if settled and turned is None:
                break
            self.datum.sigma_scale_hv = want
            self.adjustment.solve(list(self.block.registered), [], list(self.block.points), iters, refine)
        # Outliers: far beyond the noise the flight shows, and beyond what the fixes state. Fixes kept out in
        # flight (`gate_fix`, IncrementalAT `_try_georeference`) are judged again against the adjusted block: a block that
        # drifted in flight may have put good fixes out.
        if out:
            kept = self.datum.residuals([k for k in self.block.registered if k not in self.datum.rejected])
            med = np.median(np.array(list(kept.values())), axis=0)
            r = self.datum.residuals()
            kids = list(r)
            R = np.array([r[k] for k in kids]) - med
            # Each fix against its own stated sigma: beyond gnss_outlier_sigma of it scaled by the flight's noise
            # (at least half the stated), and beyond 3 stated sigmas.
            s_hv = self.datum.stated_sigmas_hv(kids)
            f_hv = np.maximum(np.array([out['estimated_h_m'] / out['stated_h_m'],
                                        out['estimated_v_m'] / out['stated_v_m']]), 0.5)
            h = np.linalg.norm(R[:, :2], axis=1) / np.sqrt(2)
            floor = np.maximum(h / s_hv[:, 0], np.abs(R[:, 2]) / s_hv[:, 1])
            dev = np.maximum(h / (s_hv[:, 0] * f_hv[0]), np.abs(R[:, 2]) / (s_hv[:, 1] * f_hv[1]))
            bad = np.flatnonzero((dev > self.opt.gnss_outlier_sigma) & (floor > 3.0))
            bad = bad[np.argsort(-dev[bad])][:len(kids) // 5]
            rejected = {kids[i] for i in bad}
            if rejected != self.datum.rejected:
                self.datum.rejected = rejected
                self.adjustment.solve(list(self.block.registered), [], list(self.block.points), iters, refine)
                # The fixes back in (or out) move the heights' slope: levelled again.
                for _ in range(4):
                    turned = self.level_block(list(self.datum.residuals()))
                    if turned is None:
                        break
                    level = {**turned, 'turned_deg': turned['turned_deg'] + (level or {}).get('turned_deg', 0.0)}
                    self.adjustment.solve(list(self.block.registered), [], list(self.block.points), iters, refine)
            if level is not None:
                axes = np.mean([self.block.kfs[k].map_T_cam[:3, 2] for k in self.block.registered], axis=0)
                level['kept_tilt_deg'] = float(np.degrees(np.arccos(np.clip(-axes[2] / np.linalg.norm(axes), -1, 1))))
                out['level'] = level
            out['rejected'] = [self.block.kfs[k].name for k in sorted(self.datum.rejected)]
        self.noise = out
        return out

    def bias_rounds(self, iterations: int | None, tilt: bool, rep: StepReport) -> tuple[StepReport, dict]:
        """Full adjustments with the GNSS bias (and the tilt) as unknowns until the bias settles: (the last
        solve's report, `rep` when none ran; {'settled', 'rounds', 'last_step_m'}, empty when no camera has a
        fix)."""
        # The bias is 3 unknowns of the adjustment beside the poses and points (the intrinsics held): one solve
        # finds it; each solve then removes the observations it leaves as outliers, which can move it again.
        settled, rounds, step = False, 0, np.zeros(3)
        if not tilt:
            self.datum.tilt_estimated = False
        for i in range(self.opt.bias_iterations if self.datum.residuals() else 0):
            before = self.datum.bias_enu.copy()
            rep = self.adjustment.solve(list(self.block.registered), [], list(self.block.points), iterations or self.opt.full_iterations,
                              gnss_bias=True, gnss_tilt=tilt)
            step = self.datum.bias_enu - before
            rounds = i + 1
            if rep.status == 'failed':
                break
            if i and np.linalg.norm(step) < 0.001:
                settled = True
                break
        return rep, ({'settled': settled, 'rounds': rounds, 'last_step_m': float(np.linalg.norm(step))}
                     if rounds else {})

    def tilt_tested(self, iterations: int | None, rep: StepReport) -> tuple[StepReport, dict]:
        """gnss_tilt "auto": the bias alone, then with the tilt; the tilt is kept when it lowers the GCPs' height
        residuals (intersected from the adjusted cameras) by more than chance: F = ((RSS_bias - RSS_tilt) / 2) /
        (RSS_tilt / (n - 3)) above its TILT_TEST_LEVEL quantile with (2, n - 3) degrees of freedom, n GCPs used in
        height (at least 4). Otherwise the bias is adjusted alone again from where the tilt left the block."""
        from scipy.stats import f as f_dist
        rep, settle = self.bias_rounds(iterations, False, rep)
        rss0, n = self._gcp_height_rss()
        if n < 4:
            self.tilt_test = {}
            return rep, settle
        slope, centre = self.datum.slope.copy(), self.datum.slope_centre.copy()
        rep_t, settle_t = self.bias_rounds(iterations, True, rep)
        rss1, _ = self._gcp_height_rss()
        f = (rss0 - rss1) / 2.0 / max(rss1 / (n - 3), 1e-12)
        f_crit = float(f_dist.ppf(TILT_TEST_LEVEL, 2, n - 3))
        kept = bool(rep_t.status != 'failed' and f > f_crit)
        self.tilt_test = {'gcps': n, 'rss_bias_m2': float(rss0), 'rss_tilt_m2': float(rss1), 'f': float(f),
                               'f_crit': f_crit, 'kept': kept}
        if kept:
            return rep_t, settle_t
        self.datum.slope, self.datum.slope_centre = slope, centre
        return self.bias_rounds(iterations, False, rep)

    def _gcp_height_rss(self) -> tuple[float, int]:
        """(sum of squared height residuals, m^2, count) of the GCPs used in height, each intersected from the
        adjusted cameras minus its survey."""
        r = []
        for n in self.block.gcps_in_height():
            got = self.block.intersect_target(n)
            if got is not None:
                r.append(float(got[0][2] - self.block.control[n].map_xyz[2]))
        return float(np.sum(np.square(r))), len(r)

    def tilt_observable(self) -> bool:
        """gnss_tilt is not "never" and the GCPs used in height spread over the block in every direction: along
        any horizontal direction u, their RMS about their centre is at least gnss_tilt_min_spread times the
        fixes' (the smallest generalised eigenvalue of the two 2x2 scatter matrices); GCPs on one line never."""
        if self.opt.gnss_tilt == 'never':
            return False
        names = self.block.gcps_in_height()
        fixes = np.array([self.block.kfs[k].fix_enu[:2] for k in self.block.registered
                          if self.block.kfs[k].fix_enu is not None and k not in self.datum.rejected]).reshape(-1, 2)
        if len(names) < 3 or len(fixes) < 3:
            return False
        g = np.array([self.block.control[n].map_xyz[:2] for n in names], float)
        cg, cf = np.cov((g - g.mean(axis=0)).T, bias=True), np.cov((fixes - fixes.mean(axis=0)).T, bias=True)
        if np.linalg.eigvalsh(cf)[0] < 1.0:
            return False     # the fixes on one line: no lean across it to find
        return bool(scipy.linalg.eigh(cg, cf, eigvals_only=True)[0] >= self.opt.gnss_tilt_min_spread ** 2)

