"""The block's adjustments: the one builder of its bundle problems, the solve that writes the result back, the
covariance of a window's camera centres, the sliding window, and the stepwise self-calibration's trials.

`BlockAdjustment` builds every bundle problem of the block (core/at_block.py) with its GNSS datum
(core/gnss_datum.py): keyframes adjusted and held, their active observations, the fixes as priors once
georeferenced, the GCPs as point priors; it keeps the log of its solves and the last self-calibration selection.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from photogram_ros.core.at_geometry import reprojection_errors_px
from photogram_ros.core.bundle import BundleOptions, BundleProblem, bundle_adjust
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.part_options import check
from photogram_ros.core.self_calibration import (MIN_GAIN_FRACTION, MIN_GAIN_PX, Selection, Trial, height_bowl,
                                                 select_stepwise)
from photogram_ros.core.window import neighbour_keyframes, select_window
from photogram_ros.params import param

# Intrinsics a stepwise self-calibration refines whenever they are candidates (`select_self_calibration`).
SELF_CALIBRATION_BASE = ('f', 'cx', 'cy')
# A self-calibration trial stops once a step lowers its cost by less than this fraction (its reprojection RMS by
# about half of it, 0.005 %), far inside the 2 % a candidate must gain; the adjustments keep 1e-6. On the
# simulator's sample flight (76 keyframes) the trials take 44 s with it, 80 s at 1e-6, and choose alike.
TRIAL_FUNCTION_TOLERANCE = 1e-4
# A window update stops once a step lowers its cost by less than this fraction. The window starts from the last
# estimate, one new keyframe off it: on toledo's photos its cost is within 0.05 % of where 15 iterations take it
# after 3-4 steps, and the tail (robust loss, a few 1e-5 a step) moves the poses by a small fraction of their
# sigma while it costs three quarters of the update (bench/adjustment_pace.py). The full adjustments keep 1e-6.
WINDOW_FUNCTION_TOLERANCE = 1e-4


@dataclass
class _Problem:
    """BlockAdjustment.problem() with the map back to the block: observation o is point `slot[o]`
    (track `tracks[slot[o]]`) seen by keyframe `kid[o]` (camera kids.index(kid[o])) at its index `oi[o]`."""
    prob: BundleProblem | None
    kids: list[int]
    tracks: list[int]
    slot: np.ndarray
    kid: np.ndarray
    oi: np.ndarray
    fixed_mask: np.ndarray
    gnss_cams: list[int]         # cameras (indices into kids) with a GNSS prior


@dataclass
class StepReport:
    kid: int
    registered: bool
    status: str
    solve_s: float = 0.0
    cost: float = float('nan')
    reprojection_rms_px: float = float('nan')
    gnss_rms_m: float = float('nan')
    window_size: int = 0
    n_points: int = 0
    joined: int = 0                 # keyframes of a segment that joined the block with this step
    waiting_oriented: int = 0       # earlier keyframes that were waiting for a pose, oriented with this step
    block_adjusted: bool = False    # a full adjustment of the pass (growth_ratio) moved every keyframe and may


def _intrinsics_by_name(camera: PinholeCamera) -> dict:
    """The camera's intrinsics by their self-calibration names (f is fx)."""
    return {'f': camera.fx, 'cx': camera.cx, 'cy': camera.cy, **dict(zip(('k1', 'k2', 'p1', 'p2', 'k3'), camera.dist))}


def _with_intrinsics_of(camera: PinholeCamera, given: PinholeCamera, names) -> PinholeCamera:
    """`camera` with the intrinsics `names` ('f', 'cx', 'cy', 'k1', 'k2', 'p1', 'p2', 'k3') taken from `given`."""
    kw = {}
    if 'f' in names:
        kw.update(fx=given.fx, fy=given.fy)
    kw.update({n: getattr(given, n) for n in ('cx', 'cy') if n in names})
    dist = [given.dist[i] if n in names else camera.dist[i] for i, n in enumerate(('k1', 'k2', 'p1', 'p2', 'k3'))]
    return replace(camera, dist=tuple(dist), **kw)


def adjust(prob, loss: str, scale_px: float, iterations: int, refine: tuple = (), gnss_bias: bool = False,
            gnss_tilt: bool = False, function_tolerance: float = 1e-6):
    return bundle_adjust(prob, BundleOptions(loss=loss, loss_scale_px=scale_px, max_iterations=iterations,
                                             refine_intrinsics=tuple(refine), estimate_gnss_bias=gnss_bias,
                                             estimate_gnss_tilt=gnss_tilt, function_tolerance=function_tolerance))

@dataclass(frozen=True)
class ProblemOptions:
    """The options of the block's bundle problems and their solve (`BlockAdjustment`): the window, the robust
    losses, the outlier gate, the iterations of a full adjustment, the stepwise self-calibration's gains."""
    window_size: int = param(10, 'keyframes adjusted per update (newest); older ones sharing points are held fixed',
                             min=2, max=200)
    max_fixed_keyframes: int = param(30, 'at most this many fixed keyframes enter a window update', min=0, max=1000)
    max_reprojection_px: float = param(2.5, 'observations with a larger error after adjustment are dropped, px',
                                       min=0.3, max=100.0)
    loss: str = param('huber', 'robust loss on reprojection errors', choices=('huber', 'cauchy', 'linear'))
    loss_scale_px: float = param(1.0, 'robust loss scale, pixels', min=0.05, max=100.0)
    mtp_loss_scale_px: float = param(3.0, 'robust loss scale of the manual tie points (marked by hand to about '
                                          '1 px; kept through outlier removal), pixels', min=0.05, max=1000.0)
    gcp_loss_scale_px: float = param(3.0, 'robust loss scale of the GCPs\' observations (markers found to a '
                                          'fraction of a pixel or marked by hand, vetted against the block before '
                                          'use), pixels: at the tie points\' scale a few pixels of camera-model '
                                          'error would turn the GCPs\' pull down', min=0.05, max=1000.0)
    full_iterations: int = param(50, 'solver iterations of a full adjustment (each round)', min=1, max=1000)
    self_calibration_min_gain: float = param(MIN_GAIN_FRACTION, 'stepwise self-calibration: a candidate intrinsic '
                                             'is kept when it lowers the reprojection RMS by at least this fraction '
                                             'of it (and self_calibration_min_gain_px)', min=0.0, max=1.0)
    self_calibration_min_gain_px: float = param(MIN_GAIN_PX, 'stepwise self-calibration: ... and by at least this, '
                                                'px', min=0.0, max=100.0)

    def __post_init__(self):
        check(self)


class BlockAdjustment:
    """The bundle problems of `block` with its GNSS datum `datum`, for the options `opt`."""

    def __init__(self, block, datum, opt: ProblemOptions):
        self.block, self.datum, self.opt = block, datum, opt
        # Every adjustment of the block's keyframes (`solve`): its iterations, status and seconds.
        self.solves: list[dict] = []
        # The last stepwise self-calibration's selection (core/self_calibration.py), None when none was made.
        self.self_calibration: Selection | None = None

    def solve_log(self) -> list[dict]:
        """Every adjustment so far: {'iterations', 'status', 's'} (copies), oldest first."""
        return [dict(s) for s in self.solves]

    def problem(self, free_kids: list[int], fixed_kids: list[int], tracks) -> BundleProblem | None:
        """The bundle problem of the adjuster's state that every adjustment solves.

        Keyframes `free_kids` are adjusted and `fixed_kids` held (cameras in that order); the points
        are those of `tracks` that have one (in that order), observed by every active observation
        in these keyframes. Once georeferenced, the free keyframes' fixes are GNSS priors (moved by
        the estimated bias; the antenna at the lever arm, or at the record's antenna offset) and the
        GCPs among the tracks point priors. Without a datum and nothing held, the first two
        keyframes are held (the gauge). None when there is no observation."""
        return self.build(free_kids, fixed_kids, tracks).prob

    def build(self, free, fixed, tracks, gcp_priors: bool = True, hold_gauge: bool = True) -> _Problem:
        """problem() with what maps its observations back to the keyframes; `prob` is None when
        there is no observation."""
        kids = list(free) + list(fixed)
        col = {k: j for j, k in enumerate(kids)}
        tracks = np.asarray(tracks, dtype=np.int64).ravel()
        tracks = tracks[self.block.points.contains_many(tracks)].tolist()
        slot, kid, oi = self.block.gather(tracks, kids)
        fixed_mask = np.array([k not in set(free) for k in kids])
        if len(slot) == 0:
            return _Problem(None, kids, tracks, slot, kid, oi, fixed_mask, [])
        if hold_gauge and not self.block.georeferenced and not fixed_mask.any():
            fixed_mask[:2] = True     # gauge: no datum yet, hold the first two keyframes
        gk = [j for j, k in enumerate(kids) if self.block.georeferenced and not fixed_mask[j]
              and self.block.kfs[k].fix_enu is not None and k not in self.datum.rejected]
        pri = [(s, self.block.control[self.block.target_name(t)]) for s, t in enumerate(tracks)
               if t < 0 and not self.block.is_check(t) and not self.block.is_tie(t)] if self.block.georeferenced and gcp_priors else []
        obs_pt = np.concatenate([slot[kid == k] for k in kids])
        tie_slots = [s for s, t in enumerate(tracks) if self.block.is_tie(t)]
        gcp_slots = [s for s, _ in pri]
        scale = None
        if tie_slots or gcp_slots:
            scale = np.full(len(obs_pt), self.opt.loss_scale_px)
            scale[np.isin(obs_pt, tie_slots)] = self.opt.mtp_loss_scale_px
            scale[np.isin(obs_pt, gcp_slots)] = self.opt.gcp_loss_scale_px
        prob = BundleProblem(
            camera=self.block.camera, map_T_cams=np.array([self.block.kfs[k].map_T_cam for k in kids]),
            points_map=self.block.points.get_many(tracks).reshape(-1, 3),
            obs_cam=np.concatenate([np.full(int(np.sum(kid == k)), col[k]) for k in kids]),
            obs_pt=obs_pt, obs_uv=np.concatenate([self.block.kfs[k].uv[oi[kid == k]] for k in kids]),
            obs_loss_scale_px=scale,
            fixed_cams=fixed_mask, fixed_points=None,
            gnss_cam=np.array(gk, int) if gk else None,
            gnss_pos_map=np.array([self.datum.target(self.block.kfs[kids[j]]) for j in gk]).reshape(-1, 3),
            gnss_cov_map=np.array([self.datum.fix_cov_used(self.block.kfs[kids[j]]) for j in gk]).reshape(-1, 3, 3),
            lever_arm_cam_m=self.datum.lever,
            point_priors_idx=np.array([s for s, _ in pri], int) if pri else None,
            point_priors_map=np.array([c.map_xyz for _, c in pri]).reshape(-1, 3),
            point_priors_sigma_m=np.array([c.sigma_m for _, c in pri]).reshape(-1, 3))
        return _Problem(prob, kids, tracks, slot, kid, oi, fixed_mask, gk)

    def solve(self, free: list[int], fixed: list[int], tracks, iterations: int, refine: tuple = (),
               gnss_bias: bool = False, gnss_tilt: bool = False, function_tolerance: float = 1e-6) -> StepReport:
        """Adjust keyframes `free` (beside `fixed`, held) and `tracks`; refine: the intrinsics self-calibrated;
        gnss_bias: the fixes' common offset as 3 more unknowns, added to `gnss_bias_enu` (only GCPs then hold the
        block's position: the caller makes sure they do); gnss_tilt: with it, the tilt of the fixes' heights as
        2 more, taken into `gnss_slope` (the caller makes sure GCPs spread to hold it). Observations left beyond
        `max_reprojection_px` are removed (hand-measured ones kept); the solver stops once a step lowers the cost
        by less than `function_tolerance` of it."""
        b = self.build(free, fixed, tracks)
        kids, tracks, slot, kid, oi, fixed_mask, gk = b.kids, b.tracks, b.slot, b.kid, b.oi, b.fixed_mask, b.gnss_cams
        if b.prob is None:
            return StepReport(kids[-1] if kids else -1, True, 'nothing_to_adjust')
        prob = b.prob
        gnss_tilt = gnss_bias and gnss_tilt and prob.gnss_cam is not None and len(prob.gnss_cam) >= 3
        if gnss_tilt:
            if not self.datum.slope.any():
                self.datum.slope_centre = np.mean(np.asarray(prob.gnss_pos_map, float)[:, :2], axis=0)
            prob = replace(prob, gnss_tilt_centre_m=self.datum.slope_centre)
        t0 = time.monotonic()
        res = adjust(prob, self.opt.loss, self.opt.loss_scale_px, iterations, refine, gnss_bias, gnss_tilt,
                     function_tolerance)
        if res.gnss_bias_enu_m is not None and res.status != 'failed':
            self.datum.bias_enu = self.datum.bias_enu + res.gnss_bias_enu_m
            if res.gnss_tilt is not None:
                # The fixes' heights adjusted: less the tilt . (EN - centre); `GnssDatum.target` adds gnss_slope . (EN - centre).
                self.datum.slope = self.datum.slope - res.gnss_tilt
                self.datum.tilt_estimated = True
        self.solves.append({'iterations': int(res.iterations), 'status': res.status,
                            's': round(time.monotonic() - t0, 2)})
        if refine and res.status != 'failed':
            self.block.camera = res.camera   # self-calibration: every later step uses the refined intrinsics
        for j, k in enumerate(kids):
            if not fixed_mask[j]:
                self.block.kfs[k].map_T_cam = np.asarray(res.map_T_cams[j])
        if tracks:
            self.block.points.set_many(tracks, np.asarray(res.points_map))
        # Observations the robust loss down-weighted past the threshold are outliers: remove them.
        err = reprojection_errors_px(self.block.camera, self.block.poses_of(kid), np.asarray(res.points_map)[slot], prob.obs_uv)
        bad = ~(err <= self.opt.max_reprojection_px)
        if res.status == 'failed' or np.median(err[np.isfinite(err)]) > self.opt.max_reprojection_px:
            bad[:] = False   # not converged: residuals say nothing about outliers yet
        for k, i, s in zip(kid[bad], oi[bad], slot[bad]):
            t = tracks[s]
            if self.block.hand_measured(t):
                continue   # a GCP's or an MTP's observation is measured by hand: keep it
            self.block.deactivate(int(k), int(i), int(t))
        good = ~bad
        rep = StepReport(kids[0], True, res.status, cost=float(res.final_cost),
                         reprojection_rms_px=float(np.sqrt(np.mean(err[good] ** 2))) if good.any() else float('nan'),
                         window_size=int((~fixed_mask).sum()))
        rep.gnss_rms_m = self.datum.rms_m([kids[j] for j in gk])
        return rep

    def centre_covariance(self, free_kids: list[int]) -> dict:
        """Marginal covariance of the camera centres of keyframes `free_kids`, as the solver computes it
        for their window problem at the current estimate (zero iterations): the free keyframes' points
        in every registered keyframe that sees them (the others held, at most max_fixed_keyframes of
        them, most shared points first) and the free keyframes' GNSS priors; no GCP priors and no
        gauge hold, unlike `problem`. Returns {keyframe id: (3, 3) map ENU m^2}, or {} when the
        problem is singular or empty."""
        free = [k for k in free_kids if self.block.kfs[k].map_T_cam is not None]
        tracks = np.unique(np.concatenate([self.block.kf_tracks(k) for k in free] or [np.zeros(0, np.int64)]))
        if len(free) == 0 or len(tracks) == 0:
            return {}
        # track_kfs, not a scan of every keyframe: old ones may be on disk
        fixed = neighbour_keyframes(free, tracks, self.block.track_kfs, self.opt.max_fixed_keyframes)
        prob = self.build(free, fixed, tracks, gcp_priors=False, hold_gauge=False).prob
        res = bundle_adjust(prob, BundleOptions(loss=self.opt.loss, loss_scale_px=self.opt.loss_scale_px,
                                                max_iterations=0, compute_covariance=True))
        if res.cam_centre_cov is None:
            return {}
        return {k: np.asarray(res.cam_centre_cov[j]) for j, k in enumerate(free)}

    def window_selection(self):
        """The window of the newest registered keyframes and the older ones held fixed with them
        (core/window.py select_window)."""
        return select_window(self.block.registered, self.opt.window_size,
                             {k: self.block.kf_tracks(k) for k in self.block.registered[-self.opt.window_size:]},
                             self.block.track_kfs, self.opt.max_fixed_keyframes)

    def select_self_calibration(self, candidates: tuple, iterations: int | None = None,
                                from_block: bool = False) -> tuple:
        """The stepwise self-calibration (core/self_calibration.py `select_stepwise`): which of `candidates`
        the block's final adjustment refines: f, cx and cy among them always (`SELF_CALIBRATION_BASE`), the
        distortion terms when they pay. The candidates start from the camera as given (a self-calibration
        made before is undone); `from_block`: from the camera the block holds, and the candidates in which it
        differs from the given one (the pass's self-calibration) are refined in every trial, not selected: a
        block adjusted with the pass's lens and trialled with the given one (a strong lens's k1 of -0.12 undone,
        28 px at the corners) starts far from its minimum, and with f free its trials fall into a block collapsed
        onto its cameras (f 520 -> 3 px on the simulator's 104-photo survey, tests/test_self_calibration_start.py).
        Each trial adjusts one and the same problem (the block's active observations,
        the fixes at their current weights) with its intrinsics refined, from the result of the trial of the
        intrinsics kept so far (the first, none refined, from the block as it is). A trial is measured by the RMS
        of its reprojection residuals, each capped at `max_reprojection_px` (an outlier counts no more than that;
        an observation the lens's distortion moved that far counts in full once a model explains it), the
        refined values (and how far they moved from the given ones) with their sigmas and correlations with the
        block's height (asked only of a candidate that pays), and the cameras' bowl against their geotags' heights (`height_bowl`, at the block's
        radius). The block is left as it was (only the candidates back at their
        given values, or, from_block, as it held them): the caller adjusts it with the kept intrinsics, along the same path as an explicit list
        of them. Returns them (also in `self.self_calibration`)."""
        iters = iterations or self.opt.full_iterations
        given_by_name = _intrinsics_by_name(self.block.camera_given)
        refined_before = ()
        if from_block:
            held = _intrinsics_by_name(self.block.camera)
            refined_before = tuple(c for c in candidates if held[c] != given_by_name[c])
        else:
            self.block.camera = _with_intrinsics_of(self.block.camera, self.block.camera_given, candidates)
        b = self.build(list(self.block.registered), [], list(self.block.points))
        if b.prob is None:
            self.self_calibration = None
            return ()
        prob = b.prob

        results = {}

        def started(res):
            return replace(prob, camera=res.camera if res.camera is not None else prob.camera,
                           map_T_cams=np.asarray(res.map_T_cams), points_map=np.asarray(res.points_map))

        def evaluate(refine: tuple) -> Trial:
            # From the adjustment of the intrinsics kept so far (the first from the block as it is).
            before = results.get(tuple(refine[:-1])) if refine else None
            res = bundle_adjust(prob if before is None else started(before),
                                BundleOptions(loss=self.opt.loss, loss_scale_px=self.opt.loss_scale_px,
                                              max_iterations=iters, refine_intrinsics=tuple(refine),
                                              function_tolerance=TRIAL_FUNCTION_TOLERANCE))
            results[tuple(refine)] = res
            cam = res.camera if res.camera is not None else prob.camera
            T = np.asarray(res.map_T_cams)
            P = np.asarray(res.points_map)
            err = reprojection_errors_px(cam, T[prob.obs_cam], P[prob.obs_pt], prob.obs_uv)
            err = np.minimum(np.nan_to_num(err, nan=np.inf), self.opt.max_reprojection_px)
            rms = float(np.sqrt(np.mean(err ** 2))) if res.status != 'failed' else float('nan')
            values = {n: float(v) for n, v in _intrinsics_by_name(cam).items() if n in refine}
            moved = {n: v - float(given_by_name[n]) for n, v in values.items()}
            bowl = None
            if prob.gnss_cam is not None and len(prob.gnss_cam) >= 7:
                Tg = T[prob.gnss_cam]
                ant = Tg[:, :3, 3] + Tg[:, :3, :3] @ prob.lever_arm_cam_m
                bowl = height_bowl(prob.gnss_pos_map[:, :2], ant[:, 2] - prob.gnss_pos_map[:, 2]).get('rise_m')
            return Trial(tuple(refine), rms, values, moved, bowl_m=bowl, status=res.status)

        def determine(trial: Trial) -> None:
            # The covariance at the trial's result (zero iterations): sigmas and correlations with the height.
            cov = bundle_adjust(started(results[trial.refine]),
                                BundleOptions(loss=self.opt.loss, loss_scale_px=self.opt.loss_scale_px,
                                              max_iterations=0, refine_intrinsics=trial.refine,
                                              compute_covariance=True))
            trial.sigmas = cov.intrinsics_sigma()
            trial.height_correlation = cov.intrinsics_height_correlation()

        # The focal and the principal point, when asked for, are refined in every trial: what they are worth shows
        # against GCP heights or precise geotags, not in the reprojection (the simulator's PPK flight: the principal
        # point buys 0.7 % of the RMS and halves the check points' error). The distortion terms are selected.
        base = tuple(c for c in candidates if c in SELF_CALIBRATION_BASE or c in refined_before)
        sel = select_stepwise(tuple(c for c in candidates if c not in base), evaluate, base=base,
                              min_gain_fraction=self.opt.self_calibration_min_gain,
                              min_gain_px=self.opt.self_calibration_min_gain_px, determine=determine)
        self.self_calibration = sel
        return sel.kept


    def window(self, kid: int, iterations: int) -> StepReport:
        """The window update of the newest keyframes (`window_selection`), reported as keyframe kid's step."""
        sel = self.window_selection()
        rep = self.solve(sel.free_kfs, sel.fixed_kfs, sel.track_ids, iterations,
                         function_tolerance=WINDOW_FUNCTION_TOLERANCE)
        rep.kid = kid
        return rep
