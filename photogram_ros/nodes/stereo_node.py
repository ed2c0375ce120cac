"""Stereo node: pairs posed keyframes, computes dense depth, publishes each pair's cloud in `map`.

Inputs: /keyframes/image (Image; at a reduction of the camera_info's size, e.g. tracker_node's
keyframe_image_reduction, the camera is scaled to it and the matching downscale follows, so pairs are matched
at the resolution the GSD settings say; what the node holds per keyframe is that reduced image), /map/keyframe_pose (PoseWithCovarianceStamped in `map`, stamped
like its keyframe image; a later pose with the same stamp is a refinement and replaces the older
one), /camera/camera_info, /map/camera_final (the camera the bundle adjuster's full adjustment adjusted its
poses with: pairs made after it use that one). Output: /map/dense_cloud (PointCloud2 x, y, z float32 as RViz2 draws them,
rgb, confidence) per pair, each preceded by /map/dense_cloud_pose (the newer keyframe's pose the cloud is placed
with, with that pose's covariance: provisional or final as the adjuster labelled it, core/pose_status.py),
optionally /stereo/disparity, and /diagnostics.

When a keyframe pairs: with its final pose, or with pair_provisional (on by default) its provisional one too
(before the first turn the georeference is an assumption, but the pair's relative pose, all its depth depends
on, is not; the map node places the cloud again when the pose turns final: map replace_provisional), and its
older partners
of the same status, once its pose has settled relative to the keyframe before it: its last refinement moved it,
relative to that keyframe, less than settle_move_m and settle_min_keyframes newer keyframes have poses, or its
pose stood still for settle_s (the flight's end), or at the latest settle_keyframes newer keyframes have poses.
The cloud goes out placed with the pose of the moment; when that pose moves later (the georeference made final at
the turn, a refinement), the map node places the cloud again (stages/map.py replace_moved). A keyframe waiting for
its pose is the last evicted by max_keyframes.

The pace (core/pace.py, config/companion.yaml): with `worker_nice` the pairs are matched in a worker thread
of that niceness (the callbacks only record and wake it); with `cpu_share` the matching keeps to that share
of a core, and a keyframe that settles while stereo is over it has its pairs shed (`keyframes_shed`, a WARN)
but stays a partner of later keyframes; a pair whose turn comes more than max_pair_lag_s after its keyframe's
final pose (stereo starved of CPU, behind) is shed the same way (pairs_shed_late); the matching after landing (io/densify.py) plans and matches every
pair again from the stored keyframes. The end of flight (`flush`) sheds nothing. A keyframe the planner finds no
partner for makes no cloud of its own: counted in keyframes_no_partner (earlier keyframes, none passing the
criteria) or keyframes_no_earlier_partner (none of its status paired before it).
"""

from __future__ import annotations

import bisect
import sys
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, NavSatFix, PointCloud2
from stereo_msgs.msg import DisparityImage

from photogram_ros import msgs
from photogram_ros.core import gsd, offheap, stereo
from photogram_ros.core.pace import CpuShare, ThreadCaps, limit_threads, nice_this_thread
from photogram_ros.core.pairs import BELOW_GROUND, PairCriteria, PlannedPair, plan_pairs
from photogram_ros.core.placements import pose_move_m
from photogram_ros.errors import PhotogramError
from photogram_ros.nodes import qos
from photogram_ros.nodes.diagnostics import Diagnostics, steady_timer
from photogram_ros.nodes.node_main import run_node
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param

TOPIC_IMAGE = 'keyframes/image'
TOPIC_POSE = 'map/keyframe_pose'
TOPIC_INFO = 'camera/camera_info'
TOPIC_CAMERA_FINAL = 'map/camera_final'
TOPIC_CLOUD = 'map/dense_cloud'
TOPIC_CLOUD_POSE = 'map/dense_cloud_pose'
TOPIC_DISPARITY = 'stereo/disparity'
TOPIC_SPARSE = 'map/sparse_cloud'
TOPIC_FIX = 'keyframes/fix'


@dataclass
class StereoNodeParams(stereo.StereoParams, PairCriteria, ThreadCaps):
    """The matcher's (core/stereo.py) and the pair planner's (core/pairs.py) parameters, and the node's:
    where the ground height and tie points come from, the keyframes it holds, when it pairs them."""
    ground_height_m: float = param(0.0, 'expected ground height in map (z, m), centre of the depth search; '
                                        'used until the sparse cloud gives it (see ground_from_sparse_cloud)',
                                   min=-1e4, max=1e4)
    ground_from_sparse_cloud: bool = param(True, f'take the ground height from the median of {TOPIC_SPARSE} '
                                                 '(the map origin is often the first fix, in the air); keyframes '
                                                 'wait for the first sparse cloud')
    max_keyframes: int = param(80, 'keyframes kept as stereo partners (memory bound), oldest dropped',
                               min=2, max=10000)
    max_position_sigma_m: float = param(2.0, 'keyframes whose pose position sigma (3D) is larger than this and '
                                             'than fix_sigma_factor times their GNSS fix\'s make no pairs, m',
                                        min=0.0, max=1e4)
    fix_sigma_factor: float = param(3.0, f'the pose sigma limit follows the GNSS mode: a keyframe is refused when its '
                                         f'pose sigma exceeds max(max_position_sigma_m, this x the 3D sigma of its '
                                         f'fix on {TOPIC_FIX}): an RTK flight keeps max_position_sigma_m, a plain '
                                         f'3D fix (~2-4 m) is refused only when the adjustment placed it much '
                                         f'worse than its fix; 0: max_position_sigma_m alone', min=0.0, max=100.0)
    publish_disparity: bool = param(False, f'also publish each pair\'s disparity on {TOPIC_DISPARITY}')
    settle_keyframes: int = param(10, 'the longest a keyframe waits for its pairs: once this many newer keyframes '
                                      'have poses it has left the bundle window and its pose no longer '
                                      'changes (match the bundle window_size; 0 pairs at once)', min=0, max=1000)
    settle_min_keyframes: int = param(1, 'a keyframe pairs earlier, once this many newer keyframes have poses '
                                         'and its last pose refinement moved it less than settle_move_m relative to '
                                         'the keyframe before it (its pose has settled in the window); >= settle_keyframes: only settle_keyframes',
                                      min=0, max=1000)
    settle_move_m: float = param(0.05, 'a pose refinement moving the keyframe less than this has settled it: the '
                                       'camera centre\'s shift plus its height above the ground times the rotation '
                                       '(rad), m', min=0.0, max=100.0)
    settle_s: float = param(5.0, 'a keyframe whose pose has not moved by settle_move_m for this long pairs '
                                 'whatever came after it (the flight\'s end, a pause), s (steady clock; 0: never)',
                            min=0.0, max=3600.0)
    cpu_share: float = param(0.0, 'share of one core the pairs may take over cpu_share_window_s (0: no limit); '
                                  'over it, the pairs of a keyframe that settles are shed (counted in '
                                  'keyframes_shed, a WARN on /diagnostics) and left to the matching after landing '
                                  '(export --densify, replay\'s map_final), so the pose chain keeps the pace',
                             min=0.0, max=256.0)
    cpu_share_window_s: float = param(20.0, 'the window of cpu_share, s', min=1.0, max=3600.0)
    max_pair_lag_s: float = param(10.0, 'a pair whose newer keyframe got its first pose to pair with longer ago than this when its '
                                        'turn comes is shed (stereo is behind: the live map stays current, with a '
                                        'gap there, counted in pairs_shed_late and keyframes_shed, a WARN) and left '
                                        'to the matching after landing; the end of flight sheds nothing; 0: never',
                                  min=0.0, max=3600.0)
    pair_provisional: bool = param(True, 'pair keyframes with provisional poses (before the first turn; labelled '
                                         f'in their covariance): the cloud goes out placed with that pose, said '
                                         f'provisional on {TOPIC_CLOUD_POSE}, and the map places it again once the '
                                         'pose is final (map replace_provisional or replace_move_m > 0); false: wait '
                                         'for the final pose (the first line\'s clouds wait for the first turn)')
    worker_nice: int = param(0, 'match pairs in a worker thread of this niceness (yielding to the pose chain in the '
                                'same process); 0: in the subscription callbacks', min=0, max=19)


@dataclass
class _Keyframe:
    stamp_ns: int
    image: np.ndarray | None = None
    map_T_cam: np.ndarray | None = None
    covariance: np.ndarray | None = None   # of its latest pose (6x6), as published: it carries the provisional label
    provisional: bool = False
    rel_stamp: int = 0                     # the posed keyframe before it when its pose last came
    rel_T: np.ndarray | None = None        # its pose relative to that keyframe then (settle_move_m's measure)
    sigma_m: float = 0.0
    fix_sigma_m: float = float('nan')   # 3D sigma of its GNSS fix (NaN: none came)
    paired: bool = False
    last_move_m: float = float('inf')   # how far the last pose refinement moved it (settle_move_m's measure)
    moved_at: float = 0.0               # steady time of the pose's last move of settle_move_m or more
    final_at: float = 0.0               # steady time of its first pose it may pair with
    shed: bool = False                  # some of its pairs were shed
    paired_T: np.ndarray | None = None  # the pose its pairs were matched with

    @property
    def complete(self) -> bool:
        return self.image is not None and self.map_T_cam is not None


@dataclass
class _PairJob:
    """A planned pair with the poses it is matched and placed with (those of its planning)."""
    pair: PlannedPair
    a_T: np.ndarray
    b_T: np.ndarray
    b_covariance: np.ndarray | None


class StereoNode(Node):
    def __init__(self, overrides: dict | None = None, **node_kwargs):
        super().__init__('stereo_node', **node_kwargs)
        p = self.params = declare(self, StereoNodeParams, overrides)
        self.diag = Diagnostics(self)
        self.camera = None
        self._kf: OrderedDict[int, _Keyframe] = OrderedDict()
        self._ms: list[float] = []
        self.create_subscription(Image, TOPIC_IMAGE, self._on_image, qos.keyframes(20))
        self.create_subscription(PoseWithCovarianceStamped, TOPIC_POSE, self._on_pose, qos.keyframes(20))
        self.create_subscription(CameraInfo, TOPIC_INFO, self._on_info, qos.sensor_data(5))
        self._camera_final = False   # the full adjustment's camera came: camera_info no longer replaces it
        self.create_subscription(CameraInfo, TOPIC_CAMERA_FINAL, self._on_final_camera, qos.latched())
        self.ground_m = None if p.ground_from_sparse_cloud else p.ground_height_m
        self._tie_points = np.zeros((0, 3))   # the newest sparse cloud, map (m)
        self._flushing = False
        self._flush_deadline = float('inf')   # a stopped flight's end: pairs past it are left out (flush)
        self._posed: list[int] = []   # stamps of keyframes with a pose, sorted
        self._moved_after_pairs_m = 0.0   # the most a pose moved after its pairs were matched
        if p.ground_from_sparse_cloud:
            self.create_subscription(PointCloud2, TOPIC_SPARSE, self._on_sparse, qos.reliable(2))
        if p.fix_sigma_factor > 0:
            self.create_subscription(NavSatFix, TOPIC_FIX, self._on_fix, qos.keyframes(20))
        self.gsd: gsd.GsdSettings | None = None   # derived at the first pair (or never: every length was set)
        self._matching: StereoNodeParams | None = None if gsd.unresolved(p) else p
        self.cloud_pose_pub = self.create_publisher(PoseWithCovarianceStamped, TOPIC_CLOUD_POSE, qos.reliable(20))
        self.cloud_pub = self.create_publisher(PointCloud2, TOPIC_CLOUD, qos.reliable(20))
        self.disp_pub = (self.create_publisher(DisparityImage, TOPIC_DISPARITY, qos.reliable(5))
                         if p.publish_disparity else None)
        for k, v in limit_threads(p.cv_threads, p.blas_threads).items():
            self.diag.set(k, v)
        self.share = CpuShare(p.cpu_share, p.cpu_share_window_s)
        if p.settle_s > 0:
            steady_timer(self, min(1.0, p.settle_s), self._on_settle_timer)
        # With worker_nice the pairing runs in a worker thread; the callbacks only record and wake it.
        self._lock = threading.RLock()
        self._wake = threading.Condition(self._lock)
        self._stop = False
        self._wanted = False     # the worker has keyframes to look at
        self._running = False    # the worker is matching a batch (outside the lock)
        self._worker = None
        if p.worker_nice > 0:
            self._worker = threading.Thread(target=self._run_worker, name='stereo_pairs', daemon=True)
            self._worker.start()

    def _run_worker(self) -> None:
        """Plan under the lock, match outside it: the callbacks (executor threads the adjuster shares in the
        mapping process) never wait for a pair."""
        self.diag.set('worker_nice', nice_this_thread(self.params.worker_nice))
        while True:
            with self._lock:
                while not self._wanted and not self._stop:
                    self._wake.wait(0.5)
                if self._stop:
                    return
                self._wanted, todo = False, []
                self._pair_pending(todo)
                self._running = bool(todo)
            try:
                for a, b, pair in todo:
                    self._run_pair(a, b, pair)
            finally:
                with self._lock:
                    self._running = False
                    self._wake.notify_all()

    def destroy_node(self) -> None:
        if self._worker is not None:
            with self._lock:
                self._stop = True
                self._wake.notify_all()
            self._worker.join(timeout=30.0)
        super().destroy_node()

    # --- inputs ----------------------------------------------------------------------------------

    def _entry(self, stamp_ns: int) -> _Keyframe:
        kf = self._kf.get(stamp_ns)
        if kf is None:
            kf = self._kf[stamp_ns] = _Keyframe(stamp_ns)
            # Bounded memory: drop the oldest keyframe that is paired or has no image; only when every kept one
            # is an image waiting for its pairs, the oldest of those (its pose came too late, or never).
            while len(self._kf) > self.params.max_keyframes:
                stamp = next((s for s, o in self._kf.items() if o.paired or o.image is None), None)
                if stamp is None:
                    stamp = next(iter(self._kf))
                old = self._kf.pop(stamp)
                if old.map_T_cam is not None:
                    self._posed.remove(stamp)
                self.diag.count('keyframes_dropped')
                # An image that never made a pair: its pose came too late (a lagging adjuster) or never.
                # (Pose-only entries, e.g. the full adjustment republishing every pose, are no loss.)
                if old.image is not None and not old.paired:
                    self.diag.count('keyframes_dropped_unpaired')
        return kf

    def _on_info(self, msg: CameraInfo, final: bool = False) -> None:
        if self._camera_final and not final:
            return
        try:
            cam = msgs.camera_from_info(msg)
        except PhotogramError as exc:
            self.diag.problem(f'bad camera_info: {exc}')
            return
        with self._lock:
            self._camera_final = self._camera_final or final
            first = self.camera is None
            self.camera = cam
            if first:
                self._pair_soon(None)

    def _on_final_camera(self, msg: CameraInfo) -> None:
        """The camera the poses of a full adjustment were adjusted with: the keyframes paired from now on
        are matched with it (they hold those poses)."""
        self._on_info(msg, final=True)

    def _on_image(self, msg: Image) -> None:
        try:
            img = msgs.image_from_msg(msg)
            if img.ndim == 3 and img.shape[2] != 3:
                raise PhotogramError(f'keyframe image has {img.shape[2]} channels; publish bgr8 or mono8')
            with self._lock:
                kf = self._entry(msgs.ns_from_time(msg.header.stamp))
                # Held until max_keyframes newer ones came: off the heap, where it would pin the pairs'
                # temporaries around it (core/offheap.py).
                kf.image = offheap.copy(img)
                self.diag.count('images')
                self._pair_soon(kf)
        except Exception as exc:  # one bad keyframe must not stop the node
            self.diag.problem(f'keyframe image rejected: {exc}')

    def _on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        try:
            if msg.header.frame_id not in ('map', '/map'):
                raise PhotogramError(f'keyframe pose is in frame {msg.header.frame_id!r}, expected map')
            provisional = msgs.pose_is_provisional(msg)
            if provisional and not self.params.pair_provisional:
                # The roll about the first line is not known yet: no depth from it; the turn republishes it final.
                self.diag.count('poses_provisional_held')
                return
            T, cov = msgs.T_from_pose_with_covariance(msg)
            with self._lock:
                kf = self._entry(msgs.ns_from_time(msg.header.stamp))
                if provisional:
                    self.diag.count('poses_provisional')
                if kf.map_T_cam is None:
                    bisect.insort(self._posed, kf.stamp_ns)
                    kf.final_at = time.monotonic()
                else:
                    kf.last_move_m = self._relative_move_m(kf, T)
                    if kf.paired and kf.paired_T is not None and kf.provisional == provisional:
                        # How far the pose moved after its pairs were matched (the map places the cloud again).
                        self._moved_after_pairs_m = max(self._moved_after_pairs_m, self.pose_move_m(kf.paired_T, T))
                        self.diag.set('pose_moved_after_pairs_max_m', round(self._moved_after_pairs_m, 3))
                if kf.map_T_cam is None or kf.last_move_m >= self.params.settle_move_m:
                    kf.moved_at = time.monotonic()
                self._remember_relative(kf, T)
                kf.map_T_cam, kf.covariance, kf.provisional = T, cov, provisional
                kf.sigma_m = float(np.sqrt(max(np.trace(cov[:3, :3]), 0.0)))
                self.diag.count('poses')
                # A new newest pose may settle older keyframes; a refinement may settle this one.
                self._pair_soon(None if self._newer_posed(kf) == 0 else kf)
        except Exception as exc:
            self.diag.problem(f'keyframe pose rejected: {exc}')

    def _on_fix(self, msg: NavSatFix) -> None:
        try:
            cov = np.asarray(msg.position_covariance, float).reshape(3, 3)
            if msg.position_covariance_type == NavSatFix.COVARIANCE_TYPE_UNKNOWN or msg.status.status < 0:
                return
            with self._lock:
                kf = self._entry(msgs.ns_from_time(msg.header.stamp))
                kf.fix_sigma_m = float(np.sqrt(max(np.trace(cov), 0.0)))
        except Exception as exc:
            self.diag.problem(f'keyframe fix rejected: {exc}')

    def sigma_limit_m(self, kf: _Keyframe) -> float:
        """The pose sigma above which `kf` makes no pairs: max_position_sigma_m, or fix_sigma_factor times its
        fix's sigma when that is larger (the limit follows the GNSS mode)."""
        p = self.params
        if p.fix_sigma_factor > 0 and np.isfinite(kf.fix_sigma_m):
            return max(p.max_position_sigma_m, p.fix_sigma_factor * kf.fix_sigma_m)
        return p.max_position_sigma_m

    def _matching_params(self, kf: _Keyframe) -> StereoNodeParams:
        """The parameters with the GSD-bound lengths derived at the first pair (stated in the log and on
        /diagnostics), from the camera and the posed keyframes' median height above the ground."""
        if self._matching is None:
            cam = self.camera   # the full resolution's GSD, whatever the keyframe images' reduction
            z = [self._kf[s].map_T_cam[2, 3] for s in self._posed if s in self._kf]
            height = float(np.median(z) if z else kf.map_T_cam[2, 3]) - self.ground_m
            self.gsd = gsd.derive(cam.width, cam.height, cam.fx, height, self.params.downscale)
            self._matching, names = gsd.resolve(self.params, self.gsd)
            self.get_logger().info(f'settings from the GSD ({", ".join(names)}): {self.gsd.summary()}')
            self.diag.set('gsd_m', self.gsd.gsd_m)
            self.diag.set('gsd_settings', ', '.join(f'{n} {getattr(self._matching, n):g}' for n in names))
        return self._matching

    def _newer_posed(self, kf: _Keyframe) -> int:
        return len(self._posed) - bisect.bisect_right(self._posed, kf.stamp_ns)

    def pose_move_m(self, before: np.ndarray, after: np.ndarray) -> float:
        """How far a pose refinement moved a keyframe: the camera centre's shift plus its height above the
        ground times the rotation angle (the shift of the ground under it), m."""
        return pose_move_m(before, after, self.ground_m or 0.0)

    def _before(self, kf: _Keyframe) -> _Keyframe | None:
        """The posed keyframe just older than `kf`."""
        i = bisect.bisect_left(self._posed, kf.stamp_ns)
        return self._kf.get(self._posed[i - 1]) if i > 0 else None

    def _remember_relative(self, kf: _Keyframe, map_T_cam: np.ndarray) -> None:
        prev = self._before(kf)
        kf.rel_stamp = prev.stamp_ns if prev is not None else 0
        kf.rel_T = np.linalg.inv(prev.map_T_cam) @ map_T_cam if prev is not None else None

    def _relative_move_m(self, kf: _Keyframe, map_T_cam: np.ndarray) -> float:
        """How far a pose refinement moved `kf` relative to the posed keyframe before it (what a pair's depth
        depends on; the block moving as a whole, e.g. its georeference made final, does not count); the
        absolute move when it has no such keyframe or another one than last time."""
        prev = self._before(kf)
        if prev is None or kf.rel_T is None or prev.stamp_ns != kf.rel_stamp:
            return self.pose_move_m(kf.map_T_cam, map_T_cam)
        rel = np.linalg.inv(prev.map_T_cam) @ map_T_cam
        # Both relative poses expressed at the older keyframe's current pose: a move in map units.
        return self.pose_move_m(prev.map_T_cam @ kf.rel_T, prev.map_T_cam @ rel)

    def _settled(self, kf: _Keyframe) -> bool:
        """Whether `kf`'s pose has settled enough to pair it (the settle_* parameters)."""
        p = self.params
        newer = self._newer_posed(kf)
        if newer >= p.settle_keyframes:
            return True
        if newer >= p.settle_min_keyframes and kf.last_move_m < p.settle_move_m:
            self.diag.count('keyframes_settled_early')
            return True
        if p.settle_s > 0 and time.monotonic() - kf.moved_at >= p.settle_s:
            self.diag.count('keyframes_settled_still')
            return True
        return False

    def _on_settle_timer(self) -> None:
        """Keyframes whose pose stood still for settle_s pair even when no newer keyframe comes."""
        with self._lock:
            if any(not kf.paired and kf.complete for kf in self._kf.values()):
                self._pair_soon(None)

    def flush(self, budget_s: float = 0.0) -> None:
        """End of flight: pair every keyframe still waiting, with the poses it has now (nothing is shed: the
        flight no longer needs the CPU). `budget_s` > 0 (a stopped flight's part of run --stop-budget-s): the
        pairs whose turn comes after it are left out, counted in pairs_skipped_end_budget and said (export
        --densify matches every pair from the final poses)."""
        with self._lock:
            self._flushing = True
            self._flush_deadline = time.monotonic() + budget_s if budget_s > 0 else float('inf')
            if self.ground_m is None:
                self.ground_m = self.params.ground_height_m
            while self._running:   # the worker's batch goes out first
                self._wake.wait(0.5)
            self._pair_pending()
            skipped = self.diag.counts().get('pairs_skipped_end_budget', 0)
            if skipped:
                self.diag.problem(f'end of flight: {skipped} stereo pairs left out (the stopped flight\'s budget, '
                                  'run --stop-budget-s): the in-flight map has gaps there; photogram-ros export '
                                  'MAPDIR --densify matches every pair from the final poses')

    def _on_sparse(self, msg: PointCloud2) -> None:
        try:
            pts = msgs.points_from_pointcloud2(msg)
            xyz = np.column_stack([pts['x'], pts['y'], pts['z']]).astype(float)
            xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
            z = xyz[:, 2]
            if z.size < 20:
                return
            with self._lock:
                self._tie_points = xyz
                first = self.ground_m is None
                self.ground_m = float(np.median(z))
                self.diag.set('ground_height_m', self.ground_m)
                if first:
                    self._pair_soon(None)
        except Exception as exc:
            self.diag.problem(f'sparse cloud rejected: {exc}')

    # --- pairing ---------------------------------------------------------------------------------

    def _pair_soon(self, kf: _Keyframe | None) -> None:
        """Pair `kf` (None: every keyframe waiting) now, or wake the worker (worker_nice). Under the lock."""
        if self._worker is not None:
            self._wanted = True
            self._wake.notify_all()
        elif kf is None:
            self._pair_pending()
        else:
            self._maybe_pair(kf)

    def _pair_pending(self, todo: list | None = None) -> None:
        for kf in list(self._kf.values()):
            self._maybe_pair(kf, todo)

    def _camera_for(self, image: np.ndarray):
        cam = self.camera
        h, w = image.shape[:2]
        if (w, h) != (cam.width, cam.height) and abs(w / cam.width - h / cam.height) < 1e-3:
            cam = cam.scaled(w / cam.width)   # keyframes published at a reduced resolution
        return cam

    def _maybe_pair(self, kf: _Keyframe, todo: list | None = None) -> None:
        """Pair `kf` if it is due: its pairs matched now, or (a, b, pair) appended to `todo` for the worker."""
        if kf.paired or not kf.complete or self.ground_m is None:
            return
        if not self._flushing and not self._settled(kf):
            return
        if self.camera is None:
            self.diag.problem('no camera_info yet: keyframes wait for the calibration')
            return
        kf.paired = True
        kf.paired_T = kf.map_T_cam
        if kf.provisional:
            self.diag.count('keyframes_paired_provisional')
        self.diag.count('keyframes')
        if kf.map_T_cam[2, 3] <= self.ground_m:
            self.diag.problem(f'keyframe at z={kf.map_T_cam[2, 3]:.1f} m is not above the ground '
                              f'({self.ground_m} m): set ground_height_m')
            return
        if not self._flushing and self.share.over():
            # Stereo is over its CPU share: the pose chain comes first. The keyframe stays a partner of later
            # ones; its own pairs are matched after landing (export --densify / replay's map_final).
            self._shed(kf, f'stereo over its CPU share of {self.params.cpu_share:g} core')
            return
        p = self._matching_params(kf)
        if kf.sigma_m > self.sigma_limit_m(kf):
            self.diag.count('pairs_skipped_poor_pose')
            self.diag.set('last_skip', f'pose sigma {kf.sigma_m:.2f} m > {self.sigma_limit_m(kf):.2f} m')
            return
        # Partners of the same status: a provisional and a final pose are in different georeferences.
        others = {s: o.map_T_cam for s, o in self._kf.items()
                  if o is not kf and o.complete and o.paired and o.provisional == kf.provisional
                  and o.sigma_m <= self.sigma_limit_m(o)}
        plan = plan_pairs(self._camera_for(kf.image), kf.map_T_cam, others, self.ground_m, p,
                          (p.min_depth_m, p.max_depth_m), self._tie_points)
        if plan.status == BELOW_GROUND:
            self.diag.problem(f'keyframe at z={kf.map_T_cam[2, 3]:.1f} m is not above the ground '
                              f'({self.ground_m} m): set ground_height_m')
            return
        if not plan.pairs:
            # No cloud of its own: no earlier keyframe to pair with, or none passing the planner's criteria
            # (baseline ratio, optical-axis angle, overlap: core/pairs.choose_pairs), e.g. a fixed-wing's roll.
            self.diag.count('keyframes_no_partner' if others else 'keyframes_no_earlier_partner')
        for pair in plan.pairs:
            # The poses of the moment go with the pair: the depth and the cloud's placement use these.
            job = _PairJob(pair, self._kf[pair.other].map_T_cam, kf.map_T_cam, kf.covariance)
            if todo is None:
                self._run_pair(self._kf[pair.other], kf, job)
            else:
                todo.append((self._kf[pair.other], kf, job))

    def _shed(self, kf: _Keyframe, why: str) -> None:
        """`kf`'s pairs (or one of them) are left to the matching after landing: counted, said."""
        if not kf.shed:
            kf.shed = True
            self.diag.count('keyframes_shed')
        self.diag.problem(f'stereo pairs shed in flight ({why}; keyframes_shed counts the keyframes): the in-flight '
                          'map has gaps there until the matching after landing (export --densify, replay\'s '
                          'map_final)')

    def _run_pair(self, a: _Keyframe, b: _Keyframe, job: _PairJob) -> None:
        p = self._matching
        pair = job.pair
        lag_s = time.monotonic() - b.final_at
        if not self._flushing and self.params.max_pair_lag_s > 0 and lag_s > self.params.max_pair_lag_s:
            # Stereo is behind (starved of CPU): the newer keyframes go first, this pair after landing.
            self.diag.count('pairs_shed_late')
            self.diag.set('shed_pair_lag_s', round(lag_s, 1))
            with self._lock:
                self._shed(b, f'stereo behind the poses by more than max_pair_lag_s {self.params.max_pair_lag_s:g} s')
            return
        if self._flushing and time.monotonic() > self._flush_deadline:
            self.diag.count('pairs_skipped_end_budget')
            return
        t0 = time.perf_counter()
        if pair.from_tie_points:
            self.diag.count('pairs_depth_from_tie_points')
        try:
            cam = self._camera_for(a.image)
            # Keyframe images reduced (tracker_node keyframe_image_reduction): matched at the same resolution.
            p = gsd.for_reduced_images(p, self.camera.width / cam.width)
            with self.share.measure():
                res = stereo.stereo_pair(cam, a.image, job.a_T, b.image, job.b_T, p, pair.depth_range_m)
        except Exception as exc:
            self.diag.count('pairs_failed')
            self.diag.problem(f'stereo pair {a.stamp_ns}/{b.stamp_ns} failed: {exc}')
            return
        ms = (time.perf_counter() - t0) * 1e3
        if not res.ok:
            self.diag.count(f'pairs_skipped_{res.status}')
            self.diag.set('last_skip', res.message)
            return
        # The placement first (the map takes it for the next cloud of b), then the cloud.
        self.cloud_pose_pub.publish(msgs.pose_with_covariance_from_T(job.b_T, b.stamp_ns, 'map', job.b_covariance))
        self.cloud_pub.publish(msgs.dense_cloud_msg(res.cloud, b.stamp_ns, 'map'))
        if self.disp_pub is not None:
            d = res.disparity.disparity_px + np.float32(res.rect.shift_px)
            self.disp_pub.publish(msgs.disparity_image_msg(d, b.stamp_ns, res.rect.f_px, res.rect.baseline_m))
        self._ms.append(ms)
        self._ms = self._ms[-50:]
        self.diag.count('pairs_done')
        self.diag.set('ms_per_pair', float(np.mean(self._ms)))
        self.diag.set('points_per_pair', int(res.cloud.size))
        self.diag.set('sgbm_ms', float(res.timings_ms.get('sgbm_ms', 0.0)))


def main(argv=None) -> int:
    """Console script `stereo_node`."""
    return run_node(StereoNode, argv)


if __name__ == '__main__':
    sys.exit(main())
