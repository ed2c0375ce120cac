"""The adjustment stage: incremental aerial triangulation of the keyframes in flight, without ROS.

In (plain methods, any thread): `set_camera` (the calibration; keyframes wait for it), `add_fix` (a keyframe
fix: geodetic position, ENU covariance, NavSatStatus status and covariance type), `add_keyframe` (stamp,
track ids, pixels, the target rows the tracker found), `add_attitude` (body FLU in ENU: a gimballed
camera's antenna offset, every keyframe's orientation prior), `request_full_adjustment`.
Work (one thread at a time, under `work`): `take_work` hands out the keyframes that may be adjusted now and
whether a full adjustment was asked for; `run_batch` adjusts them; `finish` and `full_adjustment` end the
flight. `drain` does both at once for a caller without a worker thread (tests, offline commands).
Out: through `out` (an `Outputs`): the georeference once, poses with their covariance, the path, the sparse
cloud, the live quality document, the camera a full adjustment's poses were adjusted with; through `diag` (count / set / problem(text, level)): the /diagnostics keys
and problems with OK, WARN or ERROR. `DiagnosticsLog` and `RecordedOutputs` keep them for a caller without ROS.

The policies (bundle_node's docstring tells them in full): a fix without a covariance gets one from its GNSS
mode; one above max_fix_sigma_m (max_rtk_sigma_m under RTK status) is not used; a keyframe waits for its fix
until a later fix says there is none or fix_wait_s passes; a batch's older keyframes get the short catch-up
adjustment and one publication covers the batch; the marginal covariance is recomputed every
covariance_every updates; surveyed targets are vetted against the block (core/control_live.py) before use;
health: the share not oriented, a block without georeference, the block check (core/block_check.py).

The pace: per keyframe the window adjustment (it stops once a step gains under 1e-4 of the cost,
core/at_problem.py WINDOW_FUNCTION_TOLERANCE), then the poses go out; what can wait comes after them: the
figures on /diagnostics, the live quality (every quality_every), the control vetting and the block check (every
10 oriented keyframes). A keyframe queued behind others (a batch) gets the catch-up adjustment and none of that:
the batch's newest does it once for the batch.

Provisional poses (publish_provisional, on by default: the in-flight map's poses come from the first keyframes,
labelled): a straight first line georeferences the block provisionally (the roll about the line is assumed,
core/incremental.py); its poses go out at once, each labelled in its covariance (core/pose_status.py: the
provisional roll about the line added to the rotation block; msgs.pose_is_provisional tells it from a
message), and /diagnostics says it: `georeferenced` = provisional, `poses_provisional` (published poses
that are provisional now) and `poses_provisional_last_stamp_ns` (the newest). The final georeference at the
turn publishes every pose again, final, with the same stamps: they replace the provisional ones and
`poses_provisional` drops to 0. A flight that ends on its straight line keeps them provisional (a WARN).
Whoever fuses poses into a map (stereo) waits for the final ones.

Off its GNSS: a block georeferenced for good whose window sits off its fixes (core/incremental.py off_gnss_sigma)
is adjusted whole at once and published again; /diagnostics says how often (`off_gnss_adjustments`) and how far
the window sat off at its last test, in its fixes' sigmas (`window_off_gnss_newest_sigmas`, `_mean_sigmas`).

Orientation prior: each keyframe whose stamp an autopilot attitude (`add_attitude`) covers carries
`map_R_cam_prior`, the camera's orientation in map from that attitude and the mount (`camera_mount`,
`mount_rpy_deg`; core/attitude.py camera_prior_map_R_cam): the whole body attitude for a camera fixed to
the body, the body's yaw alone for a gimballed one. The adjuster may use it for the roll about the first line.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from photogram_ros.core.at_report import convergence
from photogram_ros.core.attitude import (AttitudeHistory, antenna_offset_enu, camera_prior_map_R_cam,
                                         flu_R_cam_of_mount)
from photogram_ros.core.control import TARGET_DTYPE, ControlSet
from photogram_ros.core.control_live import LiveControl, LiveControlOptions
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.gnss_fix import COV_UNKNOWN, STATUS_GBAS_FIX, STATUS_SBAS_FIX, GnssFix
from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions, KeyframeRecord
from photogram_ros.core.pose_status import line_direction, provisional_covariance
from photogram_ros.core.survey_quality import FIX_CLASSES, fix_class
from photogram_ros.errors import ConfigError, PhotogramError
from photogram_ros.params import param
from photogram_ros.stages.adjustment_counts import NotOrientedCounts
from photogram_ros.stages.block_health import block_check_on_diagnostics
from photogram_ros.stages.end_budget import EndBudget, end_times, full_adjustment_estimate_s, skip_at_end
from photogram_ros.stages.live_quality import control_diagnostics, live_quality, quality_diagnostics
from photogram_ros.stages.report import ERROR, OK, WARN, DiagnosticsLog  # noqa: F401  (OK: for callers)
from photogram_ros.stages.segment_text import segment_diagnostics



@dataclass
class AdjustmentParams(LiveControlOptions, IncrementalOptions):
    """The adjuster's parameters (core/incremental.py), the in-flight control's (core/control_live.py)
    and the stage's own."""
    use_origin_params: bool = param(False, 'anchor map at origin_* instead of the first keyframe fix')
    origin_lat_deg: float = param(0.0, 'map origin latitude, deg', min=-90.0, max=90.0)
    origin_lon_deg: float = param(0.0, 'map origin longitude, deg', min=-180.0, max=180.0)
    origin_h_m: float = param(0.0, 'map origin ellipsoidal height, m', min=-1e4, max=1e5)
    fix_wait_s: float = param(10.0, 'how long (wall time) a keyframe waits for its fix (and a gimballed camera\'s '
                                    'attitude) before it is adjusted without one, s; a later fix ends the wait at '
                                    'once', min=0.0, max=60.0)
    sync_tolerance_ms: float = param(5.0, 'features and fix with stamps closer than this belong together, ms',
                                     min=0.0, max=1000.0)
    max_fix_sigma_m: float = param(50.0, 'fixes with a larger horizontal sigma are not used, m', min=0.01, max=1e4)
    max_rtk_sigma_m: float = param(1.0, 'a fix reporting RTK (GBAS status) with a larger horizontal sigma is not '
                                        'used, m: its receiver has lost the corrections but still says RTK',
                                   min=0.01, max=1e4)
    health_window: int = param(20, 'health: keyframes over which the share not oriented is judged', min=2, max=10000)
    health_max_unoriented: float = param(0.1, 'health: WARN above this share of the last health_window keyframes '
                                              'not oriented (ERROR above 0.5)', min=0.0, max=1.0)
    georef_warn_keyframes: int = param(10, 'health: WARN when this many keyframes with a fix are in and the block is '
                                           'still not georeferenced (ERROR at twice as many)', min=1, max=100000)
    cloud_every: int = param(5, 'publish the sparse cloud every this many keyframes', min=1, max=1000)
    cloud_recent_only: bool = param(True, 'the sparse cloud holds the tie points of the keyframes around the '
                                          'adjustment window (what stereo takes its ground and depth range from); '
                                          'off: the whole block, a message that grows with the flight')
    full_adjustment_on_shutdown: bool = param(True, 'adjust the whole block when the node stops')
    block_adjust_when_behind: bool = param(False, 'in flight, run a due full adjustment of the whole block '
                                                  '(growth_ratio, off_gnss_sigma) even while keyframes wait for the '
                                                  'adjuster; false: it waits until the adjuster has caught up (the '
                                                  'poses first; counted in block_adjustments_deferred)')
    catch_up_iterations: int = param(3, 'iterations of the window adjustment of a keyframe that already has newer '
                                        'ones queued behind it (the newest of a batch gets the full adjustment): '
                                        'lets the node catch up after a long adjustment', min=1, max=100)
    marginal_covariance: bool = param(True, 'pose covariance from the window adjustment\'s marginal covariance of '
                                            'the camera centres (one more linearisation per update, made after '
                                            'the poses went out: a keyframe\'s first pose has the stand-in, the '
                                            'window\'s next ones its marginal); off: the fix\'s variance as a '
                                            'stand-in')
    covariance_every: int = param(3, 'recompute the marginal covariance every this many window updates (it costs '
                                     'about half a window update); poses in between reuse their last one',
                                  min=1, max=100)
    control_file: str = param('', 'surveyed targets (first line a CRS, then "name marker_id x y z [sigma_h_m '
                                  'sigma_v_m]"; names CHK* are check points): the tracker\'s ArUco detections '
                                  'become GCPs and check points; "" = none')
    check_names: str = param('', 'more check points of control_file (never used in the adjustment), comma separated')
    control_heights: str = param('auto', 'heights of control_file: ellipsoidal, orthometric (EGM2008), or auto '
                                 '(orthometric when its CRS is compound with EGM2008 heights)',
                                 choices=('auto', 'ellipsoidal', 'orthometric'))
    gcp_sigma_h_m: float = param(0.0, 'horizontal sigma of every GCP, m (0: the file\'s, 0.02 m where it gives none)',
                                 min=0.0, max=100.0)
    gcp_sigma_v_m: float = param(0.0, 'vertical sigma of every GCP, m (0: the file\'s, 0.03 m where it gives none)',
                                 min=0.0, max=100.0)
    quality_every: int = param(5, 'publish the live accuracy (map/control_points: check points intersected '
                                  'from the adjusted cameras, fix shares) every this many published keyframes',
                                  min=1, max=1000)
    publish_provisional: bool = param(True, 'publish poses while the georeference is still provisional (a '
                                            'straight first line leaves the roll about it to an assumption until '
                                            'the first turn), labelled provisional in their covariance '
                                            '(core/pose_status.py) and on /diagnostics, and published again when '
                                            'the turn makes them final; off, poses start at the first turn')
    camera_mount: str = param('auto', 'how the camera hangs, for its orientation prior from the autopilot '
                                      'attitude: fixed (turns with the body), gimbal (held at mount_rpy_deg from '
                                      'nadir, turning with the body\'s yaw only), auto (gimbal when '
                                      'lever_arm_body_frd_m is set, else fixed)', choices=('auto', 'fixed', 'gimbal'))
    mount_rpy_deg: list = param([0.0, 0.0, 0.0], 'the camera\'s roll, pitch, yaw from the nominal mount (nadir, image '
                                'top toward the nose) about the body\'s forward, right, down axes, deg (pitch > 0 '
                                'looks ahead); a gimbal: its set angles from nadir')

    def check(self) -> None:
        super().check()
        if len(self.mount_rpy_deg) != 3:
            raise ConfigError(f'mount_rpy_deg needs 3 numbers (roll, pitch, yaw, deg), got {self.mount_rpy_deg}')

    @property
    def gimballed(self) -> bool:
        """The camera is held by a gimbal (camera_mount, or auto: a body lever arm is set)."""
        return self.camera_mount == 'gimbal' or (self.camera_mount == 'auto' and self.gimbal)


# 1-sigma E, N, U (m) of a fix that gives no covariance, by its NavSatFix status: what such a receiver
# typically achieves (RTK: fixed or float, the status cannot tell; SBAS/DGPS; a plain 3D fix).
UNKNOWN_FIX_SIGMA_M = {STATUS_GBAS_FIX: (0.5, 0.5, 1.0), STATUS_SBAS_FIX: (1.5, 1.5, 3.0)}
PLAIN_FIX_SIGMA_M = (5.0, 5.0, 10.0)


def unknown_fix_covariance(status: int) -> np.ndarray:
    """ENU covariance (m^2) for a fix without one, following its GNSS mode (UNKNOWN_FIX_SIGMA_M)."""
    return np.diag(np.square(UNKNOWN_FIX_SIGMA_M.get(status, PLAIN_FIX_SIGMA_M)))


def fix_sigma_limit_m(status: int, p) -> float:
    """Largest horizontal sigma (m) of a usable fix: max_fix_sigma_m, and max_rtk_sigma_m for a fix that
    reports RTK (a larger sigma under an RTK status is a receiver that lost its corrections)."""
    if status >= STATUS_GBAS_FIX:
        return min(p.max_fix_sigma_m, p.max_rtk_sigma_m)
    return p.max_fix_sigma_m


def pose_covariance(kf, centre_cov: np.ndarray | None = None, provisional_line=None) -> np.ndarray:
    """Pose covariance (x, y, z, roll, pitch, yaw): the position block is the marginal covariance
    of the camera centre when given; otherwise the fix's variance (the adjusted centre is at
    least that good) or 100 m^2 without a fix. The angles get 1 mrad^2 (the solver gives no
    orientation marginals); a provisional pose (`provisional_line`: the first line's direction in map)
    gets the provisional roll about that line on top (core/pose_status.py), its label."""
    C = np.zeros((6, 6))
    if centre_cov is not None:
        C[:3, :3] = 0.5 * (centre_cov + centre_cov.T)
    else:
        C[:3, :3] = np.diag(np.diag(kf.fix_cov) if kf.fix_cov is not None else np.full(3, 100.0))
    C[3:, 3:] = np.eye(3) * 1e-6
    return C if provisional_line is None else provisional_covariance(C, provisional_line)


def label_provisional(at, kfs, path, stamps: set, diag) -> np.ndarray | None:
    """The first line's direction that labels the poses of keyframes `kfs` provisional (pose_covariance), None
    once the georeference is final; `stamps` keeps the keyframes whose last published pose is provisional, said
    on /diagnostics (poses_provisional, poses_provisional_last_stamp_ns). `path`: every oriented keyframe."""
    line = None
    if at.georef_provisional:   # the roll about the first line is an assumption until the turn
        line = line_direction(np.array([kf.map_T_cam[:3, 3] for kf in path]))
        stamps.update(kf.stamp_ns for kf in kfs)
    else:
        stamps.difference_update(kf.stamp_ns for kf in kfs)
    diag.set('poses_provisional', len(stamps))
    diag.set('poses_provisional_last_stamp_ns', max(stamps, default=0))
    return line


@dataclass
class AdjustmentOutcome:
    """What a final (full) adjustment came to: 'done', 'failed' or 'none' (nothing to adjust), and why."""
    status: str
    reason: str = ''

    @property
    def failed(self) -> bool:
        return self.status == 'failed'


class Outputs:
    """Where the stage's results go (a node publishes them); each does nothing here."""

    def georeference(self, lat_deg: float, lon_deg: float, h_m: float, stamp_ns: int) -> None:
        """The origin of `map` (ENU tangent there), once the block is georeferenced."""

    def poses(self, poses: list) -> None:
        """[(map_T_cam (4, 4), stamp_ns, covariance (6, 6) x y z roll pitch yaw)] of the keyframes to publish."""

    def path(self, map_T_cams: list, stamps_ns: list, stamp_ns: int) -> None:
        """Every oriented keyframe's pose."""

    def cloud(self, points_map: np.ndarray, stamp_ns: int, track_ids: np.ndarray) -> None:
        """(N, 3) tie points in `map` and their track ids."""

    def quality(self, doc: dict) -> None:
        """The live accuracy document (map/control_points)."""

    def camera(self, camera, stamp_ns: int) -> None:
        """The camera (core.camera.PinholeCamera) the poses of a full adjustment were adjusted with: the input
        calibration, or its self-calibration (final_self_calibration, or the pass's: pass_self_calibration);
        published before those poses."""


class RecordedOutputs(Outputs):
    """Outputs kept in memory: the latest pose per stamp, every path, cloud, quality document."""

    def __init__(self):
        self.georeferences, self.pose_by_stamp, self.paths, self.clouds, self.qualities = [], {}, [], [], []
        self.cameras = []

    def georeference(self, lat_deg, lon_deg, h_m, stamp_ns):
        self.georeferences.append((lat_deg, lon_deg, h_m, stamp_ns))

    def poses(self, poses):
        self.pose_by_stamp.update({stamp: (T, cov) for T, stamp, cov in poses})

    def path(self, map_T_cams, stamps_ns, stamp_ns):
        self.paths.append((map_T_cams, stamps_ns, stamp_ns))

    def cloud(self, points_map, stamp_ns, track_ids):
        self.clouds.append((points_map, stamp_ns, track_ids))

    def quality(self, doc):
        self.qualities.append(doc)

    def camera(self, camera, stamp_ns):
        self.cameras.append((camera, stamp_ns))


class AdjustmentStage:
    """The in-flight adjustment (module docstring). `cond` guards the inputs; `work` serialises every use
    of `at` (the adjuster, None until the camera is set)."""

    def __init__(self, p: AdjustmentParams, diag=None, out: Outputs | None = None,
                 control: ControlSet | None = None):
        """`control`: the surveyed targets (in flight: those the command read, handed by the graph and the node);
        None reads p.control_file when it names one (a ROS user's parameter file; a bad file raises, naming the
        line)."""
        self.p, self.diag, self.out = p, diag or DiagnosticsLog(), out or Outputs()
        if control is None and p.control_file:
            from photogram_ros.io.control_file import read_control_file
            control = read_control_file(p.control_file, p.check_names.split(','), p.control_heights)
        self.control = control
        # Every target is held as a check point until it is checked against the GNSS-only block.
        self.live = LiveControl(control.file_heights, p) if control is not None else None
        self._control_in_map = False
        self.at: IncrementalAT | None = None
        self.camera = None
        self._camera_sent = None   # the camera the stereo node matches with: the input, or a refined one sent
        self._pending: dict[int, tuple] = {}   # stamp -> (arrival, track ids, uv, {target name: uv})
        self._fixes: dict[int, GnssFix] = {}
        self._georef_sent = False
        self._last_failure = ''
        self._latest_fix_ns = None
        self._published_final = False
        self._n_since_cloud = 0
        self._unpublished = 0   # keyframes oriented in a batch before its newest, not yet published
        self._not_oriented = NotOrientedCounts(self.diag)
        self._block_moved = False   # a full adjustment of the pass moved every keyframe since the last publication
        self._centre_cov: dict[int, np.ndarray] = {}   # keyframe id -> last marginal centre covariance
        self._cov_updates = 0
        self._fix_classes = {c: 0 for c in FIX_CLASSES}   # keyframes adjusted, per GNSS fix class
        self._since_quality = 0
        # Attitudes cover the last two minutes of stamps: keyframes reach the adjuster seconds late.
        self._attitude = AttitudeHistory(max_age_ns=120 * 10**9)
        self._attitude_arrival = -1e9   # monotonic time of the newest attitude
        self._flu_R_cam = flu_R_cam_of_mount(p.mount_rpy_deg)   # the camera's mount on the body
        self._provisional_stamps: set[int] = set()   # keyframes whose last published pose is provisional
        self._checked_at = 0   # keyframes oriented at the last block check (one every 10, after the poses)
        self._first_keyframe_arrival = None   # monotonic time of the first keyframe
        self._unplaced = 0                     # keyframes before an early break given up, already said
        self._adjusted_whole = False           # a full adjustment ran after the last keyframe
        self._block_verdict: dict | None = None   # the last block check: {'status', 'summary'} (live quality)
        self._full_requested = False
        self._busy = False
        self._cut_at, self._full_s, self._full_n = float('inf'), None, 0   # stop budget; last full adjustment s, n
        self.cond = threading.Condition()
        self.work = threading.RLock()

    # --- inputs ---------------------------------------------------------------------------------

    def set_camera(self, camera) -> bool:
        """The calibration (the first one counts): starts the adjuster. False when one was set already."""
        if self.camera is not None:
            return False
        self.camera = self._camera_sent = camera
        origin = (LocalFrame(self.p.origin_lat_deg, self.p.origin_lon_deg, self.p.origin_h_m)
                  if self.p.use_origin_params else None)
        with self.work:
            self.at = IncrementalAT(camera, self.p, origin=origin)
            self._unplaced = 0
            self._control_to_map()
        self.wake()
        return True

    def add_fix(self, stamp_ns: int, lat_deg: float, lon_deg: float, h_m: float, covariance_enu_m2,
                status: int, covariance_type: int) -> bool:
        """A keyframe fix (NavSatFix fields): kept for its keyframe unless it has no position or is too
        inaccurate; one without a covariance gets its GNSS mode's. True when kept."""
        cov = np.asarray(covariance_enu_m2, float).reshape(3, 3)
        if status < 0 or not np.all(np.isfinite([lat_deg, lon_deg, h_m])):
            self.diag.count('fixes_without_position')
            return False
        if covariance_type == COV_UNKNOWN or not np.all(np.diag(cov) > 0):
            cov = unknown_fix_covariance(int(status))
            self.diag.count('fixes_without_covariance')
        if np.sqrt(cov[0, 0]) > fix_sigma_limit_m(int(status), self.p):
            self.diag.count('fixes_too_inaccurate')
            return False
        with self.cond:
            # Status and covariance type only feed the live fix shares (the adjustment reads position and cov).
            self._fixes[stamp_ns] = GnssFix(lat_deg, lon_deg, h_m, cov, stamp_ns, int(status), int(covariance_type))
            self._latest_fix_ns = max(self._latest_fix_ns or 0, stamp_ns)
            self.cond.notify()
        self.diag.count('fixes')
        return True

    def add_keyframe(self, stamp_ns: int, track_ids, uv, targets=None, arrival_s: float | None = None) -> None:
        """A keyframe's features: track ids (N,), pixels (N, 2), and the target rows (marker_id, u, v) the
        tracker found; `arrival_s` is its monotonic arrival time (now when None). Raises PhotogramError on
        non-finite pixels."""
        uv = np.asarray(uv)
        if targets is None:
            targets = np.zeros(0, TARGET_DTYPE)
        if not np.all(np.isfinite(uv)) or not np.all(np.isfinite(targets['u'])):
            raise PhotogramError('non-finite pixel coordinates')
        target_uv, unknown = self.control.target_uv(targets) if self.control is not None else ({}, len(targets))
        with self.cond:
            arrival_s = time.monotonic() if arrival_s is None else arrival_s
            self._pending[stamp_ns] = (arrival_s, np.asarray(track_ids).astype(np.int64), uv, target_uv)
            if self._first_keyframe_arrival is None:
                self._first_keyframe_arrival = arrival_s
            self.cond.notify()
        self.diag.count('keyframes_received')
        if len(targets):
            self.diag.count('target_detections', len(targets))
        if unknown:
            self.diag.count('target_detections_ignored', unknown)   # no control file, or not in it

    def add_attitude(self, stamp_ns: int, q_xyzw) -> None:
        """The body's attitude (FLU in ENU, quaternion x y z w) at stamp_ns."""
        with self.cond:
            self._attitude.add(stamp_ns, q_xyzw)
            self._attitude_arrival = time.monotonic()
            self.cond.notify()

    def request_full_adjustment(self) -> None:
        with self.cond:
            self._full_requested = True
            self.cond.notify()

    def wake(self) -> None:
        with self.cond:
            self.cond.notify()

    # --- scheduling -------------------------------------------------------------------------------

    def _waits_for_attitude(self, stamp: int) -> bool:
        """A gimballed camera's keyframe waits until an attitude after its stamp is in (attitudes and
        keyframes come by different paths, and attitudes decoded from a busy MAVLink link arrive seconds
        late and in bursts): before the first one for fix_wait_s from the first keyframe, then while one
        came within fix_wait_s; not once they stopped coming for that long (an outage). The caller bounds
        each keyframe's wait by fix_wait_s."""
        if not self.p.gimbal:
            return False
        now, newest = time.monotonic(), self._attitude.newest_ns
        if newest is None:
            return now - self._first_keyframe_arrival < self.p.fix_wait_s
        live = now - self._attitude_arrival < self.p.fix_wait_s
        return live and newest < stamp - self._attitude.hold_ns

    def _record(self, stamp: int, ids, uv, fix, target_uv) -> KeyframeRecord:
        """A keyframe for the adjuster, with a gimballed camera's antenna offset and the orientation prior from an
        attitude covering its stamp and the mount (`camera_prior_map_R_cam`). Called with cond held (attitudes)."""
        offset = prior = None
        enu_R_flu = self._attitude.at(stamp) if len(self._attitude) else None
        if enu_R_flu is not None:
            prior = camera_prior_map_R_cam(enu_R_flu, self._flu_R_cam, self.p.gimballed)
        elif len(self._attitude):
            self.diag.count('keyframes_without_attitude_prior')
        if self.p.gimbal:
            if enu_R_flu is None:
                self.diag.count('keyframes_without_attitude')
                self.diag.problem('lever_arm_body_frd_m is set but no attitude (mavlink/attitude) covers the '
                                  'keyframes: the body lever arm is applied as if flying level, image top forward '
                                  '(wrong by the lever times the tilt); give the attitude, or the lever arm in the '
                                  'camera frame (lever_arm_cam_m) for a camera fixed to the body, or zeros')
            else:
                offset = antenna_offset_enu(enu_R_flu, self.p.lever_arm_body_frd_m)
        return KeyframeRecord(stamp, ids, uv, fix, target_uv=target_uv, antenna_offset_map_m=offset,
                              map_R_cam_prior=prior)

    def _match_fix(self, stamp: int) -> GnssFix | None:
        tol = int(self.p.sync_tolerance_ms * 1e6)
        best = min(self._fixes, key=lambda s: abs(s - stamp), default=None)
        if best is not None and abs(best - stamp) <= tol:
            return self._fixes.pop(best)
        return None

    def _ready(self) -> list[KeyframeRecord]:
        """Take the keyframes that may be adjusted now, in stamp order: their fix is in, or a later
        fix says there is none, or they waited fix_wait_s. Called with cond held."""
        if self.at is None:
            return []
        now, out = time.monotonic(), []
        for stamp in sorted(self._pending):
            arrived, ids, uv, target_uv = self._pending[stamp]
            fix = self._match_fix(stamp)
            # Keyframe fixes come in stamp order: once a later one is in, this one has none (outage).
            later_fix = self._latest_fix_ns is not None and self._latest_fix_ns > stamp + self.p.sync_tolerance_ms * 1e6
            if fix is None and not later_fix and now - arrived < self.p.fix_wait_s:
                break   # keep the order: later keyframes wait behind this one
            if self._waits_for_attitude(stamp) and now - arrived < self.p.fix_wait_s:
                if fix is not None:
                    self._fixes[stamp] = fix   # matched again next time
                break
            del self._pending[stamp]
            if fix is None:
                self.diag.count('keyframes_without_fix')
            out.append(self._record(stamp, ids, uv, fix, target_uv))
        # Fixes older than every pending keyframe will never match.
        oldest = min(self._pending, default=None)
        for s in [s for s in self._fixes if oldest is None or s < oldest - 10**9 * 10]:
            if len(self._fixes) > 200:
                del self._fixes[s]
        return out

    def take_work(self, stopped, wait_s: float = 0.5):
        """For a worker thread: wait until keyframes are ready or a full adjustment was asked for, and take
        them: (batch, full). None once stopped() holds (called with cond held)."""
        with self.cond:
            batch, full = self._ready(), self._full_requested
            while not batch and not full and not stopped():
                self.cond.wait(wait_s)
                batch, full = self._ready(), self._full_requested
            if stopped():
                return None
            self._full_requested = False
            self._busy = True
        return batch, full

    def work_done(self) -> None:
        with self.cond:
            self._busy = False

    def busy(self) -> bool:
        """Keyframes are being adjusted, or could be now (a replay waits for this before it ends)."""
        with self.cond:
            if self._busy or self._full_requested:
                return True
            tol = int(self.p.sync_tolerance_ms * 1e6)
            return any(any(abs(s - stamp) <= tol for s in self._fixes) for stamp in self._pending)

    def drain(self) -> int:
        """Adjust every keyframe ready now (and a full adjustment asked for), in the caller's thread: what a
        worker does, for a caller without one. Returns the number of keyframes taken."""
        with self.cond:
            batch, full = self._ready(), self._full_requested
            self._full_requested = False
        with self.work:
            self.run_batch(batch)
            if full:
                self.full_adjustment()
        return len(batch)

    def run_batch(self, batch: list[KeyframeRecord], process=None) -> None:
        """Older keyframes of a batch get a short window adjustment; the newest the full one, then
        one publication covers the batch. `process(rec, publish)` adjusts one (default `process`)."""
        if not batch:
            return
        process = process or self.process
        for i, rec in enumerate(batch):
            if time.monotonic() > self._cut_at - self.final_adjustment_estimate_s():   # a stopped flight's budget (finish)
                skip_at_end(self.diag, len(batch) - i, WARN)
                break
            process(rec, publish=i == len(batch) - 1 and self._cut_at == float('inf'))   # the final republishes
        if len(batch) > 1:
            self.diag.count('keyframes_caught_up', len(batch) - 1)

    # --- adjustment -------------------------------------------------------------------------------

    def _control_to_map(self) -> None:
        """Surveyed targets into `map`, once: when the origin is configured or set by the first fix."""
        if self.control is None or self._control_in_map or self.at.origin is None:
            return
        self.live.set_surveyed(self.control.in_map(self.at.origin, self.p.gcp_sigma_h_m, self.p.gcp_sigma_v_m))
        self.at.set_control(self.live.adjuster_control())
        self._control_in_map = True

    def _origin_from_control(self) -> None:
        """End of a flight in which no fix came: the map's origin at the control file's GCPs, so that they
        can place the block (3 or more); said on /diagnostics."""
        if self.control is None or self.at.origin is not None:
            return
        origin = self.control.central_origin()
        if origin is not None and self.at.set_origin(origin):
            self.diag.problem('no GNSS fix came in this flight: the map\'s origin is the centre of the control '
                              'file\'s GCPs, and the GCPs alone place the block (3 or more needed)', WARN)
            self._control_to_map()

    def _vet_control(self, final: bool = False) -> None:
        """Check the targets now due against the block (core/control_live.py); each fault is a WARN."""
        if self.live is None:
            return
        try:
            for note in self.live.update(self.at, final):
                self.diag.problem(f'control: {note}', WARN)
        except Exception as exc:   # the control's figures must never stop the adjustment
            self.diag.problem(f'control vetting failed: {type(exc).__name__}: {exc}')

    def process(self, rec: KeyframeRecord, publish: bool = True) -> None:
        """Adjust one keyframe (under `work`); one that is not published (an older one of a batch) gets the
        short catch-up window adjustment."""
        try:
            self._adjusted_whole = False
            rep = self.at.add_keyframe(rec, None if publish else min(self.p.catch_up_iterations,
                                                                      self.p.window_iterations),
                                       block_adjust=self.p.block_adjust_when_behind or (publish and not self._pending))
        except Exception as exc:
            self.diag.count('keyframes_failed')   # a replay's backpressure counts it as done
            self.diag.problem(f'keyframe {rec.stamp_ns} failed: {exc}')
            return
        self._control_to_map()
        self._fix_classes[fix_class(rec.fix)] += 1
        self._health(rep)
        if self.live is not None and rec.target_uv and self.at.block.n_keyframes and self.at.block.keyframe(-1).stamp_ns == rec.stamp_ns:
            # The live accuracy reads these instead of the keyframes' observation tables, which a long
            # flight keeps on disk (reading them would thaw every keyframe).
            self.live.observe(self.at.block.n_keyframes - 1, rec.target_uv)
        if self.at.unplaced_keyframes > self._unplaced:
            n, self._unplaced = self.at.unplaced_keyframes - self._unplaced, self.at.unplaced_keyframes
            self.diag.count('keyframes_unplaced', n)
            self.diag.problem(f'every track was lost early: the {n} keyframes before the break span less than '
                              'their GNSS noise and could not be placed (not oriented); the map holds the flight '
                              'after it', WARN)
        segment_diagnostics(self.diag, self.at.segments, rep.joined)
        if not rep.registered:
            self._not_oriented.count(rep.status, rec.stamp_ns)
        if rep.registered or rep.waiting_oriented:   # and keyframes that waited, oriented with it (by two views too)
            self.diag.count('keyframes_oriented', int(rep.registered) + rep.waiting_oriented)
            if rep.waiting_oriented:
                self._not_oriented.oriented_since(self.at.block, int(rep.registered) + rep.waiting_oriented)
        self.diag.set('keyframes_oriented_two_view', self.at.n_two_view_oriented())
        self._block_moved = self._block_moved or rep.block_adjusted
        if not publish:
            # Queued behind: the figures, the control vetting and the block check wait for the batch's newest.
            if rep.registered:
                self._unpublished += 1
            return
        earlier, self._unpublished = self._unpublished, 0
        self._publish_poses(rec, rep, earlier)   # the poses first: the figures below can wait
        self._report(rep)
        self._vet_control()
        if (self.at.georeferenced and not self.at.georef_provisional
                and self.at.block.n_oriented >= self._checked_at + 10):
            self._checked_at = self.at.block.n_oriented
            self._block_check()

    def _publish_poses(self, rec, rep, earlier: int) -> None:
        """The poses a keyframe's adjustment (and the `earlier` ones of its batch) gave, once georeferenced."""
        if not (self.at.georeferenced and rep.registered):
            return
        if self.at.georef_provisional and not self.p.publish_provisional:
            return
        if not self._published_final and not self.at.georef_provisional:
            # Provisional -> final georeference moved every keyframe: republish them all.
            self._published_final = True
            self._publish_block(rec.stamp_ns)
        elif self._block_moved:
            self._publish_block(rec.stamp_ns, new=1 + earlier)
        else:
            # A segment that joined (core/incremental.py: the flight after every track was lost) is published
            # whole: its keyframes had no pose until now.
            self._publish(window=self.at.block.oriented(last=max(self.p.window_size, rep.joined) + earlier),
                          new=1 + earlier)

    def _report(self, rep) -> None:
        """The window adjustment's figures on diagnostics, and the live quality when due."""
        d = self.diag
        d.set('status', rep.status)
        d.set('solve_time_s', float(rep.solve_s))
        d.set('cost', float(rep.cost))
        d.set('reprojection_rms_px', float(rep.reprojection_rms_px))
        d.set('gnss_residual_rms_m', float(rep.gnss_rms_m))
        d.set('window_size', rep.window_size)
        d.set('points', self.at.block.n_points)
        for k, v in self.at.off_gnss_figures().items():   # the window off its GNSS (core/incremental.py off_gnss)
            if k != 'n' and v is not None:
                d.set({'adjustments': 'off_gnss_adjustments', 'deferred': 'block_adjustments_deferred'}.get(
                    k, f'window_off_gnss_{k}'), v)
        self._set_georeferenced()
        control_diagnostics(self.diag, self.at, self.control, self.live)
        self._since_quality += 1
        if self._since_quality >= self.p.quality_every:
            self.publish_quality()

    def _set_georeferenced(self) -> None:
        """'georeferenced' on diagnostics (the ground station shows a drone's targets by it): True, False or
        provisional."""
        self.diag.set('georeferenced', 'provisional' if self.at.georef_provisional else str(self.at.georeferenced))

    # --- health -----------------------------------------------------------------------------------

    def _health(self, rep=None) -> None:
        """Health that tells the truth: the share of the last health_window keyframes not oriented, and a
        block still without georeference after georef_warn_keyframes keyframes with a fix."""
        at = self.at
        if rep is not None and not rep.registered:
            self._last_failure = rep.status
        recent = at.block.keyframes(last=self.p.health_window)
        n_bad = sum(kf.map_T_cam is None for kf in recent)
        self.diag.set('keyframes_registered', at.block.n_oriented)
        self.diag.set('keyframes_registered_share', at.block.n_oriented / max(at.block.n_keyframes, 1))
        share = n_bad / max(len(recent), 1)
        if len(recent) >= min(5, self.p.health_window) and share > self.p.health_max_unoriented:
            self.diag.problem(f'{n_bad} of the last {len(recent)} keyframes are not oriented (last reason: '
                              f'{self._last_failure})', ERROR if share > 0.5 else WARN)
        with_fix = sum(kf.fix_enu is not None for kf in at.block.keyframes())
        if not at.georeferenced and with_fix >= self.p.georef_warn_keyframes:
            why = (f'{at.block.n_oriented} keyframes oriented' if at.block.n_oriented else 'no keyframe oriented yet')
            self.diag.problem(f'no georeference after {with_fix} keyframes with a GNSS fix ({why}; the fixes must '
                              'spread beyond their noise, and the block must be oriented)',
                              ERROR if with_fix >= 2 * self.p.georef_warn_keyframes else WARN)

    def _block_check(self, adjustment: dict | None = None) -> None:
        """The block's own check on diagnostics (stages/block_health.py), kept for the live quality."""
        self._block_verdict = block_check_on_diagnostics(self.diag, self.at, adjustment)

    # --- live quality -----------------------------------------------------------------------------

    def quality(self) -> dict:
        """The live accuracy figures (map/control_points): stages/live_quality.py `live_quality`."""
        return live_quality(self.at, self.control, self.live, self._fix_classes, self._adjusted_whole,
                            self.p.max_row_residual_px, self._block_verdict)

    def publish_quality(self) -> None:
        """The live quality document out, its figures on diagnostics."""
        self._since_quality = 0
        if self.at is None:
            return
        try:
            q = self.quality()
        except Exception as exc:   # figures must never stop the adjustment
            self.diag.problem(f'live accuracy failed: {type(exc).__name__}: {exc}')
            return
        last = self.at.block.last_oriented()
        stamp = last.stamp_ns if last is not None else 0
        self.out.quality({'stamp_ns': stamp, **q})
        quality_diagnostics(self.diag, q)

    # --- outputs ----------------------------------------------------------------------------------

    def _publish_block(self, stamp_ns: int, new: int = 1) -> None:
        """Every pose (an adjustment moved them all), after the camera they were adjusted with when a full
        adjustment of the pass refined the lens (pass_self_calibration): the stereo node matches with it."""
        self._block_moved = False
        if self.at.block.camera != self._camera_sent:
            self._camera_sent = self.at.block.camera
            self.out.camera(self.at.block.camera, stamp_ns)
        self._publish(window=self.at.block.oriented(), new=new)

    def _publish(self, window, new: int = 1, final: bool = False) -> None:
        """Poses of `window` (`final`: a full adjustment's), the path, the sparse cloud once `new` make cloud_every."""
        at = self.at
        if not self._georef_sent and at.origin is not None:
            o = at.origin
            self.out.georeference(o.lat_deg, o.lon_deg, o.h_m, at.block.keyframe(window[-1]).stamp_ns)
            self._georef_sent = True
        # In flight the covariances are refreshed after the poses (half a window update); after a full one first.
        centre_cov = self._centre_covariances(window) if final else dict(self._centre_cov)
        kfs = [at.block.keyframe(k) for k in window]
        path = [at.block.keyframe(k) for k in at.block.oriented()]
        line = label_provisional(at, kfs, path, self._provisional_stamps, self.diag)
        self.out.poses([(kf.map_T_cam, kf.stamp_ns, pose_covariance(kf, centre_cov.get(kf.kid), line))
                        for kf in kfs])
        if not final:
            self._centre_covariances(window)
        stamp = at.block.keyframe(window[-1]).stamp_ns
        self.out.path([kf.map_T_cam for kf in path], [kf.stamp_ns for kf in path], stamp)
        self._n_since_cloud += new
        if self._n_since_cloud >= self.p.cloud_every:
            self._n_since_cloud = 0
            self.publish_cloud(stamp)

    def _centre_covariances(self, window) -> dict:
        """Keyframe id -> (3, 3) marginal covariance of its camera centre (map ENU, m^2) for the newest
        window_size keyframes of `window`, from one linearisation of the window problem at the
        current estimate (the keyframes sharing its points held, as in the window adjustment). A
        keyframe further back keeps its last one; between recomputations (covariance_every) the last
        ones are reused, and a keyframe without one gets the stand-in. In flight a pose goes out with the
        covariance of the last recomputation before it (its keyframe's first pose: the stand-in; the window's
        next publications carry its marginal)."""
        if not self.p.marginal_covariance or not window:
            return {}
        self._cov_updates += 1
        if (self._cov_updates - 1) % self.p.covariance_every:
            return self._centre_cov
        try:
            t0 = time.perf_counter()
            cov = self.at.centre_covariance(list(window)[-self.p.window_size:])
            self.diag.set('covariance_s', time.perf_counter() - t0)
        except Exception as exc:   # a stand-in covariance is better than no pose
            self.diag.problem(f'pose covariance failed: {type(exc).__name__}: {exc}')
            return {}
        if not cov:
            self.diag.count('covariance_unavailable')
        # Keyframes that left the window keep their last covariance (bounded: the newest 3 windows).
        self._centre_cov.update(cov)
        for k in [k for k in self._centre_cov if k < window[-1] - 3 * self.p.window_size]:
            del self._centre_cov[k]
        return self._centre_cov

    def publish_cloud(self, stamp_ns: int) -> None:
        if not self.at.block.n_points:
            return
        # Hot tracks are those the window and its margin still observe (core/at_block.py): a bounded
        # set on a long flight, where the whole block would grow the message (and DDS's buffers) with it.
        ids = self.at.block.tie_point_ids(hot=self.p.cloud_recent_only)
        if not len(ids):
            return
        self.out.cloud(self.at.block.points_of(ids), stamp_ns, ids)

    # --- end of flight ----------------------------------------------------------------------------

    def finish(self, process=None, budget_s: float = 0.0) -> AdjustmentOutcome:
        """End of flight: every waiting keyframe now, with or without its fix, a second chance against the block for
        those not oriented, the whole block adjusted, every pose republished. `budget_s` > 0 (a stopped flight's,
        stages/end_budget.py): the first two (catch-up adjustment) while the final's estimate fits; the rest said."""
        if self.at is None:
            return AdjustmentOutcome('none', 'no calibration: no keyframe was adjusted')
        process, budget = process or self.process, EndBudget(budget_s)
        self._cut_at = budget.deadline   # no keyframe taken past it: a worker's batch in progress too (run_batch)
        with self.work:   # after the batch the worker may be adjusting
            budget.mark()
            with self.cond:
                waiting = [(s, self._pending.pop(s)) for s in sorted(self._pending)]   # (arrival, ids, uv, targets)
                recs = [self._record(s, w[1], w[2], self._match_fix(s), w[3]) for s, w in waiting]
            for i, rec in enumerate(recs):
                if not budget.fits(self.final_adjustment_estimate_s()):
                    skip_at_end(self.diag, len(recs) - i, WARN)
                    break
                process(rec, publish=not budget.bounded)   # a stopped flight's: the final adjustment publishes
            budget.mark()
            if self.at.block.n_oriented and budget.fits(self.final_adjustment_estimate_s()):
                try:
                    if n := self.at.retry_unregistered():
                        self.diag.count('keyframes_oriented_at_end', n)
                except Exception as exc:   # the full adjustment still runs
                    self.diag.problem(f'second chance of unoriented keyframes failed: {exc}')
            if self.at.block.n_oriented:
                self._origin_from_control()
                self._vet_control(final=True)   # targets seen too seldom to be checked in flight
            budget.mark()
            out = self.full_adjustment()
            self._not_oriented.at_end(self.at.block)
            budget.mark()
            self.end_of_flight = end_times(budget.marks, len(recs), self.diag)
            return out

    def cut_at(self, deadline_s: float) -> None:
        """A stopped flight's end (bundle_node end_budget): no keyframe is taken past `deadline_s` (time.monotonic)
        less the final adjustment's estimate, and none published (the final adjustment republishes every pose)."""
        self._cut_at = deadline_s

    def waiting_keyframes(self) -> int:
        """Keyframes that wait for their fix or their turn."""
        with self.cond:
            return len(self._pending)

    def final_adjustment_estimate_s(self) -> float:
        """What a full adjustment of the keyframes oriented now takes, scaled from the last one (end_budget)."""
        return full_adjustment_estimate_s(self._full_s, self._full_n, self.at.block.n_oriented if self.at else 0)

    def full_adjustment(self) -> AdjustmentOutcome:
        """Adjust the whole block now and republish; the outcome says whether it was made."""
        with self.work:
            out = self._full_adjustment()
            if self.at is not None:
                self._health()
            return out

    def _full_adjustment(self) -> AdjustmentOutcome:
        if self.at is None or not self.at.block.n_oriented:
            return AdjustmentOutcome('none', 'no keyframe was oriented')
        try:
            t0 = time.perf_counter()
            rep = self.at.full_adjustment()
            if rep.status == 'failed':
                raise PhotogramError(f'the solver failed ({self.at.block.n_oriented} keyframes)')
            self._full_s, self._full_n = time.perf_counter() - t0, self.at.block.n_oriented
            self.diag.set('full_adjustment_s', self._full_s)
            self.diag.set('full_adjustment_rms_px', float(rep.reprojection_rms_px))
            self.diag.set('full_adjustment_status', rep.status)
            self._adjusted_whole = True
            self._set_georeferenced()   # the end of a flight without fixes places the block by its GCPs
            if self.at.georeferenced and self.at.georef_provisional:
                self.diag.problem('the georeference is still provisional: the fixes lie on one straight line, so '
                                  'the roll about it is the near-nadir assumption; the poses are published '
                                  'labelled provisional (a turn, or 3 GCPs, makes them final)', WARN)
            if self.at.self_calibration is not None:
                self.diag.set('self_calibration', self.at.self_calibration.text())
            conv = convergence(self.at, rep.status)   # None when it converged
            if conv is not None:
                self.diag.set('full_adjustment_convergence', conv['text'])
                if conv['matters']:
                    self.diag.problem(conv['text'], WARN)
            if self.at.georeferenced:
                self._block_check({'status': rep.status, **({'matters': conv['matters'], 'text': conv['text']}
                                                            if conv else {})})
            control_diagnostics(self.diag, self.at, self.control, self.live)
            self.publish_quality()
            if self.at.georeferenced:
                # The camera first: whoever matches the keyframes with these poses needs the intrinsics they
                # were adjusted with (a self-calibration changes them).
                self._camera_sent = self.at.block.camera
                self.out.camera(self.at.block.camera, self.at.block.last_oriented().stamp_ns)
                self._publish(window=self.at.block.oriented(), new=0, final=True)
                self.publish_cloud(self.at.block.last_oriented().stamp_ns)
            self.diag.count('full_adjustments')   # after publishing: a waiting caller gets the poses
            return AdjustmentOutcome('done', rep.status)
        except Exception as exc:
            self.diag.problem(f'full adjustment failed: {exc}', ERROR)
            return AdjustmentOutcome('failed', f'full adjustment failed: {exc}')

