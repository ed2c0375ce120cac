"""Incremental aerial triangulation: two-view start, PnP, triangulation, georeference, sliding window.

Input is one `KeyframeRecord` per keyframe (tracks as ids + distorted pixels, a GNSS fix in WGS84
with its ENU covariance, optional target observations by name). The reconstruction starts in an
arbitrary frame from two keyframes; as soon as the camera centres are not collinear (a straight
line leaves the roll about the line undetermined) a RANSAC similarity to the GNSS positions moves
it into `map` (ENU at the origin), a full adjustment follows, and from then on every adjustment
carries the fixes as priors weighted by their covariance. Surveyed GCPs enter as point priors;
check points are never used, only triangulated afterwards from the adjusted cameras. Manual tie
points (MTPs: points without coordinates an operator marked in several photos, `ties`) enter as
tie points measured by hand: a robust-loss scale of their own (`mtp_loss_scale_px`), kept through
outlier removal like GCP observations, and a segment that shares them with the block joins it
through them (a similarity fitted to three or more, a shift to one or two) before its GNSS.

Lever arm: the GNSS antenna is `C + map_R_cam @ lever_arm_cam_m`, a fixed offset in the camera
frame. That is exact for a camera rigidly mounted on the body and an approximation for a gimbal:
the error is |lever| times the body-vs-camera attitude difference, 1.7 cm for a 20 cm mast on a
multirotor pitched 5 degrees into its course. A record's `antenna_offset_map_m` (from the body
attitude, core/attitude.py) replaces it for that keyframe.

A gimballed camera gives the lever arm in the body frame instead (`lever_arm_body_frd_m`): its
records carry their antenna offsets, and a record without one takes the body lever arm as if
flying level, image top forward (`lever_arm_cam_from_frd`).

Every adjustment is one `problem(free, fixed, tracks)` of the adjuster's state; `centre_covariance`
evaluates the marginal covariance of a window's camera centres from the same builder.

Memory on long flights (`spill_frozen`): what can no longer enter a window leaves the Python heap
(core/at_freeze.py); results are bit-identical to keeping everything.

Parameters: `IncrementalOptions`, declared with descriptions and ranges (params.py); the bundle
node's parameter set extends it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg

from photogram_ros.core.at_freeze import Freezer
from photogram_ros.core.at_store import Keyframe, PointStore
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.core.rotations import R_from_rotvec, invert_T, make_T
from photogram_ros.core.self_calibration import (INTRINSICS, MIN_GAIN_FRACTION, MIN_GAIN_PX, Selection, Trial,
                                                 height_bowl, select_stepwise)
from photogram_ros.core.similarity import similarity_on_line, similarity_ransac, spread
from photogram_ros.core.two_view import relative_pose, scene_facing
from photogram_ros.core.window import neighbour_keyframes, select_window
from photogram_ros.errors import ConfigError, DataError
from photogram_ros.params import param

from photogram_ros.core.bundle import BundleOptions, BundleProblem, bundle_adjust

# How far the mean optical axis of a nadir flight may lie from the vertical (1 sigma, degrees): a gimbal
# held at nadir, or a camera fixed to look down, over a whole flight.
NADIR_PRIOR_DEG = 2.0
# What final_self_calibration "auto" selects from, stepwise: the radial distortion of a camera from the EXIF.
AUTO_CANDIDATES = ('k1', 'k2')
# Intrinsics a stepwise self-calibration refines whenever they are candidates (`select_self_calibration`).
SELF_CALIBRATION_BASE = ('f', 'cx', 'cy')
# The lens distortion terms: what the incremental pass may refine (`pass_self_calibration`).
DISTORTION_TERMS = ('k1', 'k2', 'p1', 'p2', 'k3')
# growth_ratio for a camera whose distortion is refined in the pass (triangulate, replay of a photo folder): a
# geometric series of full adjustments costs about 3 of the final block's.
PASS_GROWTH_RATIO = 1.5
# A self-calibration trial stops once a step lowers its cost by less than this fraction (its reprojection RMS by
# about half of it, 0.005 %), far inside the 2 % a candidate must gain; the adjustments keep 1e-6. On the
# simulator's sample flight (76 keyframes) the trials take 44 s with it, 80 s at 1e-6, and choose alike.
TRIAL_FUNCTION_TOLERANCE = 1e-4


def _clipped_sigma(x: np.ndarray, k: float = 3.5, rounds: int = 5) -> float:
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


@dataclass
class KeyframeRecord:
    stamp_ns: int
    track_ids: np.ndarray           # (K,) int
    uv: np.ndarray                  # (K, 2) distorted pixels
    fix: GnssFix | None = None
    name: str = ''
    target_uv: dict = field(default_factory=dict)   # target name -> (u, v) pixels
    # Antenna minus camera centre in map ENU (m), from the autopilot attitude and the body lever
    # arm; when None the fixed camera-frame lever arm of the options is used instead.
    antenna_offset_map_m: np.ndarray | None = None


@dataclass
class ControlPoint:
    name: str
    map_xyz: np.ndarray             # surveyed, map ENU (m)
    sigma_m: np.ndarray             # (3,) E, N, U
    role: str                       # 'gcp' (used) or 'check' (never used)


GNSS_TILT_MODES = ('never', 'auto', 'always')
# The "auto" tilt's F-test level. With 5 GCPs (2 degrees of freedom left) its quantile is 9.0 (19.0 at 95 %); the
# simulator's sample flight gives F 1.3 at most over six flights whose fixes lean 2 mm/m or less, and 11.0 for one
# whose fixes lean 10 mm/m (bench/gnss_tilt.py).
TILT_TEST_LEVEL = 0.90


@dataclass
class IncrementalOptions:
    """The aerial triangulation's parameters (ROS-free; nodes/bundle_node.py's set extends it)."""
    window_size: int = param(10, 'keyframes adjusted per update (newest); older ones sharing points are held fixed',
                             min=2, max=200)
    max_fixed_keyframes: int = param(30, 'at most this many fixed keyframes enter a window update', min=0, max=1000)
    min_init_inliers: int = param(30, 'tie points (and relative-pose inliers) the first two keyframes need to start',
                                  min=8, max=100000)
    min_init_angle_deg: float = param(2.0, 'median ray angle of the first two keyframes, deg (a shorter baseline '
                                           'waits for a later keyframe)', min=0.0, max=60.0)
    min_triangulation_angle_deg: float = param(1.5, 'a new point needs rays at least this far apart, deg',
                                               min=0.0, max=90.0)
    max_reprojection_px: float = param(2.5, 'observations with a larger error after adjustment are dropped, px',
                                       min=0.3, max=100.0)
    pnp_threshold_px: float = param(3.0, 'RANSAC threshold of a new keyframe\'s resection (and of the first '
                                         'relative pose), px', min=0.1, max=100.0)
    min_pnp_inliers: int = param(12, 'a new keyframe registers with at least this many resection inliers',
                                 min=4, max=100000)
    relative_fallback: bool = param(True, 'a keyframe that resection cannot orient (too few known points: photo-rate '
                                          'input, a break) is oriented from its relative pose to the registered '
                                          'keyframe it shares most tracks with, scaled by the known points it sees '
                                          'or by GNSS', )
    min_relative_inliers: int = param(25, 'relative-pose inliers that fallback needs', min=8, max=100000)
    segments: bool = param(True, 'keyframes that share no tie point with the block (every track lost: a long gap '
                                 'in the frames) start a segment of their own, which joins the block through its '
                                 'GNSS once that georeferences it (or at the end of the flight)')
    loss: str = param('huber', 'robust loss on reprojection errors', choices=('huber', 'cauchy', 'linear'))
    loss_scale_px: float = param(1.0, 'robust loss scale, pixels', min=0.05, max=100.0)
    mtp_loss_scale_px: float = param(3.0, 'robust loss scale of the manual tie points (marked by hand to about '
                                          '1 px; kept through outlier removal), pixels', min=0.05, max=1000.0)
    gcp_loss_scale_px: float = param(3.0, 'robust loss scale of the GCPs\' observations (markers found to a '
                                          'fraction of a pixel or marked by hand, vetted against the block before '
                                          'use), pixels: at the tie points\' scale a few pixels of camera-model '
                                          'error would turn the GCPs\' pull down', min=0.05, max=1000.0)
    window_iterations: int = param(15, 'solver iterations of a window update', min=1, max=1000)
    full_iterations: int = param(50, 'solver iterations of a full adjustment (each round)', min=1, max=1000)
    lever_arm_cam_m: list = param([0.0, 0.0, 0.0], 'GNSS antenna position in the optical camera frame '
                                  '(x right, y down, z forward), m: a camera fixed to the body')
    lever_arm_body_frd_m: list = param([0.0, 0.0, 0.0], 'GNSS antenna position relative to the camera centre in '
                                       'the body frame (forward, right, down), m: a gimballed camera, whose '
                                       'keyframes carry their antenna offset from the attitude (bundle_node follows '
                                       'mavlink/attitude); zeros: lever_arm_cam_m is used')
    georef_min_keyframes: int = param(4, 'keyframes with a fix before the block is georeferenced', min=3, max=10000)
    georef_min_spread_ratio: float = param(0.05, 'the fixes must spread across their line by this fraction of '
                                                 'its length before the georeference is final (a turn)',
                                           min=0.0, max=1.0)
    assume_nadir: bool = param(True, 'a straight first line georeferences provisionally, the roll about it '
                                     'from a near-nadir camera (final at the first turn); and a relative pose '
                                     'must see its tie points\' plane facing the camera (`min_facing`)')
    min_facing: float = param(0.5, 'with assume_nadir: a relative pose (the first two keyframes, the relative '
                                   'fallback) whose tie points\' best plane has a normal further than this |cos| '
                                   'from the optical axis is not used: it sees the ground edge-on, the planar twin '
                                   'of an aerial pair (0.5: 60 degrees, room for oblique cameras and relief)',
                              min=0.0, max=1.0)
    use_gcps: bool = param(True, 'surveyed GCPs enter the adjustment as point priors (off: every target is a '
                                 'check point)')
    estimate_gnss_bias: bool = param(True, 'estimate a constant ENU GNSS offset in the full adjustment when >= 3 '
                                           'GCPs make it observable')
    control_adjustment: bool = param(True, 'in flight, a full adjustment of the whole block (with the GNSS noise '
                                           'estimate and the GNSS bias) each time its GCPs change (3 or more: one '
                                           'seen, or one the vetting took out): the window adjustments hold the '
                                           'older keyframes, so without it GCPs seen later cannot move them, and '
                                           'the live check points show a block the final adjustment will move')
    control_adjustment_max_keyframes: int = param(1000, 'the control adjustment runs on blocks of at most this '
                                                        'many oriented keyframes (its cost grows with the block)',
                                                  min=1, max=10000000)
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
    estimate_gnss_noise: bool = param(True, 'the full adjustment estimates the flight\'s GNSS noise (horizontal and '
                                            'vertical apart) from its residuals and weights the fixes by it when '
                                            'they are poorer than they state; fixes far beyond it are not used')
    gnss_noise_min_keyframes: int = param(8, 'oriented keyframes with a fix the GNSS noise estimate needs',
                                          min=4, max=100000)
    final_self_calibration: str = param('', 'intrinsics the final full adjustment refines, comma separated (from f, '
                                             'cx, cy, k1, k2, p1, p2, k3; empty: none; all of them refined), or '
                                             '"auto": stepwise from k1, k2, each kept only when it pays in '
                                             'reprojection (core/self_calibration.py): a camera from the EXIF, whose '
                                             'distortion nobody measured, wants "auto"')
    pass_self_calibration: str = param('', 'distortion terms the full adjustments during the incremental pass refine '
                                            '(at the final georeference, then as the block grows: growth_ratio), '
                                            'comma separated from k1, k2, p1, p2, k3; empty: none. A camera whose '
                                            'distortion nobody measured (the EXIF\'s) wants k1,k2 on a long block: '
                                            'without them the block bends away from precise geotags, metres at '
                                            'the first photos of a line')
    growth_ratio: float = param(0.0, 'a full adjustment of the whole block (refining pass_self_calibration) each time '
                                     'the oriented keyframes have grown by this factor since the last one; 0: none',
                                min=0.0, max=100.0)
    pass_min_keyframes: int = param(50, 'the pass refines its distortion (and adjusts on growth) once this many keyframes '
                                        'are oriented: a block of a few windows is adjusted whole at the end anyway',
                                    min=2, max=1000000)
    self_calibration_min_gain: float = param(MIN_GAIN_FRACTION, 'stepwise self-calibration: a candidate intrinsic '
                                             'is kept when it lowers the reprojection RMS by at least this fraction '
                                             'of it (and self_calibration_min_gain_px)', min=0.0, max=1.0)
    self_calibration_min_gain_px: float = param(MIN_GAIN_PX, 'stepwise self-calibration: ... and by at least this, '
                                                'px', min=0.0, max=100.0)
    gnss_tighten: bool = param(False, 'the GNSS noise estimate may also weight the fixes tighter than they state '
                                      '(a consumer geotag states metres): horizontally by their residuals about '
                                      'the block, vertically by their heights\' scatter about the flight\'s plane')
    gnss_tighten_floor_m: float = param(0.05, 'a tightened GNSS sigma is at least this, m', min=0.001, max=100.0)
    gnss_gate_m: float = param(1.0, 'a keyframe oriented from the block\'s tie points whose fix lies further than '
                                    'this (and 2 x gnss_outlier_sigma of its sigma) from it keeps its fix out, m',
                               min=0.0, max=1e6)
    gnss_outlier_sigma: float = param(5.0, 'a fix whose residual exceeds this many estimated sigmas (and 3 stated '
                                           'sigmas) is not used', min=2.0, max=1000.0)
    # Long flights: keyframes and tracks that can no longer enter a window leave the Python heap
    # (points to compact arrays, keyframe observations to disk) so memory stays flat; a track id
    # seen again later brings them back, so results are the same either way (core/at_freeze.py).
    spill_frozen: bool = param(True, 'long flights: tie points and keyframes that can no longer enter a window '
                                     'leave memory (compact arrays, keyframe observations on disk); same results')
    spill_dir: str = param('', 'folder for the frozen keyframes\' observations ("" = a private temporary folder, '
                               'removed afterwards)')
    freeze_margin_keyframes: int = param(5, 'a track freezes this many registrations before the window',
                                         min=0, max=10000)
    freeze_every: int = param(5, 'keyframes between freeze passes', min=1, max=10000)
    max_thaws: int = param(3, 'keyframes bringing back (or looking up) ended tracks before freezing stops',
                           min=1, max=10000)

    def check(self) -> None:
        if len(self.lever_arm_cam_m) != 3:
            raise ConfigError(f'lever_arm_cam_m needs 3 numbers (x, y, z), got {self.lever_arm_cam_m}')
        if len(self.lever_arm_body_frd_m) != 3:
            raise ConfigError(f'lever_arm_body_frd_m needs 3 numbers (forward, right, down), got '
                              f'{self.lever_arm_body_frd_m}')
        bad = [v for v in self.final_refine if v not in INTRINSICS]
        if bad:
            raise ConfigError(f'final_self_calibration: {bad} are not intrinsics; choose from f, cx, cy, k1, k2, p1, '
                              'p2, k3, or give "auto"')
        bad = [v for v in self.pass_refine if v not in DISTORTION_TERMS]
        if bad:
            raise ConfigError(f'pass_self_calibration: {bad} are not distortion terms; choose from '
                              f'{", ".join(DISTORTION_TERMS)}')
        if self.gnss_tilt not in GNSS_TILT_MODES:
            raise ConfigError(f'gnss_tilt {self.gnss_tilt!r}: choose one of {", ".join(GNSS_TILT_MODES)}')
        if 0.0 < self.growth_ratio < 1.05:
            raise ConfigError(f'growth_ratio {self.growth_ratio}: give 0 (no growth adjustments) or at least 1.05')
        if any(self.lever_arm_body_frd_m) and any(self.lever_arm_cam_m):
            raise ConfigError('give the GNSS lever arm once: lever_arm_cam_m for a camera fixed to the body, '
                              'lever_arm_body_frd_m for a gimballed camera (the other all zeros)')

    @property
    def final_refine(self) -> tuple:
        """final_self_calibration as a tuple of names (with "auto": the candidates of the stepwise selection)."""
        if self.final_stepwise:
            return AUTO_CANDIDATES
        return _names(self.final_self_calibration)

    @property
    def pass_refine(self) -> tuple:
        """pass_self_calibration as a tuple of names."""
        return _names(self.pass_self_calibration)

    @property
    def final_stepwise(self) -> bool:
        """final_self_calibration is "auto": the final adjustment selects from the candidates stepwise."""
        return self.final_self_calibration.strip().lower() == 'auto'

    @property
    def gimbal(self) -> bool:
        return any(self.lever_arm_body_frd_m)


@dataclass
class _Problem:
    """IncrementalAT.problem() with the map back to the block: observation o is point `slot[o]`
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
    block_adjusted: bool = False    # a full adjustment of the pass (growth_ratio) moved every keyframe and may
                                    # have refined the lens (pass_self_calibration)


def _reprojection_errors_px(camera: PinholeCamera, map_T_cams: np.ndarray, points_map_m: np.ndarray,
                            uv_px: np.ndarray) -> np.ndarray:
    """(n,) pixel distance of each observation: the point points_map_m[i] (map m) seen from map_T_cams[i]
    (4, 4, camera to map) against uv_px[i] (distorted pixels); NaN behind the camera."""
    pc = np.einsum('nji,nj->ni', map_T_cams[:, :3, :3], points_map_m - map_T_cams[:, :3, 3])
    z = np.where(pc[:, 2] > 1e-9, pc[:, 2], np.nan)
    return np.linalg.norm(camera.normalized_to_pixel(pc[:, :2] / z[:, None]) - uv_px, axis=1)


def _intrinsics_by_name(camera: PinholeCamera) -> dict:
    """The camera's intrinsics by their self-calibration names (f is fx)."""
    return {'f': camera.fx, 'cx': camera.cx, 'cy': camera.cy, **dict(zip(('k1', 'k2', 'p1', 'p2', 'k3'), camera.dist))}


def _adjust(prob, loss: str, scale_px: float, iterations: int, refine: tuple = (), gnss_bias: bool = False,
            gnss_tilt: bool = False):
    return bundle_adjust(prob, BundleOptions(loss=loss, loss_scale_px=scale_px, max_iterations=iterations,
                                             refine_intrinsics=tuple(refine), estimate_gnss_bias=gnss_bias,
                                             estimate_gnss_tilt=gnss_tilt))


def flight_plane_sigma(fixes_enu: np.ndarray) -> float:
    """The fixes' vertical noise about the flight's plane (m): the robust scatter (`_clipped_sigma`) of their
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
    return float(np.sqrt(len(X) / max(len(X) - 3.0, 1.0)) * _clipped_sigma(r - np.median(r)))


def lever_arm_cam_from_frd(lever_frd_m) -> np.ndarray:
    """Body-FRD lever arm -> camera frame, for a nadir camera whose image top points forward.

    Optical x = body right, optical y = body backward, optical z = body down.
    """
    f, r, d = np.asarray(lever_frd_m, float)
    return np.array([r, -f, d])


def triangulate_rays(centres: np.ndarray, dirs: np.ndarray, groups: np.ndarray, n: int) -> np.ndarray:
    """Least-squares intersection of rays grouped by point: (n, 3), NaN where undetermined."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    A = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    b = np.einsum('nij,nj->ni', A, centres)
    As = np.zeros((n, 3, 3))
    bs = np.zeros((n, 3))
    np.add.at(As, groups, A)
    np.add.at(bs, groups, b)
    out = np.full((n, 3), np.nan)
    ok = np.abs(np.linalg.det(As)) > 1e-12
    out[ok] = np.linalg.solve(As[ok], bs[ok][..., None])[..., 0]
    return out


class IncrementalAT:
    """The aerial-triangulation state; feed `add_keyframe`, call `full_adjustment` at the end."""

    def __init__(self, camera: PinholeCamera, options: IncrementalOptions | None = None,
                 origin: LocalFrame | None = None, control: list[ControlPoint] | None = None, ties=()):
        self.camera = camera
        # The camera as given: a stepwise self-calibration starts its candidates from these values.
        self._camera_given = camera
        # The last stepwise self-calibration's selection (core/self_calibration.py), None when none was made.
        self.self_calibration: Selection | None = None
        # Every adjustment of the block's keyframes (_solve): its iterations, status and seconds.
        self.solves: list[dict] = []
        self.opt = options or IncrementalOptions()
        self.origin = origin
        self.kfs: list[Keyframe] = []
        self.registered: list[int] = []
        self.points = PointStore()                  # dict-like {track id: (3,) map ENU}
        self.track_kfs: dict[int, list[int]] = {}    # hot tracks: registered keyframes with an active observation
        self._freezer = Freezer(self.opt)
        self.georeferenced = False
        self.georef_provisional = False
        self.control = {c.name: c for c in (control or [])}
        # Manual tie points by name: targets without coordinates that build geometry (not check points).
        self.ties: set[str] = set(ties)
        self._target_ids: dict[str, int] = {}
        # A gimbal: the body lever arm as if flying level, image top forward, where a record has no offset.
        self._lever = (lever_arm_cam_from_frd(self.opt.lever_arm_body_frd_m) if self.opt.gimbal
                       else np.asarray(self.opt.lever_arm_cam_m, float))
        self.history: list[StepReport] = []
        # A separate block of the keyframes after a total loss of tracks, and their ids here (in order).
        self._segment: IncrementalAT | None = None
        self._segment_kids: list[int] = []
        self.segments_joined = 0
        # Keyframes of a block before a break that its GNSS could not place, given up for the segment after it.
        self.unplaced_keyframes = 0
        # Each segment that joined: its keyframes and how ('gnss', or 'mtp' with the tie points used).
        self.segment_joins: list[dict] = []
        self.rng = np.random.default_rng(0)
        # A GNSS receiver without corrections is off by a bias that wanders over minutes; weighting
        # its fixes as independent lets them bend the block away from the GCPs (camera position
        # and tilt trade off over flat ground). With GCPs the bias is observable: estimated here.
        self.gnss_bias_enu = np.zeros(3)
        self.gnss_bias_estimated = False       # a full adjustment with >= 3 GCPs estimated it
        self.gnss_tilt_estimated = False       # ... and the tilt of the fixes' heights with it (`gnss_slope`)
        # The "auto" tilt's test at the last final adjustment: {'gcps', 'rss_bias_m2', 'rss_tilt_m2', 'f', 'f_crit',
        # 'kept'} (empty when not made).
        self.gnss_tilt_test: dict = {}
        # How that estimate ended: {'settled': its last step under 1 mm, 'rounds': adjustments, 'last_step_m'}.
        self.gnss_bias_rounds: dict = {}
        # The GNSS noise as the data shows it: factors (horizontal, vertical) on the fixes' stated sigmas
        # (never below 1), and the keyframes whose fix is not used (far beyond that noise).
        self.gnss_sigma_scale_hv = np.ones(2)
        self.gnss_rejected: set[int] = set()
        self.gnss_noise: dict = {}
        # Heights of a consumer geotag wander by tens of metres within a flight: their trend across the
        # block would tilt it. A slope (dz/dE, dz/dN) taken out of the fixes' heights (about their
        # horizontal centre) where the cameras' looking down says the trend is the fixes' (`_level_block`).
        self.gnss_slope = np.zeros(2)
        self._gnss_slope_centre = np.zeros(2)
        # Oriented keyframes at the last full adjustment (`growth_ratio`).
        self._full_adjusted_n = 0
        # The GCPs in the block at the last control adjustment (`control_adjustment`), by name.
        self._control_adjusted_gcps: frozenset = frozenset()

    @property
    def lever_arm_cam_m(self) -> np.ndarray:
        """(3,) antenna in the camera frame (m) of a keyframe without its own antenna offset."""
        return self._lever.copy()

    @property
    def freezing_stopped(self) -> str:
        """Why this block is no longer frozen ('' while it is)."""
        return self._freezer.stopped

    # --- input --------------------------------------------------------------------------------

    def _new_target_track(self, name: str) -> int:
        if name not in self._target_ids:
            self._target_ids[name] = -(len(self._target_ids) + 1)   # tracker ids are >= 0
        return self._target_ids[name]

    def target_track(self, name: str) -> int | None:
        """Track id (negative) of a target by name, None while no keyframe has observed it."""
        return self._target_ids.get(name)

    def is_check(self, tid: int) -> bool:
        """A target track that never enters the adjustment: a check point, a target the control does
        not name, or any target with use_gcps off. Tracker tracks (tid >= 0) and manual tie points are not."""
        if tid >= 0:
            return False
        name = self.target_name(tid)
        if name in self.ties:
            return False
        c = self.control.get(name)
        return c is None or c.role != 'gcp' or not self.opt.use_gcps

    def add_ties(self, names) -> None:
        """Make targets `names` manual tie points (in flight: ArUco markers the control file does not list,
        ControlSet.marker_ties); before or after their first keyframe."""
        self.ties |= set(names)
        if self._segment is not None:
            self._segment.ties |= set(names)

    def is_tie(self, tid: int) -> bool:
        """A manual tie point's track."""
        return tid < 0 and self.target_name(tid) in self.ties

    def _tie_mask(self, tids: np.ndarray) -> np.ndarray:
        """(n,) bool: which of the track ids are manual tie points."""
        tids = np.asarray(tids, np.int64)
        out = np.zeros(len(tids), bool)
        if self.ties:
            neg = np.flatnonzero(tids < 0)
            out[neg] = [self.is_tie(int(t)) for t in tids[neg]]
        return out

    def _retriangulate_ties(self) -> list[str]:
        """Each manual tie point intersected afresh from every observation in the oriented keyframes (rays
        refined on their reprojection, core `intersect_point`), its observations active again: a point made
        from the photos of one part before another joined, or from a pose that later moved, is stale.
        Returns the names with a point."""
        out = []
        for name in sorted(self.ties):
            tid = self._target_ids.get(name)
            if tid is None:
                continue
            kids = [k for k in self.registered if not self.kfs[k].frozen and self.kfs[k].index(tid) is not None]
            if len(kids) < 2:
                continue
            Ts = np.array([self.kfs[k].map_T_cam for k in kids])
            uv = np.array([self.kfs[k].uv[self.kfs[k].index(tid)] for k in kids], float)
            hit = intersect_point(self.camera, Ts, uv)
            if hit is None or not np.all(np.isfinite(hit[0])):
                continue
            depth = np.einsum('ni,ni->n', hit[0][None] - Ts[:, :3, 3], Ts[:, :3, 2])
            if np.any(depth <= 0):
                continue
            frozen = self.points.is_frozen(tid)   # a frozen track keeps only its count: its point moves alone
            self.points[tid] = hit[0]
            out.append(name)
            if frozen:
                continue
            lst = self.track_kfs.setdefault(tid, [])
            for k in kids:
                self.kfs[k].active[self.kfs[k].index(tid)] = True
                if k not in lst:
                    lst.append(k)
        return out

    def _hand_measured(self, tid: int) -> bool:
        """A target observation kept through outlier removal: a GCP's (its prior holds it) or an MTP's."""
        return tid < 0 and not self.is_check(tid)

    def target_name(self, tid: int) -> str:
        for n, t in self._target_ids.items():
            if t == tid:
                return n
        return ''

    def add_keyframe(self, rec: KeyframeRecord, window_iterations: int | None = None) -> StepReport:
        """Register, triangulate and adjust one keyframe. `window_iterations` replaces the option's
        for this keyframe's window update (a node catching up after a long adjustment)."""
        ids = np.asarray(rec.track_ids, dtype=np.int64).ravel()
        uv = np.asarray(rec.uv, float).reshape(-1, 2)
        if len(ids) != len(uv):
            raise DataError(f'keyframe {rec.stamp_ns}: {len(ids)} track ids but {len(uv)} pixel positions')
        if rec.target_uv:
            ids = np.concatenate([ids, [self._new_target_track(n) for n in rec.target_uv]])
            uv = np.vstack([uv, np.asarray(list(rec.target_uv.values()), float).reshape(-1, 2)])
        ids, first = np.unique(ids, return_index=True)   # a duplicated id would be a tracker bug
        uv = uv[first]
        fix_enu = fix_cov = None
        if rec.fix is not None:
            if self.origin is None:
                self.origin = LocalFrame(rec.fix.lat_deg, rec.fix.lon_deg, rec.fix.h_m)
            fix_enu = np.asarray(self.origin.geodetic_to_enu(rec.fix.lat_deg, rec.fix.lon_deg, rec.fix.h_m))
            fix_cov = np.asarray(rec.fix.cov_enu_m2, float).reshape(3, 3)
        kf = Keyframe(len(self.kfs), int(rec.stamp_ns), rec.name or str(rec.stamp_ns), ids, uv,
                       self.camera.pixel_to_normalized(uv), np.ones(len(ids), bool), fix_enu, fix_cov)
        if rec.antenna_offset_map_m is not None:
            kf.antenna_offset = np.asarray(rec.antenna_offset_map_m, float).reshape(3)
        self._thaw_tracks_seen_again(ids)
        self.kfs.append(kf)
        self._freezer.seen(kf.kid, ids)
        t0 = time.perf_counter()
        if not self.registered:
            rep = self._try_initialise()
        else:
            rep = self._register(kf)
            if not rep.registered and self.opt.relative_fallback:
                rel = self._register_relative(kf)
                rep = rel if rel.registered else StepReport(kf.kid, False, f'{rep.status}; {rel.status}')
            if rep.registered:
                self._triangulate_new(kf)
                if not self.georeferenced or self.georef_provisional:
                    self._try_georeference()
                elif rep.status != 'registered_gnss_rotation':
                    self._gate_fix(kf)
                rep = self._window_adjust(kf.kid, iterations=window_iterations)
                if self._growth_due():
                    self._pass_adjustment(gnss_bias=False)
                    rep.block_adjusted = True
                if self._control_due():
                    self._control_adjustment()
                    rep.block_adjusted = True
            elif self._segment_wanted(kf):
                rep = self._grow_segment(kf, rec, rep, window_iterations)
        rep.solve_s = time.perf_counter() - t0
        rep.n_points = len(self.points)
        self.history.append(rep)
        if self.opt.spill_frozen and kf.kid % max(self.opt.freeze_every, 1) == 0:
            self.freeze()
        return rep

    def _pass_adjustment(self, gnss_bias: bool = True) -> StepReport:
        """A full adjustment during the pass (one round, no GNSS noise estimate); from pass_min_keyframes on,
        the distortion terms of pass_self_calibration are selected stepwise in it (each kept only when it pays,
        as in the final adjustment). The block reports the final adjustment's selection, not this one."""
        final = self.self_calibration
        refine = self.opt.pass_refine if len(self.registered) >= self.opt.pass_min_keyframes else ()
        rep = self.full_adjustment(iterations=self.opt.full_iterations, rounds=1, gnss_noise=False,
                                   refine_intrinsics=refine, stepwise=bool(refine), gnss_bias=gnss_bias)
        self.self_calibration = final
        return rep

    def _growth_due(self) -> bool:
        """The block, georeferenced for good and of pass_min_keyframes, has grown by growth_ratio since its
        last full adjustment (or reached pass_min_keyframes since)."""
        n = len(self.registered)
        return (self.opt.growth_ratio > 0.0 and self.georeferenced and not self.georef_provisional
                and n >= self.opt.pass_min_keyframes
                and (n >= self.opt.growth_ratio * max(self._full_adjusted_n, 1)
                     or self._full_adjusted_n < self.opt.pass_min_keyframes))

    def _control_due(self) -> bool:
        """The block, georeferenced for good and of at most control_adjustment_max_keyframes, holds 3 GCPs or
        more, and not the same ones as at its last control adjustment (one came, or the vetting took one out)."""
        if not (self.opt.control_adjustment and self.opt.use_gcps and self.georeferenced
                and not self.georef_provisional and len(self.registered) <= self.opt.control_adjustment_max_keyframes):
            return False
        gcps = self._gcp_names()
        return len(gcps) >= 3 and gcps != self._control_adjusted_gcps

    def _control_adjustment(self) -> StepReport:
        """The whole block adjusted on its GCPs: one round, the GNSS noise estimate (fixes poorer than they state
        would otherwise bend the block their way), then the GNSS bias; no self-calibration. The older keyframes
        move with the block; the later window adjustments take the fixes less the bias, weighted by their noise."""
        self._control_adjusted_gcps = self._gcp_names()
        self._solve(list(self.registered), [], list(self.points), self.opt.full_iterations)
        if self.opt.estimate_gnss_noise:
            self.estimate_gnss_noise()
        return self.full_adjustment(iterations=self.opt.full_iterations, rounds=1, gnss_noise=False, gnss_bias=True,
                                    tilt_test=False)

    # --- segments: the flight after every track was lost -------------------------------------------

    def _segment_wanted(self, kf: Keyframe) -> bool:
        """A keyframe with a fix that shares no track with the block (no point, no observation in an oriented
        keyframe): the tracker lost every track. One that shares tracks waits for them to become points."""
        if not self.opt.segments or not self.registered or kf.fix_enu is None:
            return False
        if self._segment is not None:
            return True
        ids = kf.track_ids[kf.track_ids >= 0]
        return not (self.points.contains_many(ids).any() or any(int(t) in self.track_kfs for t in ids))

    def _grow_segment(self, kf: Keyframe, rec: KeyframeRecord, failed: StepReport, window_iterations) -> StepReport:
        """Feed the keyframe to the segment (a block of its own in the same map frame); join the segment
        once its GNSS georeferences it (provisionally on a line, as a first line is)."""
        if self._segment is None:
            self._segment = IncrementalAT(self.camera, replace(self.opt, segments=False, spill_frozen=False,
                                                               use_gcps=False), origin=self.origin, ties=self.ties)
            self._segment_kids = []
        self._segment_kids.append(kf.kid)
        seg = self._segment.add_keyframe(rec, window_iterations)
        joins = self.segments_joined
        # Every track lost early on the first line: the block joins the segment's turn (its full adjustment).
        self._georeference_short_block()
        # Provisional too: a gap mid-line leaves a line until the next turn. Both in the map frame: the block
        # must be georeferenced as well. Manual tie points shared with the block join it without waiting.
        if self._segment_can_join():
            self._join_segment()
        if self.segments_joined > joins:
            n = self.segment_joins[-1]['keyframes']
            rep = self._window_adjust(kf.kid, iterations=window_iterations) if kf.map_T_cam is not None \
                else StepReport(kf.kid, False, seg.status)
            rep.joined = n
            rep.status = f'registered (a segment of {n} keyframes joined through its GNSS)' if rep.registered \
                else rep.status
            return rep
        return StepReport(kf.kid, False, f'{failed.status}; in a segment of its own, not georeferenced yet '
                                         f'({len(self._segment.registered)} of {len(self._segment_kids)} oriented)')

    def _shared_ties(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(segment point, block point) of the manual tie points both have triangulated (map frame)."""
        seg = self._segment
        if seg is None or not self.ties:
            return []
        out = []
        for name in sorted(self.ties):
            a, b = seg._target_ids.get(name), self._target_ids.get(name)
            if a is not None and b is not None and a in seg.points and b in self.points:
                out.append((np.asarray(seg.points[a], float), np.asarray(self.points[b], float)))
        return out

    def _ties_fit(self):
        """(similarity segment -> block, manual tie points used, whether it is a full similarity): a
        similarity from three or more shared MTPs that span an area (not on a line), else a shift from
        their offsets (the segment's own georeference then gives the rotation and scale); None without."""
        from photogram_ros.core.similarity import Similarity, umeyama
        pairs = self._shared_ties()
        if not pairs:
            return None, 0, False
        src = np.array([p for p, _ in pairs])
        dst = np.array([q for _, q in pairs])
        sv = spread(src)
        if len(pairs) >= 3 and sv[1] >= 0.2 * sv[0] > 0:
            return umeyama(src, dst), len(pairs), True
        return Similarity(1.0, np.eye(3), np.median(dst - src, axis=0)), len(pairs), False

    def _segment_can_join(self) -> bool:
        """The block is georeferenced and the segment is too (by its GNSS), or shares manual tie points that
        place it alone (three or more spanning an area)."""
        seg = self._segment
        if seg is None or not seg.registered or not self.georeferenced:
            return False
        return seg.georeferenced or self._ties_fit()[2]

    def _georeference_short_block(self) -> bool:
        """The block is too short to georeference by itself and the segment is georeferenced for good:
        georeference the block provisionally on its line from 3 keyframes with a fix, or from any geometry
        its GNSS places (it grows no more: what comes goes to the segment); its full adjustment then joins the
        segment. When its GNSS cannot place it either (a few metres of line under the GNSS noise) and the
        segment is the larger, give up the block's keyframes (not oriented) and take the segment in its place.
        Returns whether the block is georeferenced now."""
        seg = self._segment
        if self.georeferenced or seg is None or not seg.georeferenced or seg.georef_provisional:
            return False
        if self._try_georeference(line_keyframes=3) or self._try_georeference(force=True):
            return True
        if len(seg.registered) <= len(self.registered):
            return False
        self.unplaced_keyframes += len(self.registered)
        for k in self.registered:
            self.kfs[k].map_T_cam = None
        self.registered, self.points, self.track_kfs = [], PointStore(), {}
        self._freezer = Freezer(self.opt)
        self.georeferenced, self.georef_provisional = True, False   # the segment's, georeferenced for good
        kids = self._segment_kids
        self._join_segment()
        for kid in kids:
            self._freezer.seen(kid, self.kfs[kid].track_ids)
        return True

    def _move_segment_onto_ties(self) -> int:
        """Move the segment (poses and points) onto the block through the manual tie points both have
        (`_ties_fit`). Returns how many were used."""
        s, n, full = self._ties_fit()
        seg = self._segment
        if s is None or not (full or seg.georeferenced):
            return 0
        for k in seg.registered:
            seg.kfs[k].map_T_cam = s.apply_pose(seg.kfs[k].map_T_cam)
        ids, P = seg.points.arrays()
        if len(ids):
            seg.points.set_many(ids, s.apply(P))
        seg.georeferenced = True
        return n

    def _join_segment(self) -> int:
        """Move the segment's oriented keyframes and points into the block (through the manual tie points
        both share, when there are any, else through its GNSS); returns how many joined."""
        n_ties = self._move_segment_onto_ties()
        seg, kids = self._segment, self._segment_kids
        self._segment, self._segment_kids = None, []
        for s_kid in seg.registered:
            kf, skf = self.kfs[kids[s_kid]], seg.kfs[s_kid]
            kf.map_T_cam = np.asarray(skf.map_T_cam, float).copy()
            # The segment's outliers, by tracker id (its target ids are numbered on their own).
            dropped = skf.track_ids[~skf.active]
            kf.active[np.isin(kf.track_ids, dropped[dropped >= 0])] = False
            kf.reg_seq = len(self.registered)
            self.registered.append(kf.kid)
            for t in kf.track_ids[kf.active].tolist():
                self.track_kfs.setdefault(t, []).append(kf.kid)
        ids, P = seg.points.arrays()
        # Tracker ids only: the segment numbers its targets on its own; the block triangulates them below.
        new = (~self.points.contains_many(ids) & (ids >= 0)) if len(ids) else np.zeros(0, bool)
        if new.any():
            self.points.set_many(ids[new], P[new])
        self._retriangulate_ties()
        self.segments_joined += 1
        self.segment_joins.append({'keyframes': len(seg.registered), 'through': 'mtp' if n_ties else 'gnss',
                                   'mtps': n_ties})
        return len(seg.registered)

    def retry_unregistered(self) -> int:
        """Photos that did not register in sequence get a second chance against the whole block
        (resection against every point, then triangulation); returns how many registered now.
        Adjust afterwards (`full_adjustment`)."""
        n = 0
        for kf in self.kfs:
            if kf.map_T_cam is None and self.registered and (
                    self._register(kf).registered
                    or (self.opt.relative_fallback and self._register_relative(kf).registered)):
                self._triangulate_new(kf)
                n += 1
        return n

    # --- geometry steps -------------------------------------------------------------------------

    def _usable(self, kf: Keyframe) -> np.ndarray:
        """Observations that may build geometry: active and not a check point."""
        m = kf.active.copy()
        neg = kf.track_ids < 0
        if neg.any():
            m[neg] &= ~np.array([self.is_check(int(t)) for t in kf.track_ids[neg]])
        return m

    def _faces_scene(self, res) -> bool:
        """A relative pose's tie points lie in front of camera 1 on a plane it looks at (|cos| of the plane's
        normal to the optical axis >= min_facing); always true without assume_nadir."""
        if not self.opt.assume_nadir:
            return True
        return scene_facing(res.points_cam1[res.inliers]) >= self.opt.min_facing

    def _try_initialise(self) -> StepReport:
        new = self.kfs[-1]
        cands = []
        for first in self.kfs[:-1]:
            ids, i1, i2 = np.intersect1d(first.track_ids[self._usable(first)], new.track_ids[self._usable(new)],
                                         return_indices=True)
            i1 = np.flatnonzero(self._usable(first))[i1]
            i2 = np.flatnonzero(self._usable(new))[i2]
            if len(ids) < self.opt.min_init_inliers:
                continue
            thr = self.opt.pnp_threshold_px / self.camera.fx
            res = relative_pose(self._xn(first, i1), self._xn(new, i2), thr, self.opt.min_init_inliers)
            if not res.ok or res.median_angle_deg < self.opt.min_init_angle_deg or not self._faces_scene(res):
                continue
            score = int(res.inliers.sum()) * min(1.0, res.median_angle_deg / (2 * self.opt.min_init_angle_deg))
            cands.append((score, first, res))
        if cands:
            # The pair with the most inliers at enough parallax (not merely the oldest that passes).
            _, first, res = max(cands, key=lambda c: c[0])
            first.map_T_cam = np.eye(4)
            new.map_T_cam = invert_T(res.cam2_T_cam1)
            self.registered = [first.kid, new.kid]
            first.reg_seq, new.reg_seq = 0, 1
            for kf in (first, new):
                for t in kf.track_ids[kf.active].tolist():
                    self.track_kfs.setdefault(t, []).append(kf.kid)
            self._triangulate_new(new)
            # Keyframes between (and before) the pair were waiting: register them now.
            for kf in self.kfs:
                if kf.map_T_cam is None:
                    if self._register(kf).registered or (self.opt.relative_fallback
                                                         and self._register_relative(kf).registered):
                        self._triangulate_new(kf)
            rep = self._window_adjust(new.kid, full=True)
            rep.status = 'initialised'
            return rep
        # No pair yet: drop keyframes too old to ever pair with the newest one.
        return StepReport(new.kid, False, 'waiting_for_initialisation')

    def _register(self, kf: Keyframe) -> StepReport:
        import cv2
        use = self._usable(kf)
        self._thaw_tracks_seen_again(kf.track_ids)   # a second chance for an old keyframe (triangulate)
        have = self.points.contains_many(kf.track_ids) & use
        n = int(have.sum())
        if n < max(self.opt.min_pnp_inliers, 6):
            return StepReport(kf.kid, False, f'too_few_known_points ({n})')
        obj = self.points.get_many(kf.track_ids[have])
        img = self._xn(kf, have)
        prev = self.kfs[self.registered[-1]].map_T_cam
        cam_T_map = invert_T(prev)
        rvec0, _ = cv2.Rodrigues(cam_T_map[:3, :3])
        # No pose guess inside RANSAC: after a turn the previous pose is far off (and it is tried
        # separately below anyway).
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj, img, np.eye(3), None, iterationsCount=200, flags=cv2.SOLVEPNP_AP3P,
            reprojectionError=self.opt.pnp_threshold_px / self.camera.fx, confidence=0.999)
        if not ok or inl is None or len(inl) < self.opt.min_pnp_inliers:
            return StepReport(kf.kid, False, 'pnp_failed')
        inl = inl.ravel()
        # Over flat ground a minimal PnP sample can land on the mirror-image pose; refining from the
        # previous keyframe's pose as well and keeping the better-supported answer avoids it.
        thr = self.opt.pnp_threshold_px / self.camera.fx
        best = None
        # The continuation of the previous pose goes first and a jump must win clearly (10 % more
        # support): the mirror pose fits near-planar ground almost as well.
        for r0, t0 in ((rvec0, cam_T_map[:3, 3].reshape(3, 1)), (rvec, tvec)):
            r1, t1 = cv2.solvePnPRefineLM(obj[inl], img[inl], np.eye(3), None, r0.copy(), t0.copy())
            R1, _ = cv2.Rodrigues(r1)
            pc = obj @ R1.T + t1.ravel()
            z = np.where(pc[:, 2] > 1e-9, pc[:, 2], np.nan)
            e = np.linalg.norm(pc[:, :2] / z[:, None] - img, axis=1)
            ok = e < thr
            score = int(ok.sum())
            if best is None or score > 1.1 * best[0]:
                best = (score, R1, t1, ok)
        _, R, tvec, ok = best
        if ok.sum() < self.opt.min_pnp_inliers:
            return StepReport(kf.kid, False, 'pnp_failed')
        kf.map_T_cam = invert_T(make_T(R, tvec.ravel()))
        out = ~ok & ~self._tie_mask(kf.track_ids[have])
        kf.active[np.flatnonzero(have)[out]] = False
        kf.reg_seq = len(self.registered)
        self.registered.append(kf.kid)
        for t in kf.track_ids[kf.active].tolist():
            self.track_kfs.setdefault(t, []).append(kf.kid)
        return StepReport(kf.kid, True, 'registered')

    def _register_relative(self, kf: Keyframe) -> StepReport:
        """Orientation from the relative pose to the registered keyframe sharing most usable tracks
        with `kf` (essential matrix, core/two_view.py); the baseline length from the known points
        both see (depth ratio, >= 5 of them) or else from the GNSS fixes (the block's scale from its
        registered keyframes' fixes while not georeferenced)."""
        use = self._usable(kf)
        ids = kf.track_ids[use]
        best = None
        for r in self.registered[-2 * self.opt.window_size:]:
            rk = self.kfs[r]
            if rk.frozen:
                continue
            common = np.intersect1d(rk.track_ids[self._usable(rk)], ids)
            if best is None or len(common) > len(best[1]):
                best = (r, common)
        if best is None or len(best[1]) < self.opt.min_relative_inliers:
            return StepReport(kf.kid, False, f'relative: too_few_shared_tracks ({0 if best is None else len(best[1])})')
        r, common = best
        rk = self.kfs[r]
        i1 = np.array([rk.index(int(t)) for t in common])
        i2 = np.array([kf.index(int(t)) for t in common])
        thr = self.opt.pnp_threshold_px / self.camera.fx
        res = relative_pose(self._xn(rk, i1), self._xn(kf, i2), thr, self.opt.min_relative_inliers)
        T_r = rk.map_T_cam
        if res.ok and not self._faces_scene(res):
            return StepReport(kf.kid, False, 'relative: sees its tie points edge-on (the planar twin)')
        if res.ok:
            R, t = res.cam2_T_cam1[:3, :3], res.cam2_T_cam1[:3, 3]
            map_R = T_r[:3, :3] @ R.T
            d_map = T_r[:3, :3] @ (-R.T @ t)             # unit baseline r -> kf, map frame (block units)
            scale = self._relative_scale(rk, kf, common[res.inliers], res, d_map)
            if scale is None:
                return StepReport(kf.kid, False, 'relative: no_scale (neither known points nor GNSS)')
            kf.map_T_cam = make_T(map_R, T_r[:3, 3] + scale * d_map)
            inl = res.inliers
            status = 'registered_relative'
        else:
            # Too short a baseline (or a turn on the spot) for the essential matrix: with a georeferenced
            # block and a fix, the rotation from the homography of the shared tracks (a rotation when
            # the baseline is short against the height), the position from GNSS; the adjustment refines.
            got = self._gnss_and_rotation(rk, kf, i1, i2, thr)
            if got is None:
                return StepReport(kf.kid, False, f'relative: {res.status}')
            kf.map_T_cam, inl = got
            status = 'registered_gnss_rotation'
        out = np.ones(len(kf.track_ids), bool)
        out[i2[inl]] = False
        known = self.points.contains_many(kf.track_ids) & ~self._tie_mask(kf.track_ids)
        kf.active[use & known & out] = False      # known points that disagree with the relative pose
        kf.reg_seq = len(self.registered)
        self.registered.append(kf.kid)
        for tid in kf.track_ids[kf.active].tolist():
            self.track_kfs.setdefault(tid, []).append(kf.kid)
        return StepReport(kf.kid, True, status)

    def _gnss_and_rotation(self, rk: Keyframe, kf: Keyframe, i1, i2, thr: float):
        """(map_T_cam, inlier mask over i1/i2) of `kf` from its fix and the homography rotation to `rk`;
        None without a georeference, a fix or enough homography inliers."""
        import cv2
        if not self.georeferenced or kf.fix_enu is None:
            return None
        H, mask = cv2.findHomography(self._xn(rk, i1), self._xn(kf, i2), cv2.RANSAC, 2 * thr)
        if H is None or int(mask.sum()) < self.opt.min_relative_inliers:
            return None
        U, _, Vt = np.linalg.svd(H)
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt     # nearest rotation: x_kf ~ R x_r
        map_R = rk.map_T_cam[:3, :3] @ R.T
        lever = self._lever if kf.antenna_offset is None else map_R.T @ kf.antenna_offset
        C = kf.fix_enu - self.gnss_bias_enu - map_R @ lever
        return make_T(map_R, C), mask.ravel().astype(bool)

    def _relative_scale(self, rk: Keyframe, kf: Keyframe, inlier_ids, res, d_map) -> float | None:
        """Length of the baseline rk -> kf in block units (see _register_relative)."""
        known = inlier_ids[self.points.contains_many(inlier_ids)]
        if len(known) >= 5:
            X = self.points.get_many(known)
            depth_block = ((X - rk.map_T_cam[:3, 3]) @ rk.map_T_cam[:3, :3])[:, 2]
            rows = np.searchsorted(inlier_ids, known)
            depth_unit = res.points_cam1[np.flatnonzero(res.inliers)[rows], 2]
            ok = (depth_block > 0) & (depth_unit > 0)
            if ok.sum() >= 5:
                return float(np.median(depth_block[ok] / depth_unit[ok]))
        if rk.fix_enu is None or kf.fix_enu is None:
            return None
        gnss_m = float(np.linalg.norm(kf.fix_enu - rk.fix_enu))
        if self.georeferenced:
            return gnss_m
        ks = [k for k in self.registered if self.kfs[k].fix_enu is not None]
        if len(ks) < 2:
            return None
        C = np.array([self.kfs[k].map_T_cam[:3, 3] for k in ks])
        G = np.array([self.kfs[k].fix_enu for k in ks])
        block, world = np.linalg.norm(C - C[0], axis=1)[1:], np.linalg.norm(G - G[0], axis=1)[1:]
        if world.max() < 1e-6:
            return None
        return gnss_m * float(np.sum(block * world) / np.sum(world * world))

    def _xn(self, kf: Keyframe, idx) -> np.ndarray:
        """Undistorted normalised coordinates of kf's observations `idx` with the current camera: those
        stored with the keyframe (made with the camera as given) until a self-calibration changes it."""
        if self.camera == self._camera_given:
            return kf.xn[idx]
        return self.camera.pixel_to_normalized(kf.uv[idx])

    def reprojection_px(self, map_T_cam: np.ndarray, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(n,) pixel distance between the points X (n, 3, map) seen from map_T_cam and uv (n, 2
        distorted pixels); inf behind the camera."""
        T = map_T_cam
        pc = (X - T[:3, 3]) @ T[:3, :3]
        z = np.where(pc[:, 2] > 1e-9, pc[:, 2], np.nan)
        proj = self.camera.normalized_to_pixel(pc[:, :2] / z[:, None])
        e = np.linalg.norm(proj - uv, axis=1)
        return np.where(np.isfinite(e), e, np.inf)

    def _gather(self, tracks, kids=None):
        """Active observations of `tracks` (in `kids`, default every registered keyframe that sees
        them): point slot, keyframe id, observation index; vectorised per keyframe."""
        tr = np.asarray(tracks, dtype=np.int64)
        if kids is None:
            ks = set()
            for t in tracks:
                ks.update(self.track_kfs.get(int(t), ()))
            kids = sorted(ks)
        if not len(tr) or not len(kids):
            return np.zeros(0, int), np.zeros(0, int), np.zeros(0, int)
        sorter = np.argsort(tr)
        tr_sorted = tr[sorter]
        slot, kid, oi = [], [], []
        for k in kids:
            kf = self.kfs[k]
            pos = np.clip(np.searchsorted(tr_sorted, kf.track_ids), 0, len(tr) - 1)
            m = kf.active & (tr_sorted[pos] == kf.track_ids)
            idx = np.flatnonzero(m)
            slot.append(sorter[pos[idx]])
            kid.append(np.full(len(idx), k))
            oi.append(idx)
        return np.concatenate(slot), np.concatenate(kid), np.concatenate(oi)

    def _poses_of(self, kid: np.ndarray) -> np.ndarray:
        uk, inv = np.unique(kid, return_inverse=True)
        return np.array([self.kfs[k].map_T_cam for k in uk]).reshape(-1, 4, 4)[inv]

    def _triangulate_tracks(self, tracks: list[int]) -> None:
        if not tracks:
            return
        for _ in range(2):   # second pass after dropping the observations that disagree
            slot, kid, oi = self._gather(tracks)
            if len(slot) == 0:
                return
            counts = np.bincount(slot, minlength=len(tracks))
            ks = list(dict.fromkeys(kid.tolist()))     # _gather groups by keyframe, in this order
            Ts = self._poses_of(kid)
            xn = np.concatenate([self._xn(self.kfs[k], oi[kid == k]) for k in ks])
            uv = np.concatenate([self.kfs[k].uv[oi[kid == k]] for k in ks])
            dirs = np.einsum('nij,nj->ni', Ts[:, :3, :3], np.column_stack([xn, np.ones(len(xn))]))
            X = triangulate_rays(Ts[:, :3, 3], dirs, slot, len(tracks))
            Xo = X[slot]
            pc = np.einsum('nji,nj->ni', Ts[:, :3, :3], Xo - Ts[:, :3, 3])
            z = np.where(pc[:, 2] > 1e-9, pc[:, 2], np.nan)
            err = np.linalg.norm(self.camera.normalized_to_pixel(pc[:, :2] / z[:, None]) - uv, axis=1)
            bad = ~(err <= self.opt.max_reprojection_px)
            if not bad.any() or _ == 1:
                break
            # Only drop observations of points that still have two good ones.
            good_counts = np.bincount(slot[~bad], minlength=len(tracks))
            drop = bad & (good_counts[slot] >= 2)
            drop &= np.array([not self.is_tie(int(t)) for t in np.asarray(tracks)[slot]])
            if not drop.any():
                break
            for k, i, t in zip(kid[drop], oi[drop], np.asarray(tracks)[slot[drop]]):
                self._deactivate(int(k), int(i), int(t))
        # Triangulation angle: widest pair of rays, approximated by each ray against the mean ray.
        rays = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        mean = np.zeros((len(tracks), 3))
        np.add.at(mean, slot, rays)
        mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
        ang = np.degrees(np.arccos(np.clip(np.einsum('ij,ij->i', rays, mean[slot]), -1, 1)))
        max_ang = np.zeros(len(tracks))
        np.maximum.at(max_ang, slot, ang)
        worst = np.zeros(len(tracks))
        np.maximum.at(worst, slot, np.where(np.isfinite(err), err, 1e9))
        ok = (counts >= 2) & np.all(np.isfinite(X), axis=1) & (2 * max_ang >= self.opt.min_triangulation_angle_deg) \
            & (worst <= self.opt.max_reprojection_px)
        for s in np.flatnonzero(ok):
            self.points[int(tracks[s])] = X[s]

    def _triangulate_new(self, kf: Keyframe) -> None:
        use = self._usable(kf)
        cand = kf.track_ids[use]
        tracks = [int(t) for t in cand[~self.points.contains_many(cand)]
                  if len(self.track_kfs.get(int(t), ())) >= 2]
        self._triangulate_tracks(tracks)
        # Existing points seen again: drop the observations that disagree with them.
        act = np.flatnonzero(use & kf.active)
        idx = act[self.points.contains_many(kf.track_ids[act])].tolist()
        if idx:
            X = self.points.get_many(kf.track_ids[idx])
            e = self.reprojection_px(kf.map_T_cam, X, kf.uv[idx])
            for i in np.asarray(idx)[e > 2 * self.opt.max_reprojection_px]:
                if not self.is_tie(int(kf.track_ids[i])):
                    self._deactivate(kf.kid, int(i), int(kf.track_ids[i]))

    def _deactivate(self, kid: int, i: int, t: int) -> None:
        kf = self.kfs[kid]
        kf.active[i] = False
        lst = self.track_kfs.get(t)
        if lst and kid in lst:
            lst.remove(kid)
            if len(lst) < 2:
                self.points.pop(t, None)
        elif lst is None:
            # A frozen track keeps only its count (an active observation is always in its list).
            n = self.points.frozen_count_decrement(t)
            if n is not None and n < 2:
                self.points.pop(t, None)

    # --- georeference -------------------------------------------------------------------------

    def _try_georeference(self, force: bool = False, line_keyframes: int | None = None) -> bool:
        """`force`: accept any non-collinear geometry (end of flight: nothing better will come).
        `line_keyframes`: a straight line georeferences provisionally with this many keyframes with a fix
        (at least 3) spread over 10 sigmas of their GNSS; default: twice georef_min_keyframes over 5 m too."""
        ks = [k for k in self.registered if self.kfs[k].fix_enu is not None]
        if not self.georeferenced and (not ks or (force and len(ks) < 3)):
            return self._georeference_by_gcps()
        if len(ks) < (max(self.opt.georef_min_keyframes, 3) if line_keyframes is None else max(line_keyframes, 3)):
            return False
        src = np.array([self.kfs[k].map_T_cam[:3, 3] for k in ks])
        dst = np.array([self.kfs[k].fix_enu if self.kfs[k].antenna_offset is None
                        else self.kfs[k].fix_enu - self.kfs[k].antenna_offset for k in ks])
        sig = np.sqrt(np.median([np.trace(self.kfs[k].fix_cov) for k in ks]))
        sv = spread(dst)
        if force:
            # End of flight: GCPs (three or more) join the fit. On a straight line the GNSS leaves the roll
            # about it to noise, and the GCPs off the line fix it.
            gcp = self._gcp_pairs()
            if len(gcp) >= 3:
                src = np.vstack([src, [p for p, _ in gcp]])
                dst = np.vstack([dst, [q for _, q in gcp]])
        else:
            gcp = []
        # A block made without GNSS drifts in scale along the line: tolerate ~2 % of its extent.
        thr = 4.0 * sig + np.linalg.norm(self._lever) + 0.05 + 0.02 * 2 * sv[0]
        res = similarity_ransac(src, dst, thr, self.rng,
                                min_spread_ratio=0.005 if force else self.opt.georef_min_spread_ratio)
        n_in = int(res.inliers.sum()) if res.ok else len(ks)
        side = spread(dst[res.inliers])[1] if res.ok else 0.0
        # The turn must be wide against the GNSS noise averaged over the fixes, or the roll about
        # the line is noise (the adjustment that follows refines it, but needs a fair start).
        if res.ok and (force or side >= 3.0 * sig / np.sqrt(n_in)):
            s = res.sim
            # Forced on a line the GNSS noise spans: the roll about it is noise (provisional, it says so).
            provisional = force and len(gcp) < 3 and side < 3.0 * sig / np.sqrt(n_in)
        elif self.georeferenced:
            return False    # provisional already; wait for the turn
        elif self.opt.assume_nadir and len(ks) >= (2 * self.opt.georef_min_keyframes if line_keyframes is None
                                                   else line_keyframes) and sv[0] > max(
                10.0 * sig, 5.0 if line_keyframes is None else 0.0):
            # Straight line: everything but the roll about it comes from GNSS; the roll from the
            # near-nadir camera. Provisional until the first turn.
            n = len(ks)   # the cameras alone (GCPs joined a forced fit above)
            dirs = np.array([self.kfs[k].map_T_cam[:3, 2] for k in ks])
            s = similarity_on_line(src[:n], dst[:n], dirs)
            # A glitched fix on the line would tilt it: fitted again without the fixes far from the first fit.
            near = np.linalg.norm(s.apply(src[:n]) - dst[:n], axis=1) <= max(thr, 3.0 * float(np.median(
                np.linalg.norm(s.apply(src[:n]) - dst[:n], axis=1))))
            if 3 <= near.sum() < n:
                s = similarity_on_line(src[:n][near], dst[:n][near], dirs[near])
            provisional = True
        else:
            return False
        if self.georeferenced:   # provisional -> final: GNSS priors of the whole block fix the roll
            self.georef_provisional = False
            self._pass_adjustment()
            return True
        # Fixes far from where the georeferenced block puts their cameras are glitches: not used.
        far = np.linalg.norm(s.apply(src[:len(ks)]) - dst[:len(ks)], axis=1) > thr
        if far.sum() <= len(ks) // 4:
            self.gnss_rejected |= {k for k, f in zip(ks, far) if f}
        self._apply_georeference(s, provisional)
        return True

    def set_origin(self, origin: LocalFrame) -> bool:
        """The map frame's origin when no fix has set it (a flight without GNSS, placed by its GCPs): False,
        and nothing changed, once one is set."""
        if self.origin is not None:
            return False
        self.origin = origin
        return True

    def gcps_in_block(self) -> int:
        """How many GCPs have a point in the block (the datum it has besides its GNSS)."""
        return len(self._gcp_pairs())

    def _gcp_pairs(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(triangulated point, surveyed map position) of every GCP with a point in the block (not check
        points, not manual tie points)."""
        return [(self.points[t], self.control[n].map_xyz) for n, t in self._target_ids.items()
                if t in self.points and not self.is_check(t) and not self.is_tie(t)]

    def _georeference_by_gcps(self) -> bool:
        """A block whose cameras have no fix (photos without geotags, a GNSS outage from the start), or fewer
        than 3 at the end: 3 or more GCPs triangulated in it, not on a line, georeference it by the similarity of their
        points onto their surveyed positions. Each must fit it within 5 cm + 2 % of the GCPs' extent (the
        relative block's scale drift); False (not georeferenced) when they do not, or are too few."""
        gcp = self._gcp_pairs()
        if len(gcp) < 3:
            return False
        src = np.array([p for p, _ in gcp], float)
        dst = np.array([q for _, q in gcp], float)
        thr = 0.05 + 0.02 * 2 * spread(dst)[0]
        res = similarity_ransac(src, dst, thr, self.rng, min_spread_ratio=self.opt.georef_min_spread_ratio)
        if not res.ok or not res.inliers.all():
            return False
        self._apply_georeference(res.sim, provisional=False)
        return True

    def _apply_georeference(self, s, provisional: bool) -> None:
        """Move the block by the similarity `s` into the map frame, then adjust it with its datum."""
        for k in self.registered:
            self.kfs[k].map_T_cam = s.apply_pose(self.kfs[k].map_T_cam)
        ids, P = self.points.arrays()
        if len(ids):
            self.points.set_many(ids, np.array([s.apply(p[None])[0] for p in P]))
        self.georeferenced = True
        self.georef_provisional = provisional
        if provisional:
            self.full_adjustment(iterations=self.opt.full_iterations, rounds=1, gnss_noise=False)
        else:
            self._pass_adjustment()

    # --- adjustment -----------------------------------------------------------------------------

    def problem(self, free_kids: list[int], fixed_kids: list[int], tracks) -> BundleProblem | None:
        """The bundle problem of the adjuster's state that every adjustment solves.

        Keyframes `free_kids` are adjusted and `fixed_kids` held (cameras in that order); the points
        are those of `tracks` that have one (in that order), observed by every active observation
        in these keyframes. Once georeferenced, the free keyframes' fixes are GNSS priors (moved by
        the estimated bias; the antenna at the lever arm, or at the record's antenna offset) and the
        GCPs among the tracks point priors. Without a datum and nothing held, the first two
        keyframes are held (the gauge). None when there is no observation."""
        return self._problem(free_kids, fixed_kids, tracks).prob

    def _problem(self, free, fixed, tracks, gcp_priors: bool = True, hold_gauge: bool = True) -> _Problem:
        """problem() with what maps its observations back to the keyframes; `prob` is None when
        there is no observation."""
        kids = list(free) + list(fixed)
        col = {k: j for j, k in enumerate(kids)}
        tracks = np.asarray(tracks, dtype=np.int64).ravel()
        tracks = tracks[self.points.contains_many(tracks)].tolist()
        slot, kid, oi = self._gather(tracks, kids)
        fixed_mask = np.array([k not in set(free) for k in kids])
        if len(slot) == 0:
            return _Problem(None, kids, tracks, slot, kid, oi, fixed_mask, [])
        if hold_gauge and not self.georeferenced and not fixed_mask.any():
            fixed_mask[:2] = True     # gauge: no datum yet, hold the first two keyframes
        gk = [j for j, k in enumerate(kids) if self.georeferenced and not fixed_mask[j]
              and self.kfs[k].fix_enu is not None and k not in self.gnss_rejected]
        pri = [(s, self.control[self.target_name(t)]) for s, t in enumerate(tracks)
               if t < 0 and not self.is_check(t) and not self.is_tie(t)] if self.georeferenced and gcp_priors else []
        obs_pt = np.concatenate([slot[kid == k] for k in kids])
        tie_slots = [s for s, t in enumerate(tracks) if self.is_tie(t)]
        gcp_slots = [s for s, _ in pri]
        scale = None
        if tie_slots or gcp_slots:
            scale = np.full(len(obs_pt), self.opt.loss_scale_px)
            scale[np.isin(obs_pt, tie_slots)] = self.opt.mtp_loss_scale_px
            scale[np.isin(obs_pt, gcp_slots)] = self.opt.gcp_loss_scale_px
        prob = BundleProblem(
            camera=self.camera, map_T_cams=np.array([self.kfs[k].map_T_cam for k in kids]),
            points_map=self.points.get_many(tracks).reshape(-1, 3),
            obs_cam=np.concatenate([np.full(int(np.sum(kid == k)), col[k]) for k in kids]),
            obs_pt=obs_pt, obs_uv=np.concatenate([self.kfs[k].uv[oi[kid == k]] for k in kids]),
            obs_loss_scale_px=scale,
            fixed_cams=fixed_mask, fixed_points=None,
            gnss_cam=np.array(gk, int) if gk else None,
            gnss_pos_map=np.array([self._gnss_target(self.kfs[kids[j]]) for j in gk]).reshape(-1, 3),
            gnss_cov_map=np.array([self._fix_cov_used(self.kfs[kids[j]]) for j in gk]).reshape(-1, 3, 3),
            lever_arm_cam_m=self._lever,
            point_priors_idx=np.array([s for s, _ in pri], int) if pri else None,
            point_priors_map=np.array([c.map_xyz for _, c in pri]).reshape(-1, 3),
            point_priors_sigma_m=np.array([c.sigma_m for _, c in pri]).reshape(-1, 3))
        return _Problem(prob, kids, tracks, slot, kid, oi, fixed_mask, gk)

    def _solve(self, free: list[int], fixed: list[int], tracks, iterations: int, refine: tuple = (),
               gnss_bias: bool = False, gnss_tilt: bool = False) -> StepReport:
        """Adjust keyframes `free` (beside `fixed`, held) and `tracks`; refine: the intrinsics self-calibrated;
        gnss_bias: the fixes' common offset as 3 more unknowns, added to `gnss_bias_enu` (only GCPs then hold the
        block's position: the caller makes sure they do); gnss_tilt: with it, the tilt of the fixes' heights as
        2 more, taken into `gnss_slope` (the caller makes sure GCPs spread to hold it). Observations left beyond
        `max_reprojection_px` are removed (hand-measured ones kept)."""
        b = self._problem(free, fixed, tracks)
        kids, tracks, slot, kid, oi, fixed_mask, gk = b.kids, b.tracks, b.slot, b.kid, b.oi, b.fixed_mask, b.gnss_cams
        if b.prob is None:
            return StepReport(kids[-1] if kids else -1, True, 'nothing_to_adjust')
        prob = b.prob
        gnss_tilt = gnss_bias and gnss_tilt and prob.gnss_cam is not None and len(prob.gnss_cam) >= 3
        if gnss_tilt:
            if not self.gnss_slope.any():
                self._gnss_slope_centre = np.mean(np.asarray(prob.gnss_pos_map, float)[:, :2], axis=0)
            prob = replace(prob, gnss_tilt_centre_m=self._gnss_slope_centre)
        t0 = time.monotonic()
        res = _adjust(prob, self.opt.loss, self.opt.loss_scale_px, iterations, refine, gnss_bias, gnss_tilt)
        if res.gnss_bias_enu_m is not None and res.status != 'failed':
            self.gnss_bias_enu = self.gnss_bias_enu + res.gnss_bias_enu_m
            if res.gnss_tilt is not None:
                # The fixes' heights adjusted: less the tilt . (EN - centre); `_gnss_target` adds gnss_slope . (EN - centre).
                self.gnss_slope = self.gnss_slope - res.gnss_tilt
                self.gnss_tilt_estimated = True
        self.solves.append({'iterations': int(res.iterations), 'status': res.status,
                            's': round(time.monotonic() - t0, 2)})
        if refine and res.status != 'failed':
            self.camera = res.camera   # self-calibration: every later step uses the refined intrinsics
        for j, k in enumerate(kids):
            if not fixed_mask[j]:
                self.kfs[k].map_T_cam = np.asarray(res.map_T_cams[j])
        if tracks:
            self.points.set_many(tracks, np.asarray(res.points_map))
        # Observations the robust loss down-weighted past the threshold are outliers: remove them.
        err = _reprojection_errors_px(self.camera, self._poses_of(kid), np.asarray(res.points_map)[slot], prob.obs_uv)
        bad = ~(err <= self.opt.max_reprojection_px)
        if res.status == 'failed' or np.median(err[np.isfinite(err)]) > self.opt.max_reprojection_px:
            bad[:] = False   # not converged: residuals say nothing about outliers yet
        for k, i, s in zip(kid[bad], oi[bad], slot[bad]):
            t = tracks[s]
            if self._hand_measured(t):
                continue   # a GCP's or an MTP's observation is measured by hand: keep it
            self._deactivate(int(k), int(i), int(t))
        good = ~bad
        rep = StepReport(kids[0], True, res.status, cost=float(res.final_cost),
                         reprojection_rms_px=float(np.sqrt(np.mean(err[good] ** 2))) if good.any() else float('nan'),
                         window_size=int((~fixed_mask).sum()))
        rep.gnss_rms_m = self.gnss_rms_m([kids[j] for j in gk])
        return rep

    def centre_covariance(self, free_kids: list[int]) -> dict:
        """Marginal covariance of the camera centres of keyframes `free_kids`, as the solver computes it
        for their window problem at the current estimate (zero iterations): the free keyframes' points
        in every registered keyframe that sees them (the others held, at most max_fixed_keyframes of
        them, most shared points first) and the free keyframes' GNSS priors; no GCP priors and no
        gauge hold, unlike `problem`. Returns {keyframe id: (3, 3) map ENU m^2}, or {} when the
        problem is singular or empty."""
        free = [k for k in free_kids if self.kfs[k].map_T_cam is not None]
        tracks = np.unique(np.concatenate([self._kf_tracks(k) for k in free] or [np.zeros(0, np.int64)]))
        if len(free) == 0 or len(tracks) == 0:
            return {}
        # track_kfs, not a scan of every keyframe: old ones may be on disk
        fixed = neighbour_keyframes(free, tracks, self.track_kfs, self.opt.max_fixed_keyframes)
        prob = self._problem(free, fixed, tracks, gcp_priors=False, hold_gauge=False).prob
        res = bundle_adjust(prob, BundleOptions(loss=self.opt.loss, loss_scale_px=self.opt.loss_scale_px,
                                                max_iterations=0, compute_covariance=True))
        if res.cam_centre_cov is None:
            return {}
        return {k: np.asarray(res.cam_centre_cov[j]) for j, k in enumerate(free)}

    def _gate_fix(self, kf: Keyframe) -> bool:
        """A new keyframe oriented from the block's tie points, whose fix lies far beyond its sigma
        (and `gnss_gate_m`) from where the block puts it, keeps its fix out of the adjustment when the
        photos contradict the fix (a glitched geotag: weighted as stated it would drag the block after it).
        Far from the resection alone is not enough: a pose the window's tie points hold loosely (the first
        photo of a line) can be metres off where its fix is right, and a keyframe without its fix carries
        that error on to the next one, each registered from the last, so the block would leave its GNSS
        for good. A far fix is therefore tried in the window adjustment (`_fix_trial`, nothing written):
        it stays in when the adjusted camera comes within the gate of it without its tie points' errors
        growing. True when rejected."""
        if kf.fix_enu is None or kf.map_T_cam is None:
            return False
        if not self._fix_far(kf, kf.map_T_cam):
            return False
        if self._fix_trial(kf):
            return False
        self.gnss_rejected.add(kf.kid)
        return True

    def _fix_far(self, kf: Keyframe, map_T_cam: np.ndarray, about_m=None) -> bool:
        """The antenna of a camera at `map_T_cam` lies further from kf's fix (plus `about_m`, ENU m, when
        given) than the gate: on some axis beyond 2 x gnss_outlier_sigma of the fix's sigma (scaled by
        the estimated noise) and gnss_gate_m."""
        d = self._antenna_residual(kf, map_T_cam) - (0.0 if about_m is None else np.asarray(about_m, float))
        sig = np.sqrt(np.diag(self._fix_cov_used(kf)))
        return bool((np.abs(d) > np.maximum(self.opt.gnss_outlier_sigma * 2.0 * sig, self.opt.gnss_gate_m)).any())

    def _antenna_residual(self, kf: Keyframe, map_T_cam: np.ndarray) -> np.ndarray:
        """Antenna of a camera at `map_T_cam` minus kf's fix as adjusted (bias taken off), ENU m."""
        return map_T_cam[:3, 3] + map_T_cam[:3, :3] @ self._lever - self._gnss_target(kf)

    def _fix_trial(self, kf: Keyframe) -> bool:
        """The window adjustment of keyframe kf with its fix in, solved without writing anything back: True
        when the photos agree with the fix: kf's adjusted antenna comes within the gate (`_fix_far`) of its
        fix as the window's other fixes lie from theirs (their median residual: a block that is not yet
        self-calibrated can sit off its GNSS by a common amount, which says nothing about one geotag), and
        the median reprojection error of kf's observations stays within max(2 x, + 1 px) of the
        resection's and within max_reprojection_px."""
        sel = self._window_selection()
        b = self._problem(sel.free_kfs, sel.fixed_kfs, sel.track_ids)
        if b.prob is None or kf.kid not in b.kids:
            return False
        prob = b.prob
        j = b.kids.index(kf.kid)
        mine = np.asarray(prob.obs_cam) == j
        if not mine.any():
            return False
        res = _adjust(prob, self.opt.loss, self.opt.loss_scale_px, self.opt.window_iterations)
        if res.status == 'failed':
            return False
        T = np.asarray(res.map_T_cams)
        others = [self._antenna_residual(self.kfs[b.kids[i]], T[i]) for i in b.gnss_cams if i != j]
        about = np.median(others, axis=0) if others else None
        before = _reprojection_errors_px(self.camera, np.asarray(prob.map_T_cams)[prob.obs_cam[mine]],
                                         np.asarray(prob.points_map)[prob.obs_pt[mine]], prob.obs_uv[mine])
        after = _reprojection_errors_px(self.camera, T[prob.obs_cam[mine]],
                                        np.asarray(res.points_map)[prob.obs_pt[mine]], prob.obs_uv[mine])
        med0, med1 = float(np.nanmedian(before)), float(np.nanmedian(after))
        return (not self._fix_far(kf, T[j], about) and np.isfinite(med1)
                and med1 <= min(max(2.0 * med0, med0 + 1.0), self.opt.max_reprojection_px))

    def _fix_cov_used(self, kf: Keyframe) -> np.ndarray:
        """The fix's covariance (ENU m^2) scaled by the flight's estimated GNSS noise."""
        S = np.diag(self.gnss_sigma_scale_hv[[0, 0, 1]])
        return S @ np.asarray(kf.fix_cov, float).reshape(3, 3) @ S

    def _raw_height_residuals(self, kids: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Vertical residuals (m) of the adjusted antennas against the fixes' own heights (no slope taken
        out), and the fixes' horizontal positions about the slope centre (K, 2), of keyframes `kids`."""
        r = self.gnss_residuals(kids)
        x = np.array([self.kfs[k].fix_enu[:2] - self.gnss_bias_enu[:2] - self._gnss_slope_centre for k in r])
        x = x.reshape(-1, 2)
        dz = np.array([r[k][2] for k in r]) + x @ self.gnss_slope
        return dz, x

    def _flight_plane_sigma(self, kids: list[int]) -> float:
        """`flight_plane_sigma` of the fixes of keyframes `kids`."""
        return flight_plane_sigma(np.array([self.kfs[k].fix_enu for k in kids]))

    def _level_block(self, kids: list[int]) -> dict | None:
        """The block's tilt, from the fixes' heights and from the cameras looking down, each as good as
        it is: the slope of the fixes' heights across the block (what the GNSS says of the tilt) has the
        uncertainty of their vertical scatter about a block that looks down (`_clipped_sigma`, at least 2 cm) over
        their horizontal spread, as many independent heights as their correlation from photo to photo leaves; the mean optical axis of a nadir flight is vertical
        within `NADIR_PRIOR_DEG`. Their weighted mean is the tilt kept: the block is turned to it about
        its cameras' centre and the rest of the fixes' slope taken out of their heights (`gnss_slope`).

        Only with `assume_nadir`, a block whose mean axis looks down, and fewer than 3 GCPs (which fix the
        tilt themselves). Returns {'gnss_tilt_deg', 'kept_tilt_deg', 'turned_deg',
        'scatter_v_m'} when the block was turned by more than 0.05 degrees, else None."""
        if not self.opt.assume_nadir or self._n_gcps() >= 3 or len(kids) < self.opt.gnss_noise_min_keyframes:
            return None
        axes = np.array([self.kfs[k].map_T_cam[:3, 2] for k in self.registered])
        m = axes.mean(axis=0)
        m = m / np.linalg.norm(m)
        if m[2] > -0.1:
            return None     # cameras that look at or above the horizon: not a block that looks down
        if not self.gnss_slope.any():
            fixes = np.array([self.kfs[k].fix_enu[:2] - self.gnss_bias_enu[:2] for k in kids])
            self._gnss_slope_centre = fixes.mean(axis=0)
        b = m[:2] / -m[2]                       # the block's slope (dz/dE, dz/dN) as its cameras look
        dz, x = self._raw_height_residuals(kids)
        g = b - self.gnss_slope                 # the slope the fixes' own heights give the block
        # The fixes' heights about a block that looks down: their residuals with the block's slope out.
        lev = dz - x @ b
        n = len(lev)
        scatter = _clipped_sigma(lev - np.median(lev)) * np.sqrt(n / max(n - 3.0, 1.0))
        sig_v = max(scatter, 0.02)
        xc = x - x.mean(axis=0)
        # Heights that wander are correlated from photo to photo: about the slope they give the block, their
        # lag-one correlation in flight order makes fewer independent heights, (1 - rho) / (1 + rho) of them.
        fit = dz - x @ self.gnss_slope
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
        c0 = np.mean([self.kfs[k].map_T_cam[:3, 3] for k in self.registered], axis=0)
        for k in self.registered:
            T = np.array(self.kfs[k].map_T_cam, float)
            self.kfs[k].map_T_cam = make_T(R @ T[:3, :3], R @ (T[:3, 3] - c0) + c0)
        ids, P = self.points.arrays()
        if len(ids):
            self.points.set_many(ids, (np.asarray(P) - c0) @ R.T + c0)
        self.gnss_slope = p - g
        return out

    def estimate_gnss_noise(self, iterations: int | None = None, refine_intrinsics: tuple = ()) -> dict:
        """The flight's GNSS noise from the residuals of the fixes (a variance-component estimate,
        horizontal and vertical apart, robust: median absolute deviations about the median, corrected
        for the 7 datum parameters the fixes also carry; the vertical one against the fixes' own heights,
        their trend across the block included). Where it exceeds the stated sigmas by half again, the
        fixes are weighted by it and the block adjusted again, and the block's tilt is taken from the
        fixes' heights and from its cameras looking down, each by its weight (`_level_block`), until both
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
            r = self.gnss_residuals()
            if len(r) < self.opt.gnss_noise_min_keyframes or not self.georeferenced:
                if self.gnss_rejected:
                    self.gnss_noise = {**self.gnss_noise,
                                       'rejected': [self.kfs[k].name for k in sorted(self.gnss_rejected)]}
                return self.gnss_noise
            kids = list(r)
            R = np.array([r[k] for k in kids])
            stated = np.array([np.sqrt(np.mean([np.mean(np.diag(self.kfs[k].fix_cov)[:2]) for k in kids])),
                               np.sqrt(np.mean([self.kfs[k].fix_cov[2, 2] for k in kids]))])
            n = len(kids)
            redundancy = np.sqrt(3.0 * n / max(3.0 * n - 7.0, 1.0))
            h = R[:, :2] - np.median(R[:, :2], axis=0)
            dz, _ = self._raw_height_residuals(kids)
            v = dz - np.median(dz)
            est = redundancy * np.array([_clipped_sigma(h.ravel()), _clipped_sigma(v)])
            used = stated * self.gnss_sigma_scale_hv
            want = np.where(est > 1.5 * stated, est / stated, 1.0)
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
            settled = bool(np.all(np.abs(stated * want - used) <= 0.1 * used))
            turned = self._level_block(kids) if rnd < 5 else None
            if turned is not None:
                level = {**turned, 'turned_deg': turned['turned_deg'] + (level or {}).get('turned_deg', 0.0)}
                out['level'] = level
            if settled and turned is None:
                break
            self.gnss_sigma_scale_hv = want
            self._solve(list(self.registered), [], list(self.points), iters, refine)
        # Outliers: far beyond the noise the flight shows, and beyond what the fixes state. Fixes kept out in
        # flight (`_gate_fix`, `_try_georeference`) are judged again against the adjusted block: a block that
        # drifted in flight may have put good fixes out.
        if out:
            kept = self.gnss_residuals([k for k in self.registered if k not in self.gnss_rejected])
            med = np.median(np.array(list(kept.values())), axis=0)
            r = self.gnss_residuals()
            kids = list(r)
            R = np.array([r[k] for k in kids]) - med
            sig = np.array([max(out['estimated_h_m'], out['stated_h_m'] * 0.5),
                            max(out['estimated_v_m'], out['stated_v_m'] * 0.5)])
            h = np.linalg.norm(R[:, :2], axis=1) / np.sqrt(2)
            dev = np.maximum(h / sig[0], np.abs(R[:, 2]) / sig[1])
            floor = np.maximum(h / out['stated_h_m'], np.abs(R[:, 2]) / out['stated_v_m'])
            bad = np.flatnonzero((dev > self.opt.gnss_outlier_sigma) & (floor > 3.0))
            bad = bad[np.argsort(-dev[bad])][:len(kids) // 5]
            rejected = {kids[i] for i in bad}
            if rejected != self.gnss_rejected:
                self.gnss_rejected = rejected
                self._solve(list(self.registered), [], list(self.points), iters, refine)
                # The fixes back in (or out) move the heights' slope: levelled again.
                for _ in range(4):
                    turned = self._level_block(list(self.gnss_residuals()))
                    if turned is None:
                        break
                    level = {**turned, 'turned_deg': turned['turned_deg'] + (level or {}).get('turned_deg', 0.0)}
                    self._solve(list(self.registered), [], list(self.points), iters, refine)
            if level is not None:
                axes = np.mean([self.kfs[k].map_T_cam[:3, 2] for k in self.registered], axis=0)
                level['kept_tilt_deg'] = float(np.degrees(np.arccos(np.clip(-axes[2] / np.linalg.norm(axes), -1, 1))))
                out['level'] = level
            out['rejected'] = [self.kfs[k].name for k in sorted(self.gnss_rejected)]
        self.gnss_noise = out
        return out

    def _gnss_target(self, kf: Keyframe) -> np.ndarray:
        """The fix moved so that `C + map_R_cam @ lever` should meet it (exact offset when known)."""
        fix = kf.fix_enu - self.gnss_bias_enu
        if self.gnss_slope.any():
            fix = fix + np.array([0.0, 0.0, float(self.gnss_slope @ (fix[:2] - self._gnss_slope_centre))])
        if kf.antenna_offset is None:
            return fix
        return fix - kf.antenna_offset + kf.map_T_cam[:3, :3] @ self._lever

    def gnss_residuals(self, kids=None) -> dict:
        """Keyframe id -> ENU residual (m) of the adjusted antenna position minus the fix."""
        out = {}
        for k in (self.registered if kids is None else kids):
            kf = self.kfs[k]
            if kf.fix_enu is not None and kf.map_T_cam is not None:
                out[k] = kf.map_T_cam[:3, 3] + kf.map_T_cam[:3, :3] @ self._lever - self._gnss_target(kf)
        return out

    def gnss_rms_m(self, kids=None) -> float:
        r = list(self.gnss_residuals(kids).values())
        return float(np.sqrt(np.mean(np.sum(np.array(r) ** 2, axis=1)))) if r else float('nan')

    def _kf_tracks(self, k: int) -> np.ndarray:
        kf = self.kfs[k]
        t = kf.track_ids[kf.active]
        return t[self.points.contains_many(t)].astype(np.int64)

    def _window_selection(self):
        """The window of the newest registered keyframes and the older ones held fixed with them
        (core/window.py select_window)."""
        return select_window(self.registered, self.opt.window_size,
                             {k: self._kf_tracks(k) for k in self.registered[-self.opt.window_size:]},
                             self.track_kfs, self.opt.max_fixed_keyframes)

    def _window_adjust(self, kid: int, full: bool = False, iterations: int | None = None) -> StepReport:
        if full:
            return self.full_adjustment(iterations=self.opt.full_iterations, rounds=1, gnss_noise=False)
        sel = self._window_selection()
        rep = self._solve(sel.free_kfs, sel.fixed_kfs, sel.track_ids,
                          self.opt.window_iterations if iterations is None else iterations)
        rep.kid = kid
        return rep

    def seed(self, records: list, map_T_cam: dict, point_ids, points_map_m, target_uv: dict,
                        gate_px: float | None = None) -> dict:
        """Make this empty adjuster hold the merged block, ready for its `full_adjustment`.

        records: core/incremental.py KeyframeRecord of every photo of the block (in order); map_T_cam: photo name
        -> (4, 4) merged pose (map ENU, camera to map; a photo without one is a keyframe not oriented);
        point_ids / points_map_m: (M,) track ids and (M, 3) map ENU m of the merged tie points; target_uv: photo
        name -> {target name: (u, v) px} of the GCP (and manual tie point) observations the adjustment takes
        (the records' own target_uv are not read). A merged point's observation in an oriented photo that
        reprojects further than `gate_px` (None: self.opt.max_reprojection_px x 2, as a new keyframe's check of the
        points it sees again) is left inactive; a point with fewer than 2 active observations left is not
        kept. The GCPs the observations name are intersected from the merged cameras (`triangulate_targets`).
        The block is georeferenced for good (the merged block is in the map frame of its sub-blocks' GNSS and
        GCPs). Returns {'keyframes', 'oriented', 'points', 'observations', 'observations_left_out', 'gcps'}.
        Keyframes come in as `add_keyframe` and `_register` would make them, with poses and points already known."""
        if self.kfs:
            raise DataError(f'seed needs an empty adjuster; it holds {len(self.kfs)} keyframes')
        if self.origin is None:
            raise DataError('seed needs an adjuster with its map origin (the block\'s)')
        if self.opt.spill_frozen:
            raise ConfigError('seed needs an adjuster with spill_frozen off: its keyframes do not come '
                              'through add_keyframe, which the freezing follows')
        ids_m = np.asarray(point_ids, np.int64).reshape(-1)
        P = np.asarray(points_map_m, float).reshape(-1, 3)
        if len(ids_m) != len(P):
            raise DataError(f'seed: {len(ids_m)} point ids but {len(P)} points')
        order = np.argsort(ids_m)
        ids_sorted, P_sorted = ids_m[order], P[order]
        gate_px = 2.0 * self.opt.max_reprojection_px if gate_px is None else float(gate_px)
        n_obs = n_out = 0
        for rec in records:
            ids = np.asarray(rec.track_ids, np.int64).ravel()
            uv = np.asarray(rec.uv, float).reshape(-1, 2)
            if len(ids) != len(uv):
                raise DataError(f'photo {rec.name}: {len(ids)} track ids but {len(uv)} pixel positions')
            tuv = target_uv.get(rec.name, {})
            if tuv:
                ids = np.concatenate([ids, [self._new_target_track(n) for n in tuv]])
                uv = np.vstack([uv, np.asarray(list(tuv.values()), float).reshape(-1, 2)])
            ids, first = np.unique(ids, return_index=True)
            uv = uv[first]
            fix_enu = fix_cov = None
            if rec.fix is not None:
                fix_enu = np.asarray(self.origin.geodetic_to_enu(rec.fix.lat_deg, rec.fix.lon_deg, rec.fix.h_m), float)
                fix_cov = np.asarray(rec.fix.cov_enu_m2, float).reshape(3, 3)
            active = np.ones(len(ids), bool)
            kf = Keyframe(len(self.kfs), int(rec.stamp_ns), rec.name or str(rec.stamp_ns), ids, uv,
                          self.camera.pixel_to_normalized(uv), active, fix_enu, fix_cov)
            if rec.antenna_offset_map_m is not None:
                kf.antenna_offset = np.asarray(rec.antenna_offset_map_m, float).reshape(3)
            self.kfs.append(kf)
            T = map_T_cam.get(kf.name)
            if T is None:
                continue
            kf.map_T_cam = np.array(T, float)
            kf.reg_seq = len(self.registered)
            self.registered.append(kf.kid)
            pos = np.clip(np.searchsorted(ids_sorted, ids), 0, max(len(ids_sorted) - 1, 0))
            has = (ids_sorted[pos] == ids) if len(ids_sorted) else np.zeros(len(ids), bool)
            if has.any():
                e = self.reprojection_px(kf.map_T_cam, P_sorted[pos[has]], uv[has])
                far = ~(e <= gate_px)
                active[np.flatnonzero(has)[far]] = False
                n_obs += int(has.sum())
                n_out += int(far.sum())
            for t in ids[active].tolist():
                self.track_kfs.setdefault(t, []).append(kf.kid)
        keep = np.array([len(self.track_kfs.get(int(t), ())) >= 2 for t in ids_m], bool)
        if keep.any():
            self.points.set_many(ids_m[keep], P[keep])
        self.georeferenced = True
        self.georef_provisional = False
        gcps = self.triangulate_targets(sorted({n for o in target_uv.values() for n in o}))
        return {'keyframes': len(self.kfs), 'oriented': len(self.registered), 'points': int(keep.sum()),
                'observations': n_obs, 'observations_left_out': n_out, 'gcps': gcps}

    def full_adjustment(self, iterations: int | None = None, rounds: int = 2,
                        refine_intrinsics: tuple = (), gnss_noise: bool = True,
                        stepwise: bool = False, gnss_bias: bool = True, tilt_test: bool = True) -> StepReport:
        """Adjust every registered keyframe and point; repeated so that removed outliers settle.

        refine_intrinsics (e.g. ('f', 'k1')) self-calibrates the shared camera in this adjustment and in
        the GNSS noise estimate's adjustments (the fixes weighted by their estimated noise); the GNSS
        bias's adjustments hold it (with the bias free, the GCPs alone fix the cameras' heights);
        stepwise: refine_intrinsics are candidates, of which `select_self_calibration` keeps those that pay;
        gnss_noise: estimate the flight's GNSS noise afterwards (`estimate_gnss_noise`, when the option
        is on and the block is georeferenced for good); such a final adjustment refines the option
        `final_self_calibration` when refine_intrinsics is not given (stepwise when it is "auto");
        gnss_bias: estimate the GNSS bias (when the option is on and 3 GCPs make it observable);
        tilt_test: with gnss_tilt "auto", test whether the tilt pays (`_tilt_tested`); else the last test's outcome
        stands.
        """
        if not refine_intrinsics and gnss_noise:
            refine_intrinsics = self.opt.final_refine
            stepwise = stepwise or self.opt.final_stepwise
        rep = StepReport(-1, False, 'not_initialised')
        if not self.registered:
            return rep
        if gnss_noise and self.gnss_bias_estimated:
            # The final adjustment estimates the bias afresh, after its own self-calibration and GNSS noise estimate:
            # the focal length and the bias's height trade off on a flat block, so one from the control adjustments
            # in flight (fixes weighted as stated, the lens held) would steer where the final one lands.
            self.gnss_bias_enu = np.zeros(3)
            self.gnss_bias_estimated = False
            if self.gnss_tilt_estimated:
                self.gnss_slope, self.gnss_tilt_estimated = np.zeros(2), False
        if not self.georeferenced and (self._georeference_short_block() or self._try_georeference(force=True)):
            rounds = max(rounds - 1, 1)
        if self._segment is not None and self._segment.registered:
            # End of flight (or asked for): a segment still waiting joins if its GNSS places it at all.
            self._segment.full_adjustment(iterations=iterations, rounds=1, gnss_noise=False)
            if self._segment_can_join():
                self._join_segment()
        if self.ties:
            self._retriangulate_ties()
        if stepwise and refine_intrinsics:
            refine_intrinsics = self.select_self_calibration(refine_intrinsics, iterations)
        for _ in range(rounds):
            tracks = list(self.points)
            rep = self._solve(list(self.registered), [], tracks, iterations or self.opt.full_iterations,
                              refine_intrinsics)
        if gnss_noise and self.opt.estimate_gnss_noise and self.georeferenced and not self.georef_provisional:
            self.estimate_gnss_noise(iterations, refine_intrinsics)
        self._full_adjusted_n = len(self.registered)
        if gnss_bias and self.opt.estimate_gnss_bias and self._n_gcps() >= 3 and self.opt.bias_iterations:
            self.gnss_bias_estimated = True
            mode = self.opt.gnss_tilt if tilt_test or self.opt.gnss_tilt != 'auto' else (
                'always' if self.gnss_tilt_estimated else 'never')
            tilt = mode != 'never' and self._gnss_tilt_observable()
            if tilt and mode == 'auto':
                rep, settle = self._tilt_tested(iterations, rep)
            else:
                rep, settle = self._bias_rounds(iterations, tilt, rep)
            self.gnss_bias_rounds = settle
        if self.opt.spill_frozen:
            self.freeze()   # the adjustment read every keyframe back: spill the frozen ones again
        return rep

    def _bias_rounds(self, iterations: int | None, tilt: bool, rep: StepReport) -> tuple[StepReport, dict]:
        """Full adjustments with the GNSS bias (and the tilt) as unknowns until the bias settles: (the last
        solve's report, `rep` when none ran; {'settled', 'rounds', 'last_step_m'}, empty when no camera has a
        fix)."""
        # The bias is 3 unknowns of the adjustment beside the poses and points (the intrinsics held): one solve
        # finds it; each solve then removes the observations it leaves as outliers, which can move it again.
        settled, rounds, step = False, 0, np.zeros(3)
        if not tilt:
            self.gnss_tilt_estimated = False
        for i in range(self.opt.bias_iterations if self.gnss_residuals() else 0):
            before = self.gnss_bias_enu.copy()
            rep = self._solve(list(self.registered), [], list(self.points), iterations or self.opt.full_iterations,
                              gnss_bias=True, gnss_tilt=tilt)
            step = self.gnss_bias_enu - before
            rounds = i + 1
            if rep.status == 'failed':
                break
            if i and np.linalg.norm(step) < 0.001:
                settled = True
                break
        return rep, ({'settled': settled, 'rounds': rounds, 'last_step_m': float(np.linalg.norm(step))}
                     if rounds else {})

    def _tilt_tested(self, iterations: int | None, rep: StepReport) -> tuple[StepReport, dict]:
        """gnss_tilt "auto": the bias alone, then with the tilt; the tilt is kept when it lowers the GCPs' height
        residuals (intersected from the adjusted cameras) by more than chance: F = ((RSS_bias - RSS_tilt) / 2) /
        (RSS_tilt / (n - 3)) above its TILT_TEST_LEVEL quantile with (2, n - 3) degrees of freedom, n GCPs used in
        height (at least 4). Otherwise the bias is adjusted alone again from where the tilt left the block."""
        from scipy.stats import f as f_dist
        rep, settle = self._bias_rounds(iterations, False, rep)
        rss0, n = self._gcp_height_rss()
        if n < 4:
            self.gnss_tilt_test = {}
            return rep, settle
        slope, centre = self.gnss_slope.copy(), self._gnss_slope_centre.copy()
        rep_t, settle_t = self._bias_rounds(iterations, True, rep)
        rss1, _ = self._gcp_height_rss()
        f = (rss0 - rss1) / 2.0 / max(rss1 / (n - 3), 1e-12)
        f_crit = float(f_dist.ppf(TILT_TEST_LEVEL, 2, n - 3))
        kept = bool(rep_t.status != 'failed' and f > f_crit)
        self.gnss_tilt_test = {'gcps': n, 'rss_bias_m2': float(rss0), 'rss_tilt_m2': float(rss1), 'f': float(f),
                               'f_crit': f_crit, 'kept': kept}
        if kept:
            return rep_t, settle_t
        self.gnss_slope, self._gnss_slope_centre = slope, centre
        return self._bias_rounds(iterations, False, rep)

    def _gcp_height_rss(self) -> tuple[float, int]:
        """(sum of squared height residuals, m^2, count) of the GCPs used in height, each intersected from the
        adjusted cameras minus its survey."""
        r = []
        for n in self._gcps_in_height():
            got = self.intersect_target(n)
            if got is not None:
                r.append(float(got[0][2] - self.control[n].map_xyz[2]))
        return float(np.sum(np.square(r))), len(r)

    def _gcps_in_height(self) -> list[str]:
        """The GCPs used whose heights the adjustment uses (not those used horizontally only: their vertical
        sigma is HORIZONTAL_ONLY_SIGMA_V_M)."""
        return sorted(n for n in self._gcp_names() if self.control[n].sigma_m[2] < 1.0)

    def select_self_calibration(self, candidates: tuple, iterations: int | None = None) -> tuple:
        """The stepwise self-calibration (core/self_calibration.py `select_stepwise`): which of `candidates`
        the block's final adjustment refines: f, cx and cy among them always (`SELF_CALIBRATION_BASE`), the
        distortion terms when they pay. The candidates start from the camera as given (a self-calibration
        made before is undone), and each trial adjusts one and the same problem (the block's active observations,
        the fixes at their current weights) with its intrinsics refined, from the result of the trial of the
        intrinsics kept so far (the first, none refined, from the block as it is). A trial is measured by the RMS
        of its reprojection residuals, each capped at `max_reprojection_px` (an outlier counts no more than that;
        an observation the lens's distortion moved that far counts in full once a model explains it), the
        refined values (and how far they moved from the given ones) with their sigmas and correlations with the
        block's height (asked only of a candidate that pays), and the cameras' bowl against their geotags' heights (`height_bowl`, at the block's
        radius). The block is left as it was (only the candidates back at their
        given values): the caller adjusts it with the kept intrinsics, along the same path as an explicit list
        of them. Returns them (also in `self.self_calibration`)."""
        iters = iterations or self.opt.full_iterations
        self.camera = _with_intrinsics_of(self.camera, self._camera_given, candidates)
        b = self._problem(list(self.registered), [], list(self.points))
        if b.prob is None:
            self.self_calibration = None
            return ()
        prob = b.prob

        results = {}
        given_by_name = _intrinsics_by_name(self._camera_given)

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
            err = _reprojection_errors_px(cam, T[prob.obs_cam], P[prob.obs_pt], prob.obs_uv)
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
        base = tuple(c for c in candidates if c in SELF_CALIBRATION_BASE)
        sel = select_stepwise(tuple(c for c in candidates if c not in base), evaluate, base=base,
                              min_gain_fraction=self.opt.self_calibration_min_gain,
                              min_gain_px=self.opt.self_calibration_min_gain_px, determine=determine)
        self.self_calibration = sel
        return sel.kept

    # --- memory: freezing what can no longer enter a window (core/at_freeze.py) --------------------

    def freeze(self) -> None:
        """Freeze the tracks and keyframes that can no longer enter a window; called every
        `freeze_every` keyframes (and after a full adjustment) when `spill_frozen`."""
        self._freezer.freeze(self.kfs, self.registered, self.track_kfs, self.points)

    def _thaw_tracks_seen_again(self, ids: np.ndarray) -> None:
        self._freezer.thaw_seen_again(ids, self.kfs, self.registered, self.track_kfs, self.points)

    def memory_stats(self) -> dict:
        """What the triangulation holds: keyframes/points in memory and frozen, bytes spilled."""
        return {'keyframes': len(self.kfs), 'keyframes_in_memory': sum(not kf.frozen for kf in self.kfs),
                'points': len(self.points), 'points_in_memory': self.points.n_hot,
                'hot_tracks': len(self.track_kfs), 'frozen_points_mb': round(self.points.frozen_bytes / 1e6, 2),
                'spilled_mb': round(self._freezer.spilled_bytes / 1e6, 2),
                'freezing_stopped': self.freezing_stopped}

    def set_control(self, control: list[ControlPoint]) -> None:
        """Surveyed targets in this block's map frame; may come after the first keyframes (a flight
        knows its origin only from the first fix): roles are looked up at every adjustment."""
        self.control = {c.name: c for c in control}

    def control_summary(self) -> dict:
        """GCPs and check points: how many were observed, how many GCPs constrain the block (triangulated,
        with their prior: georeferenced), and the RMS of the adjusted GCPs minus their survey (m)."""
        seen = [n for n in self._target_ids if n in self.control]
        gcps = [n for n in seen if not self.is_check(self._target_ids[n])]
        used = [n for n in gcps if self._target_ids[n] in self.points] if self.georeferenced else []
        r = np.array([self.points[self._target_ids[n]] - self.control[n].map_xyz for n in used]).reshape(-1, 3)
        n_gcps = sum(c.role == 'gcp' for c in self.control.values()) if self.opt.use_gcps else 0
        out = {'gcps': n_gcps, 'gcps_seen': len(gcps), 'gcps_used': len(used), 'checks_seen': len(seen) - len(gcps),
               'gcp_residual_rms_h_m': float('nan'), 'gcp_residual_rms_v_m': float('nan')}
        if len(r):
            out['gcp_residual_rms_h_m'] = float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1))))
            out['gcp_residual_rms_v_m'] = float(np.sqrt(np.mean(r[:, 2] ** 2)))
        return out

    def triangulate_targets(self, names) -> list[str]:
        """Points for the GCPs among `names` from their active observations in the registered keyframes:
        a target held as a check point builds no geometry, so a GCP admitted later (in flight, once its
        survey agrees with the block) gets its point, and its prior, here. Returns the names with a point."""
        tids = [self._target_ids[n] for n in names if n in self._target_ids]
        self._triangulate_tracks([t for t in tids if not self.is_check(t) and t not in self.points])
        return [n for n in names if self._target_ids.get(n) in self.points]

    def drop_target_observation(self, kid: int, name: str) -> bool:
        """Take keyframe `kid`'s observation of target `name` out of the adjustment (a detection the
        control vetting rejected); False when the keyframe has none."""
        tid = self._target_ids.get(name)
        i = self.kfs[kid].index(tid) if tid is not None and 0 <= kid < len(self.kfs) else None
        if i is None:
            return False
        self._deactivate(kid, i, tid)
        return True

    def fix_sigma_enu_m(self) -> np.ndarray:
        """(3,) E, N, U sigma (m) of the oriented keyframes' fixes, the median: how well the GNSS alone
        places the block (10 m each without a fix)."""
        cov = [self.kfs[k].fix_cov for k in self.registered if self.kfs[k].fix_cov is not None]
        if not cov:
            return np.full(3, 10.0)
        return np.sqrt(np.median([np.diag(c) for c in cov], axis=0))

    def _gnss_tilt_observable(self) -> bool:
        """gnss_tilt is not "never" and the GCPs used in height spread over the block in every direction: along
        any horizontal direction u, their RMS about their centre is at least gnss_tilt_min_spread times the
        fixes' (the smallest generalised eigenvalue of the two 2x2 scatter matrices); GCPs on one line never."""
        if self.opt.gnss_tilt == 'never':
            return False
        names = self._gcps_in_height()
        fixes = np.array([self.kfs[k].fix_enu[:2] for k in self.registered
                          if self.kfs[k].fix_enu is not None and k not in self.gnss_rejected]).reshape(-1, 2)
        if len(names) < 3 or len(fixes) < 3:
            return False
        g = np.array([self.control[n].map_xyz[:2] for n in names], float)
        cg, cf = np.cov((g - g.mean(axis=0)).T, bias=True), np.cov((fixes - fixes.mean(axis=0)).T, bias=True)
        if np.linalg.eigvalsh(cf)[0] < 1.0:
            return False     # the fixes on one line: no lean across it to find
        return bool(scipy.linalg.eigh(cg, cf, eigvals_only=True)[0] >= self.opt.gnss_tilt_min_spread ** 2)

    def _gcp_names(self) -> frozenset:
        """The GCPs the adjustment uses: targets triangulated in the block that are not check points."""
        return frozenset(n for n, t in self._target_ids.items() if t in self.points and not self.is_check(t))

    def _n_gcps(self) -> int:
        return len(self._gcp_names())

    # --- results ----------------------------------------------------------------------------------

    def poses(self) -> dict[int, np.ndarray]:
        return {k: self.kfs[k].map_T_cam for k in self.registered}

    def keyframe_points(self, kid: int) -> np.ndarray:
        """(N, 3) map ENU (m) of the tie points keyframe `kid` observes (active observations)."""
        return self.points.get_many(self._kf_tracks(kid)).reshape(-1, 3)

    def observations_of(self, tid: int):
        """(map_T_cams, uv) of one track in the registered keyframes (active or not)."""
        Ts, uvs = [], []
        for k in self.registered:
            kf = self.kfs[k]
            i = kf.index(tid)
            if i is not None:
                Ts.append(kf.map_T_cam)
                uvs.append(kf.uv[i])
        return Ts, np.array(uvs).reshape(-1, 2)

    def intersect_target(self, name: str):
        """Triangulate a target (check point) from the adjusted cameras: (xyz, n_images, rms_px)."""
        tid = self._target_ids.get(name)
        if tid is None:
            return None
        Ts, uv = self.observations_of(tid)
        if len(Ts) < 2:
            return None
        return intersect_point(self.camera, np.array(Ts), uv)


def _names(text: str) -> tuple:
    """A comma-separated list of names as a tuple (blanks dropped)."""
    return tuple(v.strip() for v in text.split(',') if v.strip())


def _with_intrinsics_of(camera: PinholeCamera, given: PinholeCamera, names) -> PinholeCamera:
    """`camera` with the intrinsics `names` ('f', 'cx', 'cy', 'k1', 'k2', 'p1', 'p2', 'k3') taken from `given`."""
    kw = {}
    if 'f' in names:
        kw.update(fx=given.fx, fy=given.fy)
    kw.update({n: getattr(given, n) for n in ('cx', 'cy') if n in names})
    dist = [given.dist[i] if n in names else camera.dist[i] for i, n in enumerate(('k1', 'k2', 'p1', 'p2', 'k3'))]
    return replace(camera, dist=tuple(dist), **kw)


def reprojection_residuals_px(camera: PinholeCamera, map_T_cams: np.ndarray, uv: np.ndarray,
                              X_map: np.ndarray) -> np.ndarray:
    """(N, 2) pixels: the map point `X_map` (m) projected through the N cameras `map_T_cams` (camera to
    map), minus its observations `uv` (px, as measured: distorted)."""
    pc = np.einsum('nji,nj->ni', map_T_cams[:, :3, :3], X_map[None] - map_T_cams[:, :3, 3])
    return camera.normalized_to_pixel(pc[:, :2] / pc[:, 2:3]) - uv


def intersect_point(camera: PinholeCamera, map_T_cams: np.ndarray, uv: np.ndarray):
    """Multi-ray intersection refined by Gauss-Newton on the reprojection error (cameras fixed):
    (map point, m; number of rays; RMS of its reprojection residuals, px), or None."""
    xn = camera.pixel_to_normalized(uv)
    dirs = np.einsum('nij,nj->ni', map_T_cams[:, :3, :3], np.column_stack([xn, np.ones(len(xn))]))
    X = triangulate_rays(map_T_cams[:, :3, 3], dirs, np.zeros(len(xn), int), 1)[0]
    if not np.all(np.isfinite(X)):
        return None

    def res(X):
        return reprojection_residuals_px(camera, map_T_cams, uv, X).ravel()

    for _ in range(10):
        r = res(X)
        J = np.column_stack([(res(X + d) - r) / 1e-6 for d in np.eye(3) * 1e-6])
        dx = np.linalg.lstsq(J, -r, rcond=None)[0]
        X = X + dx
        if np.linalg.norm(dx) < 1e-7:
            break
    r = res(X).reshape(-1, 2)
    return X, len(uv), float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))
