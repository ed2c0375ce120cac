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

`IncrementalAT` keeps the order of work (register, triangulate, georeference, window, growth, control and
final adjustments); the state lives in its parts, each a module of its own:
- `block` (core/at_block.py): keyframes, points, targets, manual tie points, the shared camera, and the
  public queries every reader outside core/ uses;
- `datum` (core/gnss_datum.py): the lever arm, GNSS bias and tilt, sigma scale, rejected fixes;
- `adjustment` (core/at_problem.py): every adjustment is one `problem(free, fixed, tracks)` of the block, solved
  there; `centre_covariance` evaluates the marginal covariance of a window's camera centres from the same builder;
- `rounds` (core/gnss_rounds.py): the fix gate, the GNSS noise estimate, levelling, the bias and tilt rounds;
- `registration` (core/at_register.py) and `segments` (core/at_segments.py).

Memory on long flights (`spill_frozen`): what can no longer enter a window leaves the Python heap
(core/at_freeze.py); results are bit-identical to keeping everything.

Parameters: `IncrementalOptions`, the user-facing container (params.py; the bundle node's parameter set extends
it). Each part takes options of its own, made once from it (`IncrementalOptions.part`, core/part_options.py):
`BlockOptions` (with `FreezeOptions`), `ProblemOptions`, `RegistrationOptions` (with `TwoViewOptions`) and
`SegmentOptions`, `DatumOptions` and `GnssRoundsOptions`, each declaring its parameters' descriptions and ranges
next to the code that reads them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from photogram_ros.core.at_block import Block, BlockOptions, ControlPoint, KeyframeRecord
from photogram_ros.core.at_freeze import FreezeOptions
from photogram_ros.core.at_geometry import (intersect_point, lever_arm_cam_from_frd, reprojection_residuals_px,
                                            triangulate_rays)
from photogram_ros.core.at_problem import SELF_CALIBRATION_BASE, BlockAdjustment, ProblemOptions, StepReport
from photogram_ros.core.at_register import Registration, RegistrationOptions
from photogram_ros.core.at_segments import SegmentOptions, Segments
from photogram_ros.core.at_store import Keyframe
from photogram_ros.core.at_two_view import TwoViewOptions
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.gnss_datum import DatumOptions, GnssDatum
from photogram_ros.core.gnss_rounds import TILT_TEST_LEVEL, GnssRounds, GnssRoundsOptions, flight_plane_sigma
from photogram_ros.core.part_options import declared, options_for
from photogram_ros.core.self_calibration import INTRINSICS
from photogram_ros.core.similarity import similarity_on_line, similarity_ransac, spread
from photogram_ros.errors import ConfigError, DataError
from photogram_ros.params import param

# What other modules import from here (the adjuster's records, steps and geometry live in its parts' modules).
__all__ = ['AUTO_CANDIDATES', 'DISTORTION_TERMS', 'GNSS_TILT_MODES', 'PASS_GROWTH_RATIO', 'SELF_CALIBRATION_BASE',
           'TILT_TEST_LEVEL', 'ControlPoint', 'IncrementalAT', 'IncrementalOptions', 'KeyframeRecord', 'StepReport',
           'flight_plane_sigma', 'intersect_point', 'lever_arm_cam_from_frd', 'reprojection_residuals_px',
           'triangulate_rays']

# What final_self_calibration "auto" selects from, stepwise: the radial distortion of a camera from the EXIF.
AUTO_CANDIDATES = ('k1', 'k2')
# The lens distortion terms: what the incremental pass may refine (`pass_self_calibration`).
DISTORTION_TERMS = ('k1', 'k2', 'p1', 'p2', 'k3')
# growth_ratio for a camera whose distortion is refined in the pass (triangulate, replay of a photo folder): a
# geometric series of full adjustments costs about 3 of the final block's.
PASS_GROWTH_RATIO = 1.5
GNSS_TILT_MODES = ('never', 'auto', 'always')


@dataclass
class IncrementalOptions:
    """The aerial triangulation's parameters (ROS-free; nodes/bundle_node.py's set extends it)."""
    window_size: int = declared(ProblemOptions, 'window_size')
    max_fixed_keyframes: int = declared(ProblemOptions, 'max_fixed_keyframes')
    min_init_inliers: int = declared(RegistrationOptions, 'min_init_inliers')
    min_init_angle_deg: float = declared(RegistrationOptions, 'min_init_angle_deg')
    min_triangulation_angle_deg: float = declared(BlockOptions, 'min_triangulation_angle_deg')
    max_reprojection_px: float = declared(ProblemOptions, 'max_reprojection_px')
    pnp_threshold_px: float = declared(TwoViewOptions, 'pnp_threshold_px')
    min_pnp_inliers: int = declared(RegistrationOptions, 'min_pnp_inliers')
    relative_fallback: bool = declared(RegistrationOptions, 'relative_fallback')
    min_relative_inliers: int = declared(RegistrationOptions, 'min_relative_inliers')
    min_relative_inliers_gnss: int = declared(TwoViewOptions, 'min_relative_inliers_gnss')
    two_view_min_angle_deg: float = declared(TwoViewOptions, 'two_view_min_angle_deg')
    two_view_max_direction_deg: float = declared(TwoViewOptions, 'two_view_max_direction_deg')
    segments: bool = declared(SegmentOptions, 'segments')
    segment_min_tie_points: int = param(8, 'a segment joins the block through the tracker\'s tie points both have '
                                           'triangulated when a RANSAC similarity fits this many of them (and at '
                                           'least half), spread over an area', min=3, max=100000)
    loss: str = declared(ProblemOptions, 'loss')
    loss_scale_px: float = declared(ProblemOptions, 'loss_scale_px')
    mtp_loss_scale_px: float = declared(ProblemOptions, 'mtp_loss_scale_px')
    gcp_loss_scale_px: float = declared(ProblemOptions, 'gcp_loss_scale_px')
    window_iterations: int = declared(GnssRoundsOptions, 'window_iterations')
    full_iterations: int = declared(ProblemOptions, 'full_iterations')
    lever_arm_cam_m: list = declared(DatumOptions, 'lever_arm_cam_m')
    lever_arm_body_frd_m: list = declared(DatumOptions, 'lever_arm_body_frd_m')
    georef_min_keyframes: int = param(4, 'keyframes with a fix before the block is georeferenced', min=3, max=10000)
    georef_line_heading_deg: float = param(5.0, 'a straight first line georeferences provisionally (assume_nadir) '
                                                'once its fixes give the line\'s heading to this 1-sigma, deg: '
                                                'horizontal GNSS sigma / (the fixes\' RMS spread along the line x '
                                                'sqrt(their count)); with georef_line_min_keyframes of them over 5 m '
                                                'at least', min=0.1, max=90.0)
    georef_line_min_keyframes: int = param(6, 'keyframes with a fix a straight first line needs before it '
                                              'georeferences provisionally (assume_nadir; georef_line_heading_deg)',
                                           min=3, max=10000)
    georef_min_spread_ratio: float = param(0.05, 'the fixes must spread across their line by this fraction of '
                                                 'its length before the georeference is final (a turn)',
                                           min=0.0, max=1.0)
    assume_nadir: bool = declared(TwoViewOptions, 'assume_nadir')
    min_facing: float = declared(TwoViewOptions, 'min_facing')
    use_gcps: bool = declared(BlockOptions, 'use_gcps')
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
    gnss_tilt: str = declared(GnssRoundsOptions, 'gnss_tilt')
    gnss_tilt_min_spread: float = declared(GnssRoundsOptions, 'gnss_tilt_min_spread')
    bias_iterations: int = declared(GnssRoundsOptions, 'bias_iterations')
    estimate_gnss_noise: bool = param(True, 'the full adjustment estimates the flight\'s GNSS noise (horizontal and '
                                            'vertical apart) from its residuals and weights the fixes by it when '
                                            'they are poorer than they state; fixes far beyond it are not used')
    gnss_noise_min_keyframes: int = declared(GnssRoundsOptions, 'gnss_noise_min_keyframes')
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
    pass_min_keyframes: int = param(8, 'the pass refines its distortion (and adjusts on growth) once this many keyframes '
                                       'are oriented: the in-flight poses of a camera whose distortion nobody measured '
                                       '(the EXIF\'s) are turned by degrees until it is (seneca_part: k1 moves a '
                                       'corner 20 px; bench/georef_inflight.py)',
                                    min=2, max=1000000)
    off_gnss_sigma: float = param(0.0, 'in flight, a block georeferenced for good gets a full adjustment (the pass\'s) '
                                       'as soon as its window has left its GNSS: the newest keyframe\'s antenna '
                                       'further than this many sigmas of its fix on some axis, or the window\'s '
                                       'keyframes off their fixes by half of it on average along some axis; a sigma '
                                       'is the stated one times how poor the fixes were about the block at its last '
                                       'full adjustment, or as the datum weighs them, whichever is larger (the '
                                       'window holds the older keyframes, so a block turned or bent by a line\'s '
                                       'first photos stays so until the end of the flight without it); 0: never',
                                  min=0.0, max=1000.0)
    off_gnss_gap: int = param(2, 'keyframes between two such full adjustments, at least (doubled each time one '
                                 'leaves the window off its GNSS still)', min=1, max=100000)
    self_calibration_min_gain: float = declared(ProblemOptions, 'self_calibration_min_gain')
    self_calibration_min_gain_px: float = declared(ProblemOptions, 'self_calibration_min_gain_px')
    gnss_tighten: bool = declared(GnssRoundsOptions, 'gnss_tighten')
    gnss_tighten_floor_m: float = declared(GnssRoundsOptions, 'gnss_tighten_floor_m')
    gnss_gate_m: float = declared(GnssRoundsOptions, 'gnss_gate_m')
    gnss_outlier_sigma: float = declared(GnssRoundsOptions, 'gnss_outlier_sigma')
    # Long flights: keyframes and tracks that can no longer enter a window leave the Python heap
    # (points to compact arrays, keyframe observations to disk) so memory stays flat; a track id
    # seen again later brings them back, so results are the same either way (core/at_freeze.py).
    spill_frozen: bool = declared(BlockOptions, 'spill_frozen')
    spill_dir: str = declared(FreezeOptions, 'spill_dir')
    freeze_margin_keyframes: int = declared(FreezeOptions, 'freeze_margin_keyframes')
    freeze_every: int = param(5, 'keyframes between freeze passes', min=1, max=10000)
    max_thaws: int = declared(FreezeOptions, 'max_thaws')

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

    def part(self, cls):
        """The options of one part of the adjuster (`BlockOptions`, `ProblemOptions`, `RegistrationOptions`,
        `SegmentOptions`, ...: core/part_options.py), made from these values."""
        return options_for(cls, self)


def _read(part: str, name: str, doc: str) -> property:
    """A read-only view of `name` of the adjuster's part `part`."""
    return property(lambda self: getattr(getattr(self, part), name), doc=doc)


def _delegate(part: str, name: str):
    """The adjuster's method `name`, made by its part `part`."""
    def call(self, *args, **kwargs):
        return getattr(getattr(self, part), name)(*args, **kwargs)
    call.__name__ = name
    call.__doc__ = f'`{part}.{name}`: see there.'
    return call


class IncrementalAT:
    """The aerial triangulation's order of work; feed `add_keyframe`, call `full_adjustment` at the end. Its state
    is in its parts (see the module's doc): `block`, `datum`, `adjustment`, `rounds`, `registration`, `segments`."""

    def __init__(self, camera: PinholeCamera, options: IncrementalOptions | None = None,
                 origin: LocalFrame | None = None, control: list[ControlPoint] | None = None, ties=()):
        self.opt = options or IncrementalOptions()
        self.origin = origin
        self.block = Block(camera, self.opt.part(BlockOptions), control, ties)
        self.datum = GnssDatum(self.block, self.opt.part(DatumOptions))
        self.adjustment = BlockAdjustment(self.block, self.datum, self.opt.part(ProblemOptions))
        self.rounds = GnssRounds(self.block, self.datum, self.adjustment, self.opt.part(GnssRoundsOptions))
        self.registration = Registration(self.block, self.datum, self.opt.part(RegistrationOptions))
        self.segments = Segments(self.block, self.opt.part(SegmentOptions))
        self.history: list[StepReport] = []
        self.rng = np.random.default_rng(0)
        # Oriented keyframes at the last full adjustment (`growth_ratio`).
        self._full_adjusted_n = 0
        # The GCPs in the block at the last control adjustment (`control_adjustment`), by name.
        self._control_adjusted_gcps: frozenset = frozenset()
        # The last off-GNSS test of a window (`off_gnss`): its figures, for /diagnostics.
        self._off_gnss_last: dict = {}
        # Full adjustments the off-GNSS test asked for in flight.
        self.off_gnss_adjustments = 0
        self.block_adjustments_deferred = 0   # due full adjustments left for later: keyframes were waiting
        self._off_gnss_gap = self.opt.off_gnss_gap   # doubled while the adjustments leave the window off its GNSS
        # How poor the fixes were about the block at its last full adjustment in flight (GnssRounds.noise_factors_hv:
        # factors, horizontal and vertical, on their stated sigmas; at least 1): the off-GNSS test's yardstick.
        self._off_gnss_noise_hv = np.ones(2)

    # Read-only views of the parts' state: the flags and the self-calibration for the stages, the containers
    # (kfs, registered, points, ...) for the tests only; the package reads those through the parts' public
    # queries (at.block, at.datum, at.rounds; tests/test_code_shape.py).
    camera = _read('block', 'camera', 'The shared camera (refined by a self-calibration).')
    kfs = _read('block', 'kfs', 'Every keyframe (core/at_block.py).')
    registered = _read('block', 'registered', 'Ids of the oriented keyframes in order of registration.')
    points = _read('block', 'points', 'The tie points, {track id: map ENU m}.')
    track_kfs = _read('block', 'track_kfs', 'Hot tracks: their oriented keyframes.')
    control = _read('block', 'control', 'The surveyed targets by name.')
    ties = _read('block', 'ties', 'The manual tie points\' names.')
    georeferenced = _read('block', 'georeferenced', 'The block is in the map frame.')
    georef_provisional = _read('block', 'provisional', 'The georeference is provisional (a line: the roll about it).')
    gnss_bias_enu = _read('datum', 'bias_enu', 'The estimated GNSS bias, ENU m.')
    gnss_bias_estimated = _read('datum', 'bias_estimated', 'A full adjustment with >= 3 GCPs estimated the bias.')
    gnss_tilt_estimated = _read('datum', 'tilt_estimated', '... and the tilt of the fixes\' heights with it.')
    gnss_slope = _read('datum', 'slope', 'The slope taken out of the fixes\' heights (dz/dE, dz/dN).')
    gnss_sigma_scale_hv = _read('datum', 'sigma_scale_hv', 'Factors (horizontal, vertical) on the stated sigmas.')
    gnss_rejected = _read('datum', 'rejected', 'Keyframes whose fix is not used.')
    gnss_noise = _read('rounds', 'noise', 'The last GNSS noise estimate.')
    gnss_bias_rounds = _read('rounds', 'settle', 'How the last bias estimate ended.')
    gnss_tilt_test = _read('rounds', 'tilt_test', 'The "auto" tilt\'s last test.')
    self_calibration = _read('adjustment', 'self_calibration', 'The final adjustment\'s stepwise selection.')
    solves = _read('adjustment', 'solves', 'Every adjustment: iterations, status, seconds.')
    segments_joined = _read('segments', 'joined', 'Segments that joined the block.')
    segment_joins = _read('segments', 'joins', 'Each segment that joined: its keyframes and how.')
    unplaced_keyframes = _read('segments', 'unplaced', 'Keyframes given up for the segment after a break.')
    two_view_oriented = _read('registration', 'two_view_oriented', 'Keyframes oriented from two views, scaled by '
                              'GNSS: {kid: how (its status)}.')
    lever_arm_cam_m = property(lambda self: self.datum.lever.copy(),
                               doc='(3,) antenna in the camera frame (m) of a keyframe without its own antenna offset.')
    freezing_stopped = _read('block', 'freezing_stopped', 'Why this block is no longer frozen (\'\' while it is).')

    # The parts' methods the adjuster answers for (the bundle node, the stage, the tests).
    problem = _delegate('adjustment', 'problem')
    centre_covariance = _delegate('adjustment', 'centre_covariance')
    select_self_calibration = _delegate('adjustment', 'select_self_calibration')
    estimate_gnss_noise = _delegate('rounds', 'estimate_noise')
    gnss_residuals = _delegate('datum', 'residuals')
    gnss_rms_m = _delegate('datum', 'rms_m')
    target_track = _delegate('block', 'target_track')
    target_name = _delegate('block', 'target_name')
    is_check = _delegate('block', 'is_check')
    is_tie = _delegate('block', 'is_tie')
    reprojection_px = _delegate('block', 'reprojection_px')
    poses = _delegate('block', 'poses')
    keyframe_points = _delegate('block', 'keyframe_points')
    observations_of = _delegate('block', 'observations_of')
    intersect_target = _delegate('block', 'intersect_target')
    control_summary = _delegate('block', 'control_summary')
    triangulate_targets = _delegate('block', 'triangulate_targets')
    drop_target_observation = _delegate('block', 'drop_target_observation')
    fix_sigma_enu_m = _delegate('block', 'fix_sigma_enu_m')
    gcps_in_block = _delegate('block', 'gcps_in_block')
    memory_stats = _delegate('block', 'memory_stats')
    freeze = _delegate('block', 'freeze')
    set_control = _delegate('block', 'set_control')
    n_two_view_oriented = _delegate('registration', 'n_two_view')

    def add_ties(self, names) -> None:
        """Make targets `names` manual tie points (in flight: ArUco markers the control file does not list,
        ControlSet.marker_ties); before or after their first keyframe."""
        self.block.add_ties(names)
        if self.segments.current is not None:
            self.segments.current.block.add_ties(names)

    def seed(self, records: list, map_T_cam: dict, point_ids, points_map_m, target_uv: dict,
             gate_px: float | None = None) -> dict:
        """Make this empty adjuster hold the merged block, ready for its `full_adjustment` (core/at_block.py
        `Block.seed`, in this adjuster's map frame)."""
        return self.block.seed(self.origin, records, map_T_cam, point_ids, points_map_m, target_uv, gate_px)

    def add_keyframe(self, rec: KeyframeRecord, window_iterations: int | None = None,
                     block_adjust: bool = True) -> StepReport:
        """Register, triangulate and adjust one keyframe. `window_iterations` replaces the option's
        for this keyframe's window update (a node catching up after a long adjustment); `block_adjust` false
        leaves a full adjustment of the block that is due (growth_ratio, off-GNSS) for a later keyframe
        (counted in block_adjustments_deferred): the node has keyframes waiting, whose poses come first."""
        ids = np.asarray(rec.track_ids, dtype=np.int64).ravel()
        uv = np.asarray(rec.uv, float).reshape(-1, 2)
        if len(ids) != len(uv):
            raise DataError(f'keyframe {rec.stamp_ns}: {len(ids)} track ids but {len(uv)} pixel positions')
        if rec.target_uv:
            ids = np.concatenate([ids, [self.block.new_target_track(n) for n in rec.target_uv]])
            uv = np.vstack([uv, np.asarray(list(rec.target_uv.values()), float).reshape(-1, 2)])
        ids, first = np.unique(ids, return_index=True)   # a duplicated id would be a tracker bug
        uv = uv[first]
        fix_enu = fix_cov = None
        if rec.fix is not None:
            if self.origin is None:
                self.origin = LocalFrame(rec.fix.lat_deg, rec.fix.lon_deg, rec.fix.h_m)
            fix_enu = np.asarray(self.origin.geodetic_to_enu(rec.fix.lat_deg, rec.fix.lon_deg, rec.fix.h_m))
            fix_cov = np.asarray(rec.fix.cov_enu_m2, float).reshape(3, 3)
        kf = Keyframe(len(self.block.kfs), int(rec.stamp_ns), rec.name or str(rec.stamp_ns), ids, uv,
                       self.block.camera.pixel_to_normalized(uv), np.ones(len(ids), bool), fix_enu, fix_cov)
        if rec.antenna_offset_map_m is not None:
            kf.antenna_offset = np.asarray(rec.antenna_offset_map_m, float).reshape(3)
        if rec.map_R_cam_prior is not None:
            R = np.asarray(rec.map_R_cam_prior, float)
            if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-3):
                raise DataError(f'keyframe {rec.stamp_ns}: map_R_cam_prior must be a 3x3 rotation, got {R.tolist()}')
            kf.map_R_cam_prior = R
        self.block.add(kf)
        t0 = time.perf_counter()
        if not self.block.registered:
            rep = self._try_initialise()
        else:
            rep = self.registration.resect(kf)
            if not rep.registered and self.opt.relative_fallback:
                rel = self.registration.relative(kf)
                rep = rel if rel.registered else StepReport(kf.kid, False, f'{rep.status}; {rel.status}')
            if rep.registered:
                self.block.triangulate_new(kf)
                # The segment's tracks it continues became points of the block: the segment joins through them.
                joined = self._join_segment_by_tracks()
                georeferenced_before = self.block.georeferenced
                if not self.block.georeferenced or self.block.provisional:
                    self._try_georeference()
                elif rep.status != 'registered_gnss_rotation':
                    self.rounds.gate_fix(kf)
                waiting = self._orient_waiting(kf, georeferenced_before)
                rep = self._window_adjust(kf.kid, iterations=window_iterations)
                rep.joined, rep.waiting_oriented = joined, waiting
                drifted = not self._growth_due() and self._off_gnss_due(kf.kid)
                if (drifted or self._growth_due()) and not block_adjust:
                    self.block_adjustments_deferred += 1
                elif drifted or self._growth_due():
                    self.off_gnss_adjustments += int(drifted)
                    self._pass_adjustment(gnss_bias=False)
                    rep.block_adjusted = True
                    if drifted:
                        self._off_gnss_back_off(kf.kid)
                if self._control_due():
                    self._control_adjustment()
                    rep.block_adjusted = True
            elif self.segments.wanted(kf):
                rep = self._grow_segment(kf, rec, rep, window_iterations)
        rep.solve_s = time.perf_counter() - t0
        rep.n_points = len(self.block.points)
        self.history.append(rep)
        if self.opt.spill_frozen and kf.kid % max(self.opt.freeze_every, 1) == 0:
            self.block.freeze()
        return rep

    def _orient_waiting(self, kf: Keyframe, georeferenced_before: bool) -> int:
        """Keyframes still without a pose (taken before the block's first pair, or left by resection and the
        relative fallback for too few known points), outside a segment, tried again: by resection (the points the
        block knows now), else from two views (`Registration.two_view`: gated, scaled by GNSS). Those sharing
        min_relative_inliers_gnss tracks with the newly oriented `kf`, two views with it; every one, two views with
        the recent oriented keyframes, when the block has just been georeferenced (before, no fix can vouch for a
        two-view pose). Returns how many got a pose."""
        if not self.opt.relative_fallback or not self.block.georeferenced:
            return 0
        in_segment = set(self.segments.kids)
        ids = kf.track_ids[self.block.usable(kf)]
        partners = [kf.kid] if georeferenced_before else self.block.registered[-2 * self.opt.window_size:]
        n = 0
        for w in self.block.kfs:
            if w.map_T_cam is not None or w.frozen or w.kid in in_segment:
                continue
            if georeferenced_before and len(np.intersect1d(w.track_ids, ids)) < self.opt.min_relative_inliers_gnss:
                continue
            if self.registration.resect(w).registered or self.registration.two_view(w, partners, 'waiting').registered:
                self.block.triangulate_new(w)
                n += 1
        return n

    def _pass_adjustment(self, gnss_bias: bool = True) -> StepReport:
        """A full adjustment during the pass (one round, no GNSS noise estimate); from pass_min_keyframes on,
        the distortion terms of pass_self_calibration are selected stepwise in it (each kept only when it pays,
        as in the final adjustment). The block reports the final adjustment's selection, not this one."""
        final = self.adjustment.self_calibration
        refine = self.opt.pass_refine if len(self.block.registered) >= self.opt.pass_min_keyframes else ()
        rep = self.full_adjustment(iterations=self.opt.full_iterations, rounds=1, gnss_noise=False,
                                   refine_intrinsics=refine, stepwise=bool(refine), gnss_bias=gnss_bias)
        self.adjustment.self_calibration = final
        return rep

    def _growth_due(self) -> bool:
        """The block, georeferenced for good and of pass_min_keyframes, has grown by growth_ratio since its
        last full adjustment (or reached pass_min_keyframes since)."""
        n = len(self.block.registered)
        return (self.opt.growth_ratio > 0.0 and self.block.georeferenced and not self.block.provisional
                and n >= self.opt.pass_min_keyframes
                and (n >= self.opt.growth_ratio * max(self._full_adjusted_n, 1)
                     or self._full_adjusted_n < self.opt.pass_min_keyframes))

    def _off_gnss_due(self, kid: int) -> bool:
        """The block, georeferenced for good, has left its GNSS at its window (`off_gnss_sigma`: the newest keyframe
        `kid`, or the window on average), and off_gnss_gap keyframes came since its last full adjustment."""
        if (self.opt.off_gnss_sigma <= 0.0 or not self.block.georeferenced or self.block.provisional
                or len(self.block.registered) < self._full_adjusted_n + self._off_gnss_gap):
            return False
        due, self._off_gnss_last = off_gnss(self.datum, self.block.registered[-self.opt.window_size:], kid,
                                           self.opt.off_gnss_sigma, self._off_gnss_noise_hv)
        return due

    def _measure_gnss_noise(self) -> None:
        """After a full adjustment of a block georeferenced for good (the fixes used, at least gnss_noise_min_keyframes
        of them): how poor its fixes are about it (`GnssRounds.noise_factors_hv`, each at least 1), kept as the
        off-GNSS test's yardstick. A block adjusted whole sits on its GNSS as well as its photos let it, so what is
        left is the fixes' own noise, which the in-flight adjustments do not estimate (the datum's `sigma_scale_hv` is
        the final and control adjustments'). It does not see all of a wander: the block tilts and bends to heights
        that wander (a consumer geotag's), and a full adjustment the test asks for tilts it further to their trend."""
        if not self.block.georeferenced or self.block.provisional:
            return
        res = self.datum.residuals([k for k in self.block.registered if k not in self.datum.rejected])
        if len(res) >= self.opt.gnss_noise_min_keyframes:
            self._off_gnss_noise_hv = np.maximum(self.rounds.noise_factors_hv(res), 1.0)

    @property
    def off_gnss_noise_hv(self) -> np.ndarray:
        """The off-GNSS test's yardstick (`_measure_gnss_noise`): factors (horizontal, vertical) on the fixes' stated
        sigmas, a copy."""
        return self._off_gnss_noise_hv.copy()

    def off_gnss_figures(self) -> dict:
        """{'adjustments': the full adjustments the off-GNSS test asked for, 'deferred': due full adjustments left for
        later (add_keyframe block_adjust), 'newest_sigmas', 'mean_sigmas', 'n': how far the window sat off its fixes
        at its last test (`off_gnss`; absent before the first)}."""
        return {'adjustments': self.off_gnss_adjustments, 'deferred': self.block_adjustments_deferred,
                **self._off_gnss_last}

    def _off_gnss_back_off(self, kid: int) -> None:
        """After an off-GNSS full adjustment: a window still off its GNSS (what the whole block cannot mend: a lens
        model or fixes that do not fit) doubles the gap before the next one, so that a long flight does not adjust
        whole every few keyframes; a window back on it restores off_gnss_gap."""
        still, _ = off_gnss(self.datum, self.block.registered[-self.opt.window_size:], kid, self.opt.off_gnss_sigma,
                            self._off_gnss_noise_hv)
        self._off_gnss_gap = 2 * self._off_gnss_gap if still else self.opt.off_gnss_gap

    def _control_due(self) -> bool:
        """The block, georeferenced for good and of at most control_adjustment_max_keyframes, holds 3 GCPs or
        more, and not the same ones as at its last control adjustment (one came, or the vetting took one out)."""
        if not (self.opt.control_adjustment and self.opt.use_gcps and self.block.georeferenced
                and not self.block.provisional and len(self.block.registered) <= self.opt.control_adjustment_max_keyframes):
            return False
        gcps = self.block.gcp_names()
        return len(gcps) >= 3 and gcps != self._control_adjusted_gcps

    def _control_adjustment(self) -> StepReport:
        """The whole block adjusted on its GCPs: one round, the GNSS noise estimate (fixes poorer than they state
        would otherwise bend the block their way), then the GNSS bias; no self-calibration. The older keyframes
        move with the block; the later window adjustments take the fixes less the bias, weighted by their noise."""
        self._control_adjusted_gcps = self.block.gcp_names()
        self.adjustment.solve(list(self.block.registered), [], list(self.block.points), self.opt.full_iterations)
        if self.opt.estimate_gnss_noise:
            self.rounds.estimate_noise()
        return self.full_adjustment(iterations=self.opt.full_iterations, rounds=1, gnss_noise=False, gnss_bias=True,
                                    tilt_test=False)

    def _grow_segment(self, kf: Keyframe, rec: KeyframeRecord, failed: StepReport, window_iterations) -> StepReport:
        """Feed the keyframe to the segment (a block of its own in the same map frame); join the segment
        once its GNSS georeferences it (provisionally on a line, as a first line is)."""
        if self.segments.current is None:
            self.segments.start(IncrementalAT(self.block.camera, replace(self.opt, segments=False, spill_frozen=False,
                                                                         use_gcps=False),
                                              origin=self.origin, ties=self.block.ties))
        self.segments.kids.append(kf.kid)
        seg = self.segments.current.add_keyframe(rec, window_iterations)
        joins = self.segments.joined
        # Every track lost early on the first line: the block joins the segment's turn (its full adjustment).
        self._georeference_short_block()
        # The tracker's tie points shared with the block join it at once, in whatever frame both are. Else
        # provisional too: a gap mid-line leaves a line until the next turn. Both in the map frame: the block
        # must be georeferenced as well. Manual tie points shared with the block join it without waiting.
        if not self._join_segment_by_tracks() and self.segments.can_join():
            self.segments.join()
        if self.segments.joined > joins:
            n, how = self.segments.joins[-1]['keyframes'], self.segments.joins[-1]['through']
            if how == 'ties' and (not self.block.georeferenced or self.block.provisional):
                self._try_georeference()
            rep = self._window_adjust(kf.kid, iterations=window_iterations) if kf.map_T_cam is not None \
                else StepReport(kf.kid, False, seg.status)
            rep.joined = n
            through = {'ties': 'the tracker\'s tie points', 'mtp': 'manual tie points'}.get(how, 'its GNSS')
            rep.status = f'registered (a segment of {n} keyframes joined through {through})' if rep.registered \
                else rep.status
            return rep
        return StepReport(kf.kid, False, f'{failed.status}; in a segment of its own, not georeferenced yet '
                                         f'({self.segments.current.block.n_oriented} of {len(self.segments.kids)} oriented)')

    def _join_segment_by_tracks(self) -> int:
        """The segment (if any) joins the block through the tracker's tie points both have triangulated
        (core/at_segments.py `join_by_tracks`); returns how many keyframes joined."""
        if self.segments.current is None:
            return 0
        return self.segments.join_by_tracks(self.opt.segment_min_tie_points)

    def _georeference_short_block(self) -> bool:
        """The block is too short to georeference by itself and the segment is georeferenced for good:
        georeference the block provisionally on its line from 3 keyframes with a fix, or from any geometry
        its GNSS places (it grows no more: what comes goes to the segment); its full adjustment then joins the
        segment. When its GNSS cannot place it either (a few metres of line under the GNSS noise) and the
        segment is the larger, give up the block's keyframes (not oriented) and take the segment in its place.
        Returns whether the block is georeferenced now."""
        seg = self.segments.current
        if self.block.georeferenced or seg is None or not seg.block.georeferenced or seg.block.provisional:
            return False
        if self._try_georeference(line_keyframes=3) or self._try_georeference(force=True):
            return True
        if seg.block.n_oriented <= self.block.n_oriented:
            return False
        self.segments.unplaced += self.block.give_up_oriented()
        self.block.georeferenced, self.block.provisional = True, False   # the segment's, georeferenced for good
        kids = self.segments.kids
        self.segments.join()
        for kid in kids:
            self.block.freezer.seen(kid, self.block.kfs[kid].track_ids)
        return True

    def retry_unregistered(self) -> int:
        """Photos that did not register in sequence get a second chance against the whole block
        (resection against every point, then triangulation); returns how many registered now.
        Adjust afterwards (`full_adjustment`)."""
        return self.registration.register_waiting() if self.block.registered else 0

    def _try_georeference(self, force: bool = False, line_keyframes: int | None = None) -> bool:
        """`force`: accept any non-collinear geometry (end of flight: nothing better will come).
        `line_keyframes`: a straight line georeferences provisionally with this many keyframes with a fix
        (at least 3) spread over 10 sigmas of their GNSS; default: georef_line_min_keyframes over 5 m whose fixes
        give the line's heading to georef_line_heading_deg (`line_heading_sigma_rad`)."""
        ks = [k for k in self.block.registered if self.block.kfs[k].fix_enu is not None]
        if not self.block.georeferenced and (not ks or (force and len(ks) < 3)):
            return self._georeference_by_gcps()
        # Fixes of mixed quality (RTK fixed beside FLOAT photos): only the precise ones place the block; the
        # adjustments that follow weight every fix by its own sigma.
        ks = self.datum.similarity_fixes(ks, 3)
        if len(ks) < (max(self.opt.georef_min_keyframes, 3) if line_keyframes is None else max(line_keyframes, 3)):
            return False
        src = np.array([self.block.kfs[k].map_T_cam[:3, 3] for k in ks])
        dst = np.array([self.block.kfs[k].fix_enu if self.block.kfs[k].antenna_offset is None
                        else self.block.kfs[k].fix_enu - self.block.kfs[k].antenna_offset for k in ks])
        sig = np.sqrt(np.median([np.trace(self.block.kfs[k].fix_cov) for k in ks]))
        sv = spread(dst)
        if force:
            # End of flight: GCPs (three or more) join the fit. On a straight line the GNSS leaves the roll
            # about it to noise, and the GCPs off the line fix it.
            gcp = self.block.gcp_pairs()
            if len(gcp) >= 3:
                src = np.vstack([src, [p for p, _ in gcp]])
                dst = np.vstack([dst, [q for _, q in gcp]])
        else:
            gcp = []
        # A block made without GNSS drifts in scale along the line: tolerate ~2 % of its extent.
        thr = 4.0 * sig + np.linalg.norm(self.datum.lever) + 0.05 + 0.02 * 2 * sv[0]
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
        elif self.block.georeferenced:
            return False    # provisional already; wait for the turn
        elif self.opt.assume_nadir and (
                (line_keyframes is None and len(ks) >= self.opt.georef_line_min_keyframes and sv[0] > 5.0
                 and line_heading_sigma_rad(
                    [self.block.kfs[k].fix_cov for k in ks], sv[0]) <= np.radians(self.opt.georef_line_heading_deg))
                or (line_keyframes is not None and len(ks) >= line_keyframes and sv[0] > 10.0 * sig)):
            # Straight line: everything but the roll about it comes from GNSS; the roll from the cameras'
            # attitude priors (the autopilot and the mount: a fixed wing banks and crabs) when they have them,
            # else from the near-nadir camera. Provisional until the first turn.
            n = len(ks)   # the cameras alone (GCPs joined a forced fit above)
            dirs = np.array([self.block.kfs[k].map_T_cam[:3, 2] for k in ks])
            prior = [k for k in ks if self.block.kfs[k].map_R_cam_prior is not None]
            att = (np.array([self.block.kfs[k].map_T_cam[:3, :3] for k in prior]),
                   np.array([self.block.kfs[k].map_R_cam_prior for k in prior])) if len(prior) >= 3 else None
            s = line_similarity_robust(src[:n], dst[:n], dirs, att, thr)
            if s is None:
                return False    # the line's fixes do not agree on one placement yet (a glitched fix): wait
            provisional = True
        else:
            return False
        if self.block.georeferenced:   # provisional -> final: GNSS priors of the whole block fix the roll
            self.block.provisional = False
            self._pass_adjustment()
            return True
        # Fixes far from where the georeferenced block puts their cameras are glitches: not used.
        far = np.linalg.norm(s.apply(src[:len(ks)]) - dst[:len(ks)], axis=1) > thr
        if far.sum() <= len(ks) // 4:
            self.datum.rejected |= {k for k, f in zip(ks, far) if f}
        self._apply_georeference(s, provisional)
        return True

    def set_origin(self, origin: LocalFrame) -> bool:
        """The map frame's origin when no fix has set it (a flight without GNSS, placed by its GCPs): False,
        and nothing changed, once one is set."""
        if self.origin is not None:
            return False
        self.origin = origin
        return True

    def _georeference_by_gcps(self) -> bool:
        """A block whose cameras have no fix (photos without geotags, a GNSS outage from the start), or fewer
        than 3 at the end: 3 or more GCPs triangulated in it, not on a line, georeference it by the similarity of their
        points onto their surveyed positions. Each must fit it within 5 cm + 2 % of the GCPs' extent (the
        relative block's scale drift); False (not georeferenced) when they do not, or are too few."""
        gcp = self.block.gcp_pairs()
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
        for k in self.block.registered:
            self.block.kfs[k].map_T_cam = s.apply_pose(self.block.kfs[k].map_T_cam)
        ids, P = self.block.points.arrays()
        if len(ids):
            self.block.points.set_many(ids, np.array([s.apply(p[None])[0] for p in P]))
        self.block.georeferenced = True
        self.block.provisional = provisional
        if provisional:
            self.full_adjustment(iterations=self.opt.full_iterations, rounds=1, gnss_noise=False)
        else:
            self._pass_adjustment()

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
        tilt_test: with gnss_tilt "auto", test whether the tilt pays (GnssRounds.tilt_tested); else the last test's outcome
        stands.
        """
        if not refine_intrinsics and gnss_noise:
            refine_intrinsics = self.opt.final_refine
            stepwise = stepwise or self.opt.final_stepwise
        rep = StepReport(-1, False, 'not_initialised')
        if not self.block.registered:
            return rep
        if gnss_noise and self.datum.bias_estimated:
            # The final adjustment estimates the bias afresh, after its own self-calibration and GNSS noise estimate:
            # the focal length and the bias's height trade off on a flat block, so one from the control adjustments
            # in flight (fixes weighted as stated, the lens held) would steer where the final one lands.
            self.datum.forget_bias()
        if not self.block.georeferenced and (self._georeference_short_block() or self._try_georeference(force=True)):
            rounds = max(rounds - 1, 1)
        if self.segments.current is not None and self.segments.current.block.n_oriented:
            # End of flight (or asked for): a segment still waiting joins if its GNSS places it at all.
            self.segments.current.full_adjustment(iterations=iterations, rounds=1, gnss_noise=False)
            if self.segments.can_join():
                self.segments.join()
        if self.block.ties:
            self.block.retriangulate_ties()
        if stepwise and refine_intrinsics:
            # The final adjustment (gnss_noise) starts from the pass's lens; a pass selects afresh from the given one.
            refine_intrinsics = self.adjustment.select_self_calibration(refine_intrinsics, iterations,
                                                                        from_block=gnss_noise)
        for _ in range(rounds):
            tracks = list(self.block.points)
            rep = self.adjustment.solve(list(self.block.registered), [], tracks, iterations or self.opt.full_iterations,
                              refine_intrinsics)
        if gnss_noise and self.opt.estimate_gnss_noise and self.block.georeferenced and not self.block.provisional:
            self.rounds.estimate_noise(iterations, refine_intrinsics)
        self._full_adjusted_n = len(self.block.registered)
        self._measure_gnss_noise()
        if gnss_bias and self.opt.estimate_gnss_bias and self.block.n_gcps() >= 3 and self.opt.bias_iterations:
            self.datum.bias_estimated = True
            mode = self.opt.gnss_tilt if tilt_test or self.opt.gnss_tilt != 'auto' else (
                'always' if self.datum.tilt_estimated else 'never')
            tilt = mode != 'never' and self.rounds.tilt_observable()
            if tilt and mode == 'auto':
                rep, settle = self.rounds.tilt_tested(iterations, rep)
            else:
                rep, settle = self.rounds.bias_rounds(iterations, tilt, rep)
            self.rounds.settle = settle
        if self.opt.spill_frozen:
            self.block.freeze()   # the adjustment read every keyframe back: spill the frozen ones again
        return rep


    def _try_initialise(self) -> StepReport:
        """The block's first pair (core/at_register.py `initialise`), adjusted in full."""
        kid = self.registration.initialise()
        if kid is None:
            return StepReport(self.block.kfs[-1].kid, False, 'waiting_for_initialisation')
        rep = self.full_adjustment(iterations=self.opt.full_iterations, rounds=1, gnss_noise=False)
        rep.status = 'initialised'
        rep.waiting_oriented = len(self.block.registered) - 1   # the pair's first and the keyframes registered with it
        return rep

    def _window_adjust(self, kid: int, iterations: int | None = None) -> StepReport:
        return self.adjustment.window(kid, self.opt.window_iterations if iterations is None else iterations)


def _names(text: str) -> tuple:
    """A comma-separated list of names as a tuple (blanks dropped)."""
    return tuple(v.strip() for v in text.split(',') if v.strip())


def off_gnss(datum, kids, newest: int, sigma: float, noise_hv=(1.0, 1.0)) -> tuple[bool, dict]:
    """Has the window `kids` left its GNSS? Each keyframe's antenna residual (m, ENU) over its fix's sigma: the
    stated one times the flight's noise factor (horizontal, vertical), the larger of the datum's
    (`GnssDatum.sigma_scale_hv`, what the fixes are weighted by) and `noise_hv` (how poor the fixes were about the
    block at its last full adjustment, IncrementalAT `_measure_gnss_noise`); fixes left out of the adjustment not
    counted. True when keyframe `newest` is off by more than `sigma` on some axis, or the window's mean by more than
    sigma / 2 (a shift or turn the window shares). Also returns the figures: {'newest_sigmas', 'mean_sigmas', 'n'}."""
    res = datum.residuals([k for k in kids if k not in datum.rejected])
    if not res:
        return False, {'newest_sigmas': None, 'mean_sigmas': None, 'n': 0}
    scale = np.maximum(datum.sigma_scale_hv, np.asarray(noise_hv, float).reshape(2))[[0, 0, 1]]
    z = {k: np.asarray(r, float) / (scale * np.sqrt(np.maximum(np.diag(np.asarray(datum.block.kfs[k].fix_cov, float)
                                                                         .reshape(3, 3)), 1e-12)))
         for k, r in res.items()}
    mean = np.mean(list(z.values()), axis=0)
    last = float(np.max(np.abs(z[newest]))) if newest in z else 0.0
    m = float(np.max(np.abs(mean))) if len(z) >= 3 else 0.0
    return last > sigma or m > sigma / 2.0, {'newest_sigmas': round(last, 2), 'mean_sigmas': round(m, 2), 'n': len(z)}


def line_heading_sigma_rad(fix_covs, along_spread_m: float) -> float:
    """1-sigma (rad) of a straight line's heading fitted to its fixes: the median horizontal sigma of one fix
    (sqrt of the mean of its E and N variances) over their RMS spread along the line times sqrt(their count)."""
    covs = [np.asarray(c, float).reshape(3, 3) for c in fix_covs]
    if not covs or along_spread_m <= 0.0:
        return float('inf')
    sig_h = float(np.sqrt(np.median([0.5 * (c[0, 0] + c[1, 1]) for c in covs])))
    return sig_h / (along_spread_m * np.sqrt(len(covs)))


def line_similarity_robust(src, dst, dirs, att, thr: float):
    """The similarity of a straight line's cameras onto their fixes (core/similarity.similarity_on_line) with its
    glitched fixes left out: the fix farthest from the fit is dropped while one is beyond `thr` (at most a quarter
    of them); None when the fixes left still do not fit within `thr` (the line waits for more keyframes)."""
    keep = np.ones(len(src), bool)
    for dropped in range(len(src) // 4 + 1):
        s = similarity_on_line(src[keep], dst[keep], dirs[keep], attitude_priors=att)
        r = np.linalg.norm(s.apply(src) - dst, axis=1)
        if not (r[keep] > thr).any():
            return s
        if dropped == len(src) // 4 or keep.sum() <= 3:
            return None
        keep[int(np.argmax(np.where(keep, r, -np.inf)))] = False
    return None

