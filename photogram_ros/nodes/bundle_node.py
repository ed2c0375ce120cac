"""Bundle node: incremental aerial triangulation of the keyframes, with GNSS priors, in flight.

Inputs (relative names, so a namespace per drone works):
  keyframes/features  PointCloud2 table (track_id uint32, u, v, xn, yn), stamped like its keyframe; rows
                      in the target id range (msgs.py) are ArUco targets the tracker found
  keyframes/fix       NavSatFix interpolated to the keyframe time (ENU diagonal covariance,
                      ellipsoidal altitude); optional: a keyframe without a fix is adjusted without
  keyframes/image     Image (only counted: geometry needs the features alone)
  camera/camera_info  CameraInfo (the calibration; keyframes wait for it)
  mavlink/attitude    Imu, body FLU in ENU (optional): each keyframe's orientation prior from it and the camera's
                      mount (camera_mount, mount_rpy_deg); a gimbal's antenna offset (see Lever arm)
  bundle/full_adjustment  std_msgs/Empty: adjust the whole block now (also done on shutdown)
Outputs:
  map/keyframe_pose   PoseWithCovarianceStamped in `map` for the new keyframe and, re-stamped with
                      their own stamps, the refined keyframes of the window (a later pose with the
                      same stamp replaces the earlier one). Before the first turn (a straight first line)
                      the poses are provisional: their covariance carries the provisional roll about the
                      line (core/pose_status.py; msgs.pose_is_provisional), /diagnostics says
                      georeferenced=provisional and poses_provisional; the final ones replace them at the turn
  map/path            nav_msgs/Path of all oriented keyframes
  /tf, /tf_static     the drone's frame tree (core/frames.py: map -> <ns>/odom -> <ns>/base_link ->
                      <ns>/camera_optical), odom -> base_link at each published pose, where tf2_msgs is
                      importable (nodes/tf_publisher.py); without it /diagnostics says so (`tf`)
  map/sparse_cloud    PointCloud2 x, y, z, track_id of the tie points around the window (every
                      `cloud_every` keyframes; `cloud_recent_only` off: the whole block)
  map/georeference    NavSatFix (latched): latitude, longitude and ellipsoidal altitude of the
                      origin of `map` (ENU tangent there). The origin is the configured one or the
                      first keyframe fix. Published once the block is georeferenced.
  map/camera_final    CameraInfo (latched): after each full adjustment, before its poses, the camera they were
                      adjusted with (final_self_calibration refines it; in flight, a full adjustment of the
                      pass that refined the lens, pass_self_calibration, sends it before every pose it
                      moved); the stereo pairs and the products match with it
  map/control_points  std_msgs/String (latched), JSON: the survey's live accuracy every `quality_every`
                      published keyframes and after a full adjustment: each check point intersected from
                      the adjusted cameras against its survey and the check-point RMSE (horizontal,
                      vertical, count), the GCPs' residuals apart (intersected too), every target's
                      detections, the keyframe shares per GNSS fix class, the GNSS bias (3 GCPs or more)
  /diagnostics        solve time, cost, reprojection RMS, GNSS residual RMS, window size; with a
                      control file GCPs seen / used, GCP residual RMS, check points seen, unknown markers,
                      check_rmse_h_m / check_rmse_v_m / checks_measured; keyframe shares per fix class

Health (/diagnostics tells the truth): WARN (ERROR above half) when more than health_max_unoriented of
the last health_window keyframes are not oriented, with the last reason; WARN/ERROR when the block has no
georeference after georef_warn_keyframes keyframes with a fix; WARN when a body lever arm is applied
without an attitude. Fixes without a covariance get one from their GNSS mode (RTK, SBAS, plain 3D), and a
fix under RTK status with more than max_rtk_sigma_m is not used. `finish()` and `full_adjustment()`
return an AdjustmentOutcome ('done', 'failed', 'none'); the console script exits 4 when it failed.

Ground control (`control_file`, io/control_file.py; or the ControlSet a command read, handed by the graph in its
place): targets named in the file become GCPs (point
priors) or check points (never used), in the map frame as soon as its origin is known; markers
the file does not name are counted and ignored. A GCP is held as a check point until the block is
georeferenced for good and control_min_keyframes keyframes have seen it; then its detections and its
survey are checked against the block as the GNSS placed it (core/control_live.py): a far detection is
dropped, a GCP the block contradicts horizontally is not used, one whose height it contradicts is used
horizontally only. Each such fault is a WARN on /diagnostics naming the target, and map/control_points
carries the verdicts ('control': every point's use, the detections not used and why, the faults).

The node is an adapter: the adjustment, its policies, health and quality are the ROS-free stage
(stages/adjustment.py), which it feeds from the topics and whose results it publishes.

Threading: callbacks only queue what arrives; a worker thread of the node runs the adjustments
(numpy/scipy release the GIL in their kernels), so a several-second adjustment never holds an
executor thread. When keyframes queue up behind an adjustment, the older ones of the batch get a
short window adjustment (`catch_up_iterations`) and only the newest the full one, so the node
catches up instead of falling further behind; the poses are published once per batch.

Off its GNSS: the window holds the older keyframes, so a block the first photos of a line (or a segment) turned
would stay turned until landing; once the window sits off its fixes (`off_gnss_sigma`, core/incremental.py) the
whole block is adjusted at once and every pose published again (/diagnostics: off_gnss_adjustments,
window_off_gnss_newest_sigmas, window_off_gnss_mean_sigmas).

Lever arm: `lever_arm_cam_m` (antenna in the camera frame) is fixed, for a camera fixed to the body; a gimbal
gives `lever_arm_body_frd_m` (body frame), turned by `mavlink/attitude` (body FLU in ENU, queued 2 min deep: an
adjustment may hold the executor for seconds) into each keyframe's antenna offset in `map` (core/attitude.py);
without an attitude within 0.2 s, the level-flight camera-frame offset.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, Imu, NavSatFix, PointCloud2
from std_msgs.msg import Empty, String

from photogram_ros import msgs
from photogram_ros.core.control import ControlSet
from photogram_ros.core.incremental import KeyframeRecord
from photogram_ros.errors import PhotogramError
from photogram_ros.nodes.diagnostics import ERROR, Diagnostics
from photogram_ros.nodes.node_main import run_node
from photogram_ros.nodes.ros_params import declare
from photogram_ros.nodes import qos, tf_publisher
from photogram_ros.nodes.stage_diagnostics import StageDiagnostics
from photogram_ros.nodes.tf_publisher import TfPublisher
from photogram_ros.stages.adjustment import (  # noqa: F401  (the node's names for the stage's)
    PLAIN_FIX_SIGMA_M, UNKNOWN_FIX_SIGMA_M, AdjustmentOutcome, AdjustmentParams, AdjustmentStage, Outputs,
    fix_sigma_limit_m, pose_covariance, unknown_fix_covariance)

TOPIC_FEATURES = 'keyframes/features'
TOPIC_FIX = 'keyframes/fix'
TOPIC_IMAGE = 'keyframes/image'
TOPIC_INFO = 'camera/camera_info'
TOPIC_FULL = 'bundle/full_adjustment'
TOPIC_POSE = 'map/keyframe_pose'
TOPIC_PATH = 'map/path'
TOPIC_CLOUD = 'map/sparse_cloud'
TOPIC_GEOREF = 'map/georeference'
TOPIC_ATTITUDE = 'mavlink/attitude'
TOPIC_CONTROL_POINTS = 'map/control_points'
TOPIC_CAMERA_FINAL = 'map/camera_final'


@dataclass
class BundleNodeParams(AdjustmentParams):
    """The node's parameters: the adjustment stage's (stages/adjustment.py)."""


class _Publishers(Outputs):
    """The stage's results as messages on the node's topics."""

    def __init__(self, node: Node):
        self.pose = node.create_publisher(PoseWithCovarianceStamped, TOPIC_POSE, qos.reliable(50))
        self._path = node.create_publisher(Path, TOPIC_PATH, qos.reliable(2))
        self._cloud = node.create_publisher(PointCloud2, TOPIC_CLOUD, qos.reliable(2))
        self.georef = node.create_publisher(NavSatFix, TOPIC_GEOREF, qos.latched())
        self._quality = node.create_publisher(String, TOPIC_CONTROL_POINTS, qos.latched())
        self._camera = node.create_publisher(CameraInfo, TOPIC_CAMERA_FINAL, qos.latched())
        self.tf = TfPublisher(node)

    def georeference(self, lat_deg, lon_deg, h_m, stamp_ns):
        self.georef.publish(msgs.georeference_msg(lat_deg, lon_deg, h_m, stamp_ns))

    def poses(self, poses):
        poses = list(poses)
        for map_T_cam, stamp_ns, cov in poses:
            self.pose.publish(msgs.pose_with_covariance_from_T(map_T_cam, stamp_ns, 'map', cov))
        self.tf.poses(poses)

    def path(self, map_T_cams, stamps_ns, stamp_ns):
        self._path.publish(msgs.path_msg(map_T_cams, stamps_ns, stamp_ns))

    def cloud(self, points_map, stamp_ns, track_ids):
        self._cloud.publish(msgs.sparse_cloud_msg(points_map, stamp_ns, track_ids))

    def quality(self, doc):
        self._quality.publish(msgs.json_msg(doc))

    def camera(self, camera, stamp_ns):
        self._camera.publish(msgs.camera_info_msg(camera, stamp_ns))


class BundleNode(Node):
    _covariance = staticmethod(pose_covariance)

    def __init__(self, overrides: dict | None = None, control: ControlSet | None = None, **node_kwargs):
        """`control`: the flight's surveyed targets as a command read them (`replay`/`run --gcp`, through the
        graph), taken in place of the control_file parameter; None: the stage reads control_file."""
        super().__init__('bundle_node', **node_kwargs)
        self.p = declare(self, BundleNodeParams, overrides)
        self.diag = Diagnostics(self)
        # A bad control file stops the start, naming the line.
        self.outputs = _Publishers(self)
        self.stage = AdjustmentStage(self.p, StageDiagnostics(self.diag), self.outputs, control=control)
        if not self.outputs.tf.available:
            self.diag.set('tf', tf_publisher.NOT_AVAILABLE)
        # Fixes first: the executor serves ready subscriptions in creation order, and a burst of
        # features must not keep their fixes waiting.
        self.create_subscription(NavSatFix, TOPIC_FIX, self._on_fix, qos.reliable(50))
        self.create_subscription(PointCloud2, TOPIC_FEATURES, self._on_features, qos.reliable(50))
        self.create_subscription(Image, TOPIC_IMAGE, lambda m: self.diag.count('images'), qos.reliable(50))
        self.create_subscription(CameraInfo, TOPIC_INFO, self._on_info, qos.reliable(5))
        self.create_subscription(Empty, TOPIC_FULL, self._on_full, qos.reliable(2))
        # Every camera: the attitude gives each keyframe its orientation prior (and a gimbal its antenna offset).
        self.create_subscription(Imu, TOPIC_ATTITUDE, self._on_attitude,
                                 qos.reliable(1200))
        # The timer only wakes the worker: a keyframe whose fix never comes is taken after fix_wait_s.
        self.create_timer(0.5, self._wake)
        self._stop = False
        self._worker = threading.Thread(target=self._run, name='bundle_worker', daemon=True)
        self._worker.start()

    @property
    def at(self):
        """The adjuster (core/incremental.py IncrementalAT), None until the camera_info came."""
        return self.stage.at

    @property
    def control(self):
        return self.stage.control

    def waiting_keyframes(self) -> int:
        """Keyframes waiting for their fix (bench/replay_probe.py counts them)."""
        return self.stage.waiting_keyframes()

    @property
    def live(self):
        return self.stage.live

    # --- inputs ---------------------------------------------------------------------------------

    def _on_info(self, msg: CameraInfo) -> None:
        if self.stage.camera is not None:
            return
        try:
            camera = msgs.camera_from_info(msg)
        except PhotogramError as exc:
            self.diag.problem(f'bad camera_info: {exc}', ERROR)
            return
        self.stage.set_camera(camera)

    def _on_fix(self, msg: NavSatFix) -> None:
        try:
            f = msgs.fix_from_navsatfix(msg)
            self.stage.add_fix(f['stamp_ns'], f['lat_deg'], f['lon_deg'], f['h_m'], f['covariance_enu_m2'],
                               int(f['status']), int(f['covariance_type']))
        except Exception as exc:  # one bad message must not stop the node
            self.diag.problem(f'bad keyframe fix: {exc}')

    def _on_features(self, msg: PointCloud2) -> None:
        try:
            obs, targets = msgs.keyframe_table_from_msg(msg)
            self.stage.add_keyframe(msgs.ns_from_time(msg.header.stamp), obs['track_id'],
                                    np.column_stack([obs['u'], obs['v']]), targets)
        except Exception as exc:
            self.diag.problem(f'bad keyframe features: {exc}')

    def _on_attitude(self, msg) -> None:
        try:
            q, _ = msgs.orientation_from_imu(msg)
            self.stage.add_attitude(msgs.ns_from_time(msg.header.stamp), q)
        except Exception as exc:
            self.diag.problem(f'bad attitude: {exc}')

    def _on_full(self, _msg) -> None:
        self.stage.request_full_adjustment()

    def _wake(self) -> None:
        self.stage.wake()

    # --- the worker -------------------------------------------------------------------------------

    def _run(self) -> None:
        """The worker: adjusts what the stage hands out, and full adjustments asked for on the topic."""
        while True:
            got = self.stage.take_work(lambda: self._stop)
            if got is None:
                return
            batch, full = got
            try:
                with self.stage.work:
                    self._process_batch(batch)
                    if full:
                        self.full_adjustment()
            except Exception as exc:   # the worker must survive anything one keyframe can do
                self.diag.problem(f'bundle worker: {type(exc).__name__}: {exc}', ERROR)
            finally:
                self.stage.work_done()

    def busy(self) -> bool:
        """Keyframes are being adjusted, or could be now (a replay waits for this before it ends)."""
        return self.stage.busy()

    def _process_batch(self, batch: list[KeyframeRecord]) -> None:
        self.stage.run_batch(batch, self._process)

    def _process(self, rec: KeyframeRecord, publish: bool = True) -> None:
        self.stage.process(rec, publish)

    # --- outputs ----------------------------------------------------------------------------------

    def quality(self) -> dict:
        """The live accuracy figures (map/control_points)."""
        return self.stage.quality()

    def publish_quality(self) -> None:
        self.stage.publish_quality()

    def finish(self, budget_s: float = 0.0) -> AdjustmentOutcome:
        """End of flight (called by the graph): every waiting keyframe now, the second chance of those not
        oriented, the final adjustment and every pose again (stages/adjustment.py; `budget_s` > 0: a stopped
        flight's share, what does not fit left out and said). Its outcome; the step times logged."""
        out = self.stage.finish(self._process, budget_s)
        self.get_logger().info(f'end of flight: {getattr(self.stage, "end_of_flight", "")}'
                               + (f' (budget {budget_s:.0f} s)' if budget_s > 0 else ''))
        return out

    def end_budget(self, budget_s: float) -> None:
        """A stopped flight's end begins (Graph.finish_flight): the worker takes no keyframe past `budget_s` from
        now less the final adjustment's estimate, and publishes none (the final adjustment republishes every pose),
        so that its batch in progress fits in the budget (stages/adjustment.py run_batch)."""
        self.stage.cut_at(time.monotonic() + max(budget_s, 0.0))

    def full_adjustment(self) -> AdjustmentOutcome:
        """Adjust the whole block now and republish; the outcome says whether it was made."""
        return self.stage.full_adjustment()

    def destroy_node(self):
        with self.stage.cond:
            self._stop = True
            self.stage.cond.notify_all()
        self._worker.join(timeout=30.0)
        return super().destroy_node()


EXIT_FINAL_ADJUSTMENT_FAILED = 4    # as `photogram-ros run` (commands/run.py EXIT_FINISH_FAILED)


def main(argv=None) -> int:
    """Console script `bundle_node`: at the stop the final adjustment (full_adjustment_on_shutdown); its
    failure is printed and makes the exit status 4."""
    outcome = []

    def on_exit(node):
        if node.p.full_adjustment_on_shutdown:
            outcome.append(node.full_adjustment())
            if outcome[-1].failed:
                print(f'bundle_node: {outcome[-1].reason}', file=sys.stderr, flush=True)

    rc = run_node(BundleNode, argv, on_exit=on_exit)
    return rc or (EXIT_FINAL_ADJUSTMENT_FAILED if outcome and outcome[-1].failed else 0)


if __name__ == '__main__':
    sys.exit(main())
