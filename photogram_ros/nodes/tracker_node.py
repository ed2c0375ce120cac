"""tracker_node: camera frames + camera_info + GPS fixes in, mapping keyframes out.

Subscribes `<image_topic>` (sensor_msgs/Image) and `<image_topic>/compressed` (CompressedImage; a
remapping of image_topic moves it too, image_transport's convention),
`camera_info_topic` and `fix_topic`. Publishes per keyframe, all with the keyframe image's stamp:
/keyframes/image (Image bgr8, at the resolution the map's cell needs: reduced by `keyframe_image_reduction`,
from the GSD by default, core/gsd.keyframe_reduction: 1 at 640 x 480, 4 at 20 MP; stereo scales the camera
to it), /keyframes/image/compressed (CompressedImage: the full-resolution JPEG, the camera's own bytes when
the frame came compressed, only when the image above is reduced: the map saves it for the products after
landing), /keyframes/features (PointCloud2: track_id uint32, u, v, xn, yn
float64; see core/tracker.py; with `detect_targets` also the keyframe's ArUco targets, in the id
range msgs.py reserves for them), /keyframes/fix (NavSatFix interpolated to the stamp, when GPS
has one), optionally /tracker/debug_image, and /diagnostics.

Frames go into a queue and a worker thread tracks them; beyond `queue_size` waiting frames, one is dropped
only when the chain can spare it (core/frame_queue.py): the waiting frame whose removal leaves the smallest GNSS
gap between its neighbours, when that gap is within `drop_gap_share` of the tracker's keyframe spacing (redundant
overlap, as video-rate frames are); a frame the chain needs (photo-rate input: every photo a keyframe) is kept and
the queue grows, up to `queue_max_mb` of frames. Without GNSS positions the oldest waiting frame is dropped. Each
drop is counted (`drops`, and `drops_<reason>`) and said on /diagnostics with its reason. A compressed frame larger than `track_max_px`
(a 20 MP photo) is decoded straight at the tracker's working size (core/tracker.EncodedImage), and at
full size never: a keyframe's image is decoded again at its reduction (libjpeg's DCT scaling). Its targets
are searched only where the surveyed targets of `control_file` (the graph passes bundle_node's) can be, from
the keyframe's GNSS fix (`target_search` regions, core/control.target_regions): squares on that reduced
image, a full-resolution grey decode only when one lies where a target can be, read in windows around them;
no control file or no target near the footprint: no search. Keyframes go out from a second
thread (`keyframe_thread`): the decodes, the target detection and the messages of a 20 MP keyframe stay off
the frame loop; they are never dropped, and leave in keyframe order.
A missing or inconsistent calibration is reported on /diagnostics as an error and the frames are
not used until a good camera_info (or calibration_file) is there; the node stays up.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, NavSatFix, PointCloud2

from photogram_ros import msgs
from photogram_ros.core import gsd
from photogram_ros.core.camera import load_calibration
from photogram_ros.core.frame_queue import FrameQueue
from photogram_ros.core.keyframes import FixBuffer
from photogram_ros.core.control import (ARUCO_DICTIONARIES, ControlSet, TargetRegionOptions, detect_keyframe_targets,
                                        detect_keyframe_targets_encoded, detect_targets_in_regions, target_regions)
from photogram_ros.core.pace import ThreadCaps, limit_threads
from photogram_ros.core.tracker import EncodedImage, Tracker, TrackerParams
from photogram_ros.errors import CalibrationError, PhotogramError
from photogram_ros.nodes import qos
from photogram_ros.nodes.diagnostics import ERROR, WARN, Diagnostics
from photogram_ros.nodes.node_main import run_node
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param


# Compressed frames kept for their keyframe's image: a keyframe waits at most for its GNSS fix (fix_lag_max_s,
# 20 frames at 1 Hz); beyond, the keyframe's own compressed image (Keyframe.encoded) is used.
MAX_ENCODED_KEPT = 32
# The control of a flight without a control file: no target to search for (target_search regions).
_NO_CONTROL = ControlSet([])


@dataclass
class TrackerNodeParams(TrackerParams, ThreadCaps, TargetRegionOptions):
    image_topic: str = param('camera/image_raw', 'Raw image topic; "<topic>/compressed" is subscribed too')
    camera_info_topic: str = param('camera/camera_info', 'CameraInfo topic (ignored with calibration_file)')
    fix_topic: str = param('gps/fix', 'NavSatFix topic interpolated to keyframe stamps')
    calibration_file: str = param('', 'Calibration YAML (ROS or OpenCV layout) used instead of camera_info')
    queue_size: int = param(2, 'Frames waiting for the tracker; beyond this a redundant one is dropped (the waiting '
                            'frame whose neighbours are nearest by GNSS, within drop_gap_share of the keyframe '
                            'spacing; without GNSS the oldest): frames the chain needs are kept', min=1, max=1000)
    drop_gap_share: float = param(0.5, 'A waiting frame is redundant (may be dropped) when the GNSS gap its removal '
                                  'leaves is within this share of the median distance between the tracker\'s last '
                                  'keyframes', min=0.0, max=1.0)
    queue_max_mb: float = param(512.0, 'Frames the chain needs stay queued beyond queue_size up to this many MB of '
                                'messages; beyond, the most redundant waiting frame is dropped anyway (an ERROR on '
                                '/diagnostics)', min=1.0, max=100000.0)
    reliable_input: bool = param(False, 'Subscribe images reliably (bag replay) instead of best effort '
                                 '(sensor-data QoS, matches any camera driver)')
    input_depth: int = param(10, 'DDS history depth of the image subscriptions (raise it for fast bag replay)',
                             min=1, max=10000)
    publish_debug_image: bool = param(False, 'Publish /tracker/debug_image with the tracks drawn')
    keyframe_qos_depth: int = param(20, 'History depth of the reliable keyframe publishers', min=1, max=10000)
    detect_targets: bool = param(True, 'Find ArUco targets (GCPs, check points) in keyframes and send them '
                                 'with their features (where target_search says; bundle_node.control_file names '
                                 'them)')
    target_dictionary: str = param('DICT_4X4_50', 'ArUco dictionary of the target boards',
                                   choices=ARUCO_DICTIONARIES)
    target_search: str = param('regions', 'Where targets are searched: only where the surveyed targets of '
                               'control_file can be, from the keyframe\'s GNSS position (regions: no control file, '
                               'no search; core/control.target_regions), or the whole image (everywhere: also '
                               'markers no control file lists, which become tie points)',
                               choices=('regions', 'everywhere'))
    control_file: str = param('', 'Surveyed targets for the target search (io/control_file.py; the graph passes '
                                  'bundle_node.control_file when this is empty)')
    control_heights: str = param('auto', 'Heights of control_file: ellipsoidal, orthometric (EGM2008), or auto',
                                 choices=('auto', 'ellipsoidal', 'orthometric'))
    health_window: int = param(20, 'health: keyframes over which the share after an unbridged break (tracking '
                                   'lost: a new segment) is judged', min=2, max=10000)
    decode_reduced: bool = param(True, 'Decode compressed frames larger than track_max_px at the working size '
                                 '(JPEG DCT scaling) and fully only for keyframes; false decodes every frame fully')
    keyframe_thread: bool = param(True, 'Publish keyframes (full decode, target detection, image message) from a '
                                  'thread of their own instead of the frame loop')
    keyframe_image_reduction: int = param(0, 'Keyframe images on keyframes/image are reduced by this (1, 2, 4 '
                                          'or 8; 0: from the GSD, the largest whose pixel is no larger than '
                                          'the map cell: 1 at 640x480, 4 at 20 MP); a reduced one also goes '
                                          'out at full resolution as JPEG on keyframes/image/compressed',
                                          choices=(0, 1, 2, 4, 8))
    jpeg_quality: int = param(90, 'JPEG quality of keyframes/image/compressed when the frame came raw', min=10,
                              max=100)
    health_max_lost: float = param(0.2, 'health: WARN above this share of the last health_window keyframes '
                                        'coming after an unbridged break (ERROR above 0.5)', min=0.0, max=1.0)
    frame_fix_wait_s: float = param(0.5, 'Before a frame is tracked, wait up to this long (and at most a quarter '
                                    'of the interval since the last frame: a video is barely slowed) for a fix at '
                                    'or after its stamp while the fix stream is live (a frame and its fix arrive '
                                    'on two topics in either order: the keyframe rule then sees the same GNSS '
                                    'whatever the order, and a replay gives the same keyframes every time); a '
                                    'stream that misses the wait is not waited for again until its next fix; 0: '
                                    'no wait, s', min=0.0, max=5.0)


class SharedFixBuffer(FixBuffer):
    """The tracker's FixBuffer, read and written from two threads: fixes come in on the executor thread (`add`,
    the drop rule's `near`), the worker's tracker reads them (`at`, `near`, `latest_ns`). One lock around each."""

    def __init__(self, max_gap_s: float = 1.0, keep: int = 600):
        super().__init__(max_gap_s, keep)
        self._lock = threading.RLock()
        self.added = 0          # fixes given so far (flush: whether the stream still comes)

    def add(self, fix) -> None:
        with self._lock:
            super().add(fix)
            self.added += 1

    def __len__(self) -> int:
        with self._lock:
            return super().__len__()

    def latest_ns(self):
        with self._lock:
            return super().latest_ns()

    def near(self, stamp_ns: int, max_s: float):
        with self._lock:
            return super().near(stamp_ns, max_s)

    def at(self, stamp_ns: int):
        with self._lock:
            return super().at(stamp_ns)


class TrackerNode(Node):
    def __init__(self, overrides: dict | None = None, **node_kwargs):
        super().__init__('tracker_node', **node_kwargs)
        self.params = p = declare(self, TrackerNodeParams, overrides)
        self.diag = Diagnostics(self)
        for k, v in limit_threads(p.cv_threads, p.blas_threads).items():
            self.diag.set(k, v)
        self.tracker = Tracker(None, TrackerParams(**{k: getattr(p, k) for k in TrackerParams.__dataclass_fields__}))
        self._camera_from_file = None
        self.control = None
        self._target_ms_total = 0.0   # CPU of the target searches, all keyframes
        if p.control_file:   # a bad file: fail at start
            from photogram_ros.io.control_file import read_control_file
            self.control = read_control_file(p.control_file, (), p.control_heights)
        if p.calibration_file:
            self._camera_from_file = load_calibration(p.calibration_file)   # bad file: fail at start
            self.tracker.set_camera(self._camera_from_file)
        self._cond = threading.Condition()
        self._track_lock = threading.Lock()   # the worker and flush() both drive the tracker
        self._frames = FrameQueue(p.queue_size, int(p.queue_max_mb * 1e6))
        # The one store of the fixes: the tracker's own buffer, shared (under a lock) with the drop rule's look-ups
        # of the waiting frames' positions in the executor thread.
        self._fixes = SharedFixBuffer(p.fix_max_gap_s)
        self.tracker.fixes = self._fixes
        self._fix_wait_missed_at = -1   # the fix count at the last missed frame_fix_wait_s (_wait_for_fix)
        self._camera_pending = None
        self._camera_error = 'no camera_info received yet' if self._camera_from_file is None else ''
        self._stop = False
        self.keyframes_published = 0
        self._lost_history: deque = deque(maxlen=p.health_window)   # per keyframe: an unbridged break before it
        self._last_frame_ms = float('nan')
        self.frames_done = 0   # frames tracked, refused or dropped: lets a bag replay wait for the tracker
        self._last_stamp_ns = None   # the stamp of the last frame tracked: time never goes back
        self._stamp_fault = None     # the frames dropped for their stamp since the last one tracked (_stamp_goes_on)

        self.pub_image = self.create_publisher(Image, 'keyframes/image', qos.keyframes(p.keyframe_qos_depth))
        self.pub_image_full = self.create_publisher(CompressedImage, 'keyframes/image/compressed',
                                                    qos.keyframes(p.keyframe_qos_depth))
        self.pub_features = self.create_publisher(PointCloud2, 'keyframes/features', qos.keyframes(p.keyframe_qos_depth))
        self.pub_fix = self.create_publisher(NavSatFix, 'keyframes/fix', qos.keyframes(p.keyframe_qos_depth))
        self.pub_debug = (self.create_publisher(Image, 'tracker/debug_image', qos.reliable(2))
                          if p.publish_debug_image else None)

        def img_qos():
            return qos.reliable(p.input_depth) if p.reliable_input else qos.best_effort(p.input_depth)
        self.create_subscription(Image, p.image_topic, self._on_image, img_qos())
        self.create_subscription(CompressedImage, self.compressed_topic(p.image_topic), self._on_image, img_qos())
        self.create_subscription(CameraInfo, p.camera_info_topic, self._on_camera_info, qos.reliable(10))
        # Fixes come 5-20 per frame: a deep history so a busy executor does not lose the ones a keyframe
        # needs for its interpolation.
        self.create_subscription(NavSatFix, p.fix_topic, self._on_fix, qos.reliable(200))
        # The compressed frames the tracker was given, by stamp, until their keyframe is published (or a newer
        # keyframe is): a keyframe's image is decoded from them at its reduction, never at full size.
        self._encoded: OrderedDict[int, EncodedImage] = OrderedDict()
        self._kf_out: deque = deque()          # (keyframe, frame_id) waiting for the publisher thread
        self._kf_busy = False
        self._kf_cond = threading.Condition()
        self._worker = threading.Thread(target=self._run, name='tracker_worker', daemon=True)
        self._worker.start()
        self._publisher = None
        if p.keyframe_thread:
            self._publisher = threading.Thread(target=self._run_publisher, name='tracker_keyframes', daemon=True)
            self._publisher.start()

    def compressed_topic(self, image_topic: str) -> str:
        """The compressed sibling of `image_topic` as image_transport finds it: `<image_topic as remapped>/
        compressed`, so `-r camera/image_raw:=/cam0/image` moves both; a remapping of the sibling's own
        name (`-r camera/image_raw/compressed:=...`) wins."""
        own = image_topic.rstrip('/') + '/compressed'
        if self.resolve_topic_name(own) != self.resolve_topic_name(own, only_expand=True):
            return own   # remapped by its own rule, which the subscription applies
        return self.resolve_topic_name(image_topic).rstrip('/') + '/compressed'

    # --- callbacks (executor thread): cheap, never raise -----------------------------------------

    def _on_image(self, msg) -> None:
        spacing = self.tracker.keyframe_spacing_m()
        with self._cond:
            dropped = self._frames.push(msg, msgs.ns_from_time(msg.header.stamp), len(msg.data),
                                        lambda t: self._fixes.near(t, self.params.fix_max_gap_s),
                                        None if spacing is None else self.params.drop_gap_share * spacing)
            self.frames_done += len(dropped)
            waiting, over = len(self._frames), self._frames.kept_over_size
            self._cond.notify()
        self.diag.count('frames_received')
        self.diag.set('queue_waiting', waiting)
        self.diag.set('queue_kept_over_size', over)
        for d in dropped:
            self.diag.count('drops')
            self.diag.count(f'drops_{d.reason}')
            self.diag.problem(f'{d.message} (the last frame took {self._last_frame_ms:.0f} ms to decode and track)',
                              ERROR if d.reason == 'over_memory' else WARN)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        if self._camera_from_file is not None:
            return
        try:
            cam = msgs.camera_from_info(msg)
        except CalibrationError as exc:
            self._camera_error = f'camera_info rejected: {exc}'
            self.diag.problem(self._camera_error, ERROR)
            return
        with self._cond:
            self._camera_pending = cam

    def _on_fix(self, msg: NavSatFix) -> None:
        try:
            fix = msgs.gnss_fix_from_navsatfix(msg)
        except Exception as exc:   # a malformed fix must not stop the node
            self.diag.problem(f'bad NavSatFix: {exc}')
            return
        self._fixes.add(fix)     # the tracker reads it from there
        with self._cond:
            self._cond.notify_all()   # a frame may wait for this fix (_wait_for_fix)

    # --- worker ----------------------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._frames and not self._stop:
                    self._cond.wait(0.5)
                if self._stop:
                    return
                # A frame may come just before its camera_info (drivers publish them in either order):
                # give the calibration a moment before the frame is refused.
                if self.tracker.camera is None and self._camera_pending is None and not self._stop:
                    self._cond.wait_for(lambda: self._camera_pending is not None or self._stop, 1.0)
                msg = self._frames.popleft()
                cam, self._camera_pending = self._camera_pending, None
                self._wait_for_fix(msg)
            try:
                with self._track_lock:
                    self._handle(msg, cam)
            except Exception as exc:   # the worker must survive anything one frame can do
                self.diag.problem(f'tracker failed on a frame: {type(exc).__name__}: {exc}', ERROR)
            with self._cond:
                self.frames_done += 1

    def _wait_for_fix(self, msg) -> None:
        """Under self._cond: give the frame's fix frame_fix_wait_s (at most a quarter of the frame interval) to
        arrive when the fix stream is live (a fix came since the last missed wait) and its newest fix is older
        than the frame. A missed wait is counted (frames_fix_late) and the stream is not waited for again
        until a new fix arrives."""
        stamp = getattr(getattr(msg, 'header', None), 'stamp', None)
        if stamp is None:     # not a frame message: _handle reports it
            return
        stamp_ns = msgs.ns_from_time(stamp)
        wait_s = self.params.frame_fix_wait_s
        if self._last_stamp_ns is not None:
            wait_s = min(wait_s, 0.25 * max(stamp_ns - self._last_stamp_ns, 0) * 1e-9)
        latest = self._fixes.latest_ns()
        if wait_s <= 0 or latest is None or latest >= stamp_ns or self._fix_wait_missed_at == self._fixes.added:
            return
        if not self._cond.wait_for(lambda: self._stop or (self._fixes.latest_ns() or 0) >= stamp_ns, wait_s):
            self._fix_wait_missed_at = self._fixes.added
            self.diag.count('frames_fix_late')

    def _handle(self, msg, cam) -> None:
        if cam is not None:
            try:
                self.tracker.set_camera(cam)
                self._camera_error = ''
            except CalibrationError as exc:
                self._camera_error = f'camera_info rejected: {exc}'
        if self.tracker.camera is None or self._camera_error:
            self.diag.count('frames_unused')
            self.diag.problem(f'frames not used: {self._camera_error or "no calibration"}', ERROR)
            return
        stamp_ns = msgs.ns_from_time(msg.header.stamp)
        if not self._stamp_goes_on(stamp_ns):
            return
        try:
            t0 = time.perf_counter()
            image = self._frame_image(msg)
            t1 = time.perf_counter()
            kfs = self.tracker.process(image, stamp_ns, clock_ns=time.monotonic_ns())
            dt = time.perf_counter() - t1
            self.diag.set('frame_from_msg_ms', (t1 - t0) * 1e3)   # a compressed frame decodes in process()
            self._last_frame_ms = (time.perf_counter() - t0) * 1e3
        except CalibrationError as exc:
            self.diag.count('frames_unused')
            self.diag.problem(f'frames not used: {exc}', ERROR)
            return
        except PhotogramError as exc:
            self.diag.count('bad_images')
            self.diag.problem(str(exc))
            return
        self.diag.count('frames_tracked')
        frame_id = msg.header.frame_id or 'camera_optical'
        for kf in kfs:
            self._send_keyframe(kf, frame_id)
        self._update_diagnostics(dt)
        if self.pub_debug is not None:
            self._publish_debug(image.full() if isinstance(image, EncodedImage) else image, stamp_ns, frame_id)

    def _stamp_goes_on(self, stamp_ns: int) -> bool:
        """Whether a frame's stamp comes after the last tracked frame's. A frame whose stamp repeats it or goes back
        (a camera clock reset, a bag recorded twice over) is dropped, counted (`stamps_repeated`, `stamps_back`) and
        named on /diagnostics with its stamp: the first of a run of them at once, the run's span when time goes on."""
        last = self._last_stamp_ns
        if last is not None and stamp_ns <= last:
            kind = 'stamps_repeated' if stamp_ns == last else 'stamps_back'
            self.diag.count(kind)
            self.diag.count('frames_dropped_stamp')
            if self._stamp_fault is None:
                self._stamp_fault = [stamp_ns, stamp_ns, 0]
                what = ("repeats the last tracked frame's" if kind == 'stamps_repeated'
                        else f'goes back {(last - stamp_ns) * 1e-9:.3f} s from the last tracked frame\'s')
                self.diag.problem(f'frame stamped {stamp_ns * 1e-9:.3f} s dropped: its stamp {what} '
                                  f'({last * 1e-9:.3f} s); frames are dropped until time goes on')
            f = self._stamp_fault
            f[0], f[1], f[2] = min(f[0], stamp_ns), max(f[1], stamp_ns), f[2] + 1
            return False
        if self._stamp_fault is not None:
            lo, hi, n = self._stamp_fault
            self._stamp_fault = None
            span = f'stamped {lo * 1e-9:.3f} s' if n == 1 else f'stamped {lo * 1e-9:.3f} to {hi * 1e-9:.3f} s'
            self.diag.problem(f'{n} frame(s) {span} dropped: not after the frame tracked before them '
                              f'({last * 1e-9:.3f} s); tracking goes on at {stamp_ns * 1e-9:.3f} s')
            self.diag.set('stamp_faults_last', f'{n} frame(s) {span}')
        self._last_stamp_ns = stamp_ns
        return True

    def _frame_image(self, msg):
        """The frame as the tracker takes it: a JPEG frame larger than track_max_px stays compressed (the
        tracker decodes it at its working size), anything else decoded (msgs.image_from_msg)."""
        cam = self.tracker.camera
        if (self.params.decode_reduced and hasattr(msg, 'format') and 'jp' in msg.format.lower()
                and cam is not None and max(cam.width, cam.height) > self.params.track_max_px):
            self.diag.count('frames_decoded_reduced')
            enc = EncodedImage(bytes(msg.data))
            with self._kf_cond:
                self._encoded[msgs.ns_from_time(msg.header.stamp)] = enc
                while len(self._encoded) > MAX_ENCODED_KEPT:
                    self._encoded.popitem(last=False)
            return enc
        return msgs.image_from_msg(msg)

    # --- keyframes out ---------------------------------------------------------------------------

    def _send_keyframe(self, kf, frame_id: str) -> None:
        """Publish now (keyframe_thread false) or queue for the publisher thread (never dropped)."""
        if self._publisher is None:
            self._publish_keyframe(kf, frame_id)
            return
        with self._kf_cond:
            self._kf_out.append((kf, frame_id))
            self.diag.set('keyframes_queued', len(self._kf_out))
            self._kf_cond.notify()

    def _run_publisher(self) -> None:
        while True:
            with self._kf_cond:
                while not self._kf_out and not self._stop:
                    self._kf_cond.wait(0.5)
                if not self._kf_out:
                    return
                kf, frame_id = self._kf_out.popleft()
                self._kf_busy = True
            try:
                self._publish_keyframe(kf, frame_id)
            except Exception as exc:   # the publisher must survive anything one keyframe can do
                self.diag.problem(f'keyframe {kf.index} not published: {type(exc).__name__}: {exc}', ERROR)
            finally:
                with self._kf_cond:
                    self._kf_busy = False
                    self._kf_cond.notify_all()

    def busy(self) -> bool:
        """Keyframes made and not yet published (Graph.drain waits for them)."""
        with self._kf_cond:
            return bool(self._kf_out) or self._kf_busy

    def wait_keyframes_out(self, timeout_s: float = 30.0) -> bool:
        """Until every keyframe made so far is published; False if `timeout_s` passed first."""
        deadline = time.monotonic() + timeout_s
        with self._kf_cond:
            while self._kf_out or self._kf_busy:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._kf_cond.wait(min(left, 0.1))
        return True

    def image_reduction(self) -> int:
        """The reduction of the keyframe images on keyframes/image (keyframe_image_reduction, or the GSD's)."""
        cam = self.tracker.camera
        r = self.params.keyframe_image_reduction
        return r if r or cam is None else gsd.keyframe_reduction(cam.width, cam.height)

    def _encoded_of(self, stamp_ns: int) -> EncodedImage | None:
        """The compressed frame of a keyframe (and the older ones forgotten: keyframes go out in order)."""
        with self._kf_cond:
            enc = self._encoded.pop(stamp_ns, None)
            while self._encoded and next(iter(self._encoded)) < stamp_ns:
                self._encoded.popitem(last=False)
        return enc

    def _keyframe_images(self, kf, reduction: int):
        """(the image for keyframes/image at `reduction`, the full-resolution JPEG bytes or None when not reduced,
        the target rows or None). A compressed keyframe is decoded at the reduction only (and in grey for its
        targets); a raw one is reduced with INTER_AREA and encoded once. PhotogramError if undecodable."""
        import cv2
        cam = self.tracker.camera
        enc = self._encoded_of(kf.stamp_ns)
        if enc is None:   # forgotten while the keyframe waited: the keyframe holds its compressed image too
            enc = kf.encoded()
        t0 = time.perf_counter()
        regions = self._target_regions(kf, cam)
        if enc is not None:
            image = msgs.decode_reduced(enc.data, reduction)
            size = cam.scaled(1.0 / reduction)
            image = image[:size.height, :size.width]   # libjpeg rounds the reduced size up
            jpeg = enc.data if reduction > 1 else None
            if regions is not None and regions.status == 'rings' and reduction > 1:
                targets = self._targets(lambda data, c, d: self._search_regions(data, image, c, regions, d),
                                        enc.data, cam)
            elif regions is None or regions.box(cam) is not None:
                targets = self._targets(detect_keyframe_targets_encoded, enc.data, cam)
            else:
                targets = None
        else:
            if reduction > 1:   # a raw frame
                self.diag.count('keyframe_images_reduced_from_full')
            full = kf.image
            searched = regions is None or regions.box(cam) is not None
            targets = self._targets(detect_keyframe_targets, full, cam) if searched else None
            image, jpeg = full, None
            if reduction > 1:
                size = cam.scaled(1.0 / reduction)
                image = cv2.resize(full, (size.width, size.height), interpolation=cv2.INTER_AREA)
                ok, buf = cv2.imencode('.jpg', full, [cv2.IMWRITE_JPEG_QUALITY, self.params.jpeg_quality])
                jpeg = buf if ok else None
        self.diag.set('keyframe_images_ms', (time.perf_counter() - t0) * 1e3)   # decodes and target search
        return image, jpeg, targets

    def _target_regions(self, kf, cam):
        """Where keyframe `kf`'s targets can be (core/control.TargetRegions; status 'rings' with no ring: not
        searched), or None: searched everywhere (target_search everywhere, or no GNSS fix to predict from)."""
        p = self.params
        if not p.detect_targets or p.target_search == 'everywhere':
            return None
        if self.control is None:
            self.diag.count('keyframes_target_search_off_no_control')
            return target_regions(cam, _NO_CONTROL, 0.0, 0.0, 0.0)
        if kf.fix is None:
            self.diag.count('keyframes_target_search_whole_no_fix')
            return None
        sigma_h = float(np.sqrt(max(kf.fix.cov_enu_m2[0, 0], kf.fix.cov_enu_m2[1, 1], 0.0)))
        regions = target_regions(cam, self.control, kf.fix.lat_deg, kf.fix.lon_deg, kf.fix.h_m, sigma_h, p)
        if regions.status != 'rings':
            self.diag.count('keyframes_target_search_whole_no_height')
            self.diag.problem(f'keyframe {kf.index}: targets searched in the whole image: {regions.why}')
            return None
        if not regions.rings_px:
            self.diag.count('keyframes_target_search_none_near')
        return regions

    def _search_regions(self, data, image, cam, regions, dictionary):
        import cv2
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        targets, stats = detect_targets_in_regions(data, grey, cam, regions, dictionary)
        self.diag.count('keyframes_target_search_regions')
        self.diag.count('target_search_full_decodes', stats['full_decode'])
        self.diag.count('target_search_windows', stats['windows'])
        return targets

    def _targets(self, detect, image, cam):
        if not self.params.detect_targets:
            return None
        t0 = time.perf_counter()
        targets = detect(image, cam, self.params.target_dictionary)
        self._target_ms_total += (time.perf_counter() - t0) * 1e3
        self.diag.set('target_detection_ms', (time.perf_counter() - t0) * 1e3)
        self.diag.set('target_detection_ms_total', self._target_ms_total)
        self.diag.count('targets_detected', len(targets))
        return targets

    def _publish_keyframe(self, kf, frame_id: str) -> None:
        t0 = time.perf_counter()
        reduction = self.image_reduction()
        try:
            image, jpeg, targets = self._keyframe_images(kf, reduction)
        except PhotogramError as exc:
            # Its features still go out: the adjustment needs them more than stereo needs the image.
            self.diag.count('keyframe_images_undecodable')
            self.diag.problem(f'keyframe {kf.index}: {exc}: its image is not published')
            image = jpeg = targets = None
        if image is not None:
            self.pub_image.publish(msgs.image_msg(image, kf.stamp_ns, frame_id))
            self.diag.set('keyframe_image_reduction', reduction)
        if jpeg is not None:
            self.pub_image_full.publish(msgs.compressed_msg_from_bytes(jpeg, kf.stamp_ns, frame_id))
        self.pub_features.publish(msgs.keyframe_features_msg(kf.observations, kf.stamp_ns, frame_id, targets))
        if kf.fix is not None:
            self.pub_fix.publish(msgs.navsatfix_from_gnss_fix(kf.fix))
        else:
            self.diag.count('keyframes_without_fix')
        self.keyframes_published += 1
        self.diag.count('keyframes')
        self.diag.set('keyframe_ms', (time.perf_counter() - t0) * 1e3)
        # A bridged break is the normal way of photo-rate input (descriptor matching carries the tracks
        # on): counted; tracking lost (a new segment) is a problem, and judged over the last keyframes.
        lost = kf.break_before and not kf.bridged
        self._lost_history.append(lost)
        if kf.bridged:
            self.diag.count('keyframes_bridged')
        if lost:
            self.diag.problem(f'tracking lost before keyframe {kf.index} (no descriptor match with the last '
                              'keyframes nor with any earlier keyframe it overlaps by GNSS: its tracks start a new '
                              'segment)')
        n_lost = sum(self._lost_history)
        share = n_lost / len(self._lost_history)
        if len(self._lost_history) >= 5 and share > self.params.health_max_lost:
            self.diag.problem(f'tracking lost before {n_lost} of the last {len(self._lost_history)} keyframes '
                              '(too little overlap, blur or texture: the bundle adjuster cannot chain them)',
                              ERROR if share > 0.5 else WARN)

    def _update_diagnostics(self, dt: float) -> None:
        s = self.tracker.stats
        self.diag.set('fps', self.diag.rate_hz('frames_tracked'))
        self.diag.set('process_ms', dt * 1e3)
        self.diag.set('tracks_alive', s.tracks_alive)
        self.diag.set('keyframe_rate_hz', self.diag.rate_hz('keyframes', 30.0))
        self.diag.set('breaks', s.breaks)
        self.diag.set('bridged', s.bridged)
        self.diag.set('cross_strip_revisits', self.tracker.cross.revisits)   # keyframes matched across strips
        self.diag.set('cross_strip_stored', self.tracker.cross.stored)
        self.diag.set('gaps', s.gaps)
        self.diag.set('unusable_frames', s.unusable)
        self.diag.set('last_overlap', s.last_overlap)
        self.diag.set('fix_lag_s', self.tracker.fix_lag_s())

    def _publish_debug(self, image, stamp_ns: int, frame_id: str) -> None:
        import cv2
        vis = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        pts, ids = self.tracker.current_tracks()
        for (u, v), i in zip(pts, ids):
            color = (int(i * 67) % 256, int(i * 151) % 256, 255)
            cv2.circle(vis, (int(round(u)), int(round(v))), 3, color, 1)
        self.pub_debug.publish(msgs.image_msg(vis, stamp_ns, frame_id))

    # --- lifecycle -------------------------------------------------------------------------------

    def flush(self, timeout_s: float = 5.0, max_wait_s: float = 600.0) -> int:
        """Wait for queued frames (and for a lagging fix stream that still delivers), then emit the keyframes
        still waiting for a fix; returns their count. The queue is waited for while the tracker takes
        frames from it (a loaded machine tracks slowly, and a frame flushed past would miss the final
        adjustment): until it is empty, no frame was taken for `timeout_s`, or `max_wait_s`."""
        start = moved = time.monotonic()
        last = None
        while True:
            with self._cond:
                queued, done = len(self._frames), self.frames_done
            now = time.monotonic()
            if not queued or now - moved > timeout_s or now - start > max_wait_s:
                break
            if done != last:
                last, moved = done, now
            time.sleep(0.02)
        deadline = time.monotonic() + timeout_s
        # Fixes after the last frame: the last keyframes need them. While the fix stream lags behind the
        # newest keyframe still waiting and keeps coming, wait for it (until the deadline or 1 s of silence).
        last_fix = time.monotonic()
        added = self._fixes.added
        while True:
            with self._track_lock:
                lagging = self.tracker.fix_lag_s(newest=True) > 0.0
            now = time.monotonic()
            if self._fixes.added != added:   # a fix arrived since the last look
                last_fix, added = now, self._fixes.added
            if not lagging or now - last_fix > 1.0 or now > deadline:
                break
            time.sleep(0.05)
        with self._track_lock:
            kfs = self.tracker.flush()
        for kf in kfs:
            self._send_keyframe(kf, 'camera_optical')
        self.wait_keyframes_out(max(deadline - time.monotonic(), 0.0) + 30.0)
        return len(kfs)

    def drop_queued(self, keep: int = 0) -> int:
        """Drop the queued frames not taken yet but the `keep` next in line (a stopped flight's budget: no frame
        comes after them, so the drop rule's stamps no longer matter); returns how many."""
        with self._cond:
            items = [self._frames.popleft() for _ in range(len(self._frames))]
            self._frames.extend(items[:keep])
        return max(len(items) - keep, 0)

    def destroy_node(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._worker.join(timeout=5.0)
        if self._publisher is not None:
            with self._kf_cond:
                self._kf_cond.notify_all()
            self._publisher.join(timeout=30.0)   # the keyframes made are published first
        super().destroy_node()


def main(argv=None) -> int:
    """Console script `tracker_node`."""
    return run_node(TrackerNode, argv)


if __name__ == '__main__':
    sys.exit(main())
