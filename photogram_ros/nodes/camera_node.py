"""Camera ingest: a folder of photos, a video file or a video device onto the mapper's camera topics.

Publishes camera/image_raw (bgr8), camera/camera_info (the calibration, every frame) and, for
geotagged photos, gps/fix from the EXIF GPS stamped at the photo time, so survey photos without a
flight log still georeference: weighted as `triangulate` weighs them (a DJI RTK photo by its XMP RtkStd* sigmas,
its RtkFlag as the NavSatStatus, io/image_source.dji_rtk_accuracy; others by exif_sigma_m / exif_sigma_v_m,
triangulate's EXIF sigmas); its altitude read as `exif_altitude` says (above mean sea level by default, as
the EXIF standard and `triangulate` read it: one rule, io/image_source.exif_altitude_reading, through the EGM2008
geoid of core/geoid.py). A photo folder plays the photos of the camera most of it was taken with
(image size and EXIF make and model: io/image_source.FolderSource); a photo of another size or camera
(a panorama, a thumbnail) is named on /diagnostics and left out. Without `calibration_file` the camera
comes from the EXIF of that camera's first photo (core/exif_intrinsics.py: focal length in pixels,
principal point centred, no distortion), said on /diagnostics. A video file has no GPS of its own: `gnss_log` names a CSV of
fixes (io/image_source.read_fix_log: the columns `photogram-ros fixes --format csv` writes from a
.tlog, a dataflash .bin or a bag), published on gps/fix in time order with the frames, as a live
receiver would; `video_start_unix_s` places the video on the log's clock. A camera driver already
publishing these topics needs no ingest node. JPEG photos larger than `compressed_above_px` (20 MP
survey photos) go out undecoded, as their file's bytes on camera/image_raw/compressed: the tracker
decodes them at its working size (about 0.1 s for 20 MP instead of 0.25 s for the full decode here and
60 MB per raw image message). With `resume_keyframes_of` (run resuming a map after a crash) the map's
keyframes saved without a pose are played first, their stored images with their stamps and kept fixes
(io/image_source.StoredKeyframes), so that the tracker and adjuster orient them. `publish_next` /
`peek_stamp_ns` let a replay (nodes/replay_session.py) drive the frames itself, one at a time (`autostart` false).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, NavSatFix

from photogram_ros import msgs
from photogram_ros.errors import CalibrationError, ConfigError, PhotogramError
from photogram_ros.io.geo_txt import EXIF_SIGMA_H_M, EXIF_SIGMA_V_M
from photogram_ros.io.image_source import StoredKeyframes
from photogram_ros.nodes import qos as qos_profiles
from photogram_ros.nodes.diagnostics import Diagnostics
from photogram_ros.nodes.node_main import run_job
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param


TAKEOFF_NOT_GIVEN = -9999.0   # takeoff_altitude_m's "not given" (a ROS 2 double parameter has no None)


@dataclass
class CameraParams:
    source: str = param('', 'Folder of JPEG/PNG/TIFF photos, a video file, or a camera device '
                            '(/dev/video0 or an index such as 0)')
    rate: float = param(1.0, 'Playback speed of folders and files: 1 = EXIF/recorded timing, 0 = next frame as '
                             'soon as reliable subscribers acknowledged the previous one', min=0.0, max=1000.0)
    calibration_file: str = param('', 'Camera calibration, ROS camera_calibration or OpenCV YAML (make one with '
                                      'photogram-ros calibrate); "" for a photo folder: from the EXIF')
    publish_exif_fix: bool = param(True, 'Publish the EXIF GPS of photos on gps/fix, stamped at the photo time')
    exif_altitude: str = param('orthometric', 'What the photos\' EXIF GPSAltitude is, read as triangulate '
                                              '--exif-altitude reads it (io/image_source.exif_altitude_reading): '
                                              'orthometric, above mean sea level as the EXIF standard says (EGM2008, '
                                              'core/geoid; a DJI XMP drone-dji:AbsoluteAltitude where the EXIF has '
                                              'none), ellipsoidal (WGS84: some RTK/PPK geotaggers), or relative to '
                                              'the take-off point (many drones; needs takeoff_altitude_m)',
                               choices=('orthometric', 'ellipsoidal', 'relative'))
    takeoff_altitude_m: float = param(TAKEOFF_NOT_GIVEN, 'Height of the take-off point, m, for exif_altitude '
                                                         'relative (its datum: takeoff_heights); -9999 = not given',
                                      min=TAKEOFF_NOT_GIVEN, max=10000.0)
    takeoff_heights: str = param('orthometric', 'Vertical datum of takeoff_altitude_m: orthometric (EGM2008) or '
                                                'ellipsoidal (WGS84)', choices=('orthometric', 'ellipsoidal'))
    exif_sigma_m: float = param(EXIF_SIGMA_H_M, 'Horizontal 1-sigma of EXIF GPS positions without DJI RTK XMP (as '
                                                'triangulate weighs them) and of gnss_log rows without variances '
                                                '(vertical there twice it), m', min=0.001, max=10000.0)
    exif_sigma_v_m: float = param(EXIF_SIGMA_V_M, 'Vertical 1-sigma of EXIF GPS positions without DJI RTK XMP, m (as '
                                                  'triangulate weighs them: the heights of one flight agree far better '
                                                  'than their absolute error). A DJI RTK photo\'s fix takes its XMP '
                                                  'RtkStd* sigmas and RtkFlag status instead '
                                                  '(io/image_source.dji_rtk_accuracy)', min=0.001, max=10000.0)
    gnss_log: str = param('', 'CSV of GNSS fixes for a video (t_unix_s, lat_deg, lon_deg, h_m [ellipsoidal], '
                              'optional var_e_m2 var_n_m2 var_u_m2 status: photogram-ros fixes --format csv); '
                              'published on gps/fix in time order with the frames')
    video_start_unix_s: float = param(0.0, 'Time of a video file\'s first frame, Unix s; 0 = the first fix of '
                                           'gnss_log, else when the file is opened', min=0.0, max=1e10)
    exif_utc_offset_h: float = param(0.0, 'Camera clock minus UTC, h, for photos without OffsetTimeOriginal',
                                     min=-14.0, max=14.0)
    fallback_period_s: float = param(1.0, 'Spacing of photos without EXIF time (played in file-name order), s',
                                     min=0.001, max=3600.0)
    loop: bool = param(False, 'Start again from the first frame at the end (stamps keep increasing)')
    compressed_above_px: int = param(4096, 'JPEG photos whose long side exceeds this are published undecoded on '
                                          'camera/image_raw/compressed (the tracker decodes them at its working '
                                          'size); others decoded on camera/image_raw; 0: every JPEG photo',
                                     min=0, max=1_000_000)
    frame_id: str = param('camera_optical', 'frame_id of images and camera_info')
    fix_frame_id: str = param('gps', 'frame_id of the EXIF fixes')
    autostart: bool = param(True, 'Publish on a timer from the start; false leaves it to publish_next() calls')
    watch_quiet_s: float = param(0.0, 'A photo folder: after its last photo, wait for new ones (a companion computer '
                                      'downloading from the camera during the flight) until none came for this long, '
                                      's; 0 = the folder ends at its last photo. For run and camera_node (a replay '
                                      'plays the folder as listed)', min=0.0, max=86400.0)
    resume_keyframes_of: str = param('', 'A map folder whose keyframes were saved without a pose (taken before a '
                                         'crash, never oriented): their images are played first, with their stamps '
                                         'and the fixes the map kept, those stamped before the source\'s first frame, '
                                         'so that this run orients them; run sets it when it resumes a map. "" = none')
    wait_for_subscribers: int = param(1, 'Folders and files: the first frame waits until this many subscribers '
                                         'take the images, their camera_info and the fixes (a tracker in another '
                                         'process that starts later misses none); 0 = at once. A device never '
                                         'waits', min=0, max=100)


class CameraNode(Node):
    def __init__(self, overrides: dict | None = None, **node_kwargs):
        super().__init__('camera_node', **node_kwargs)
        from photogram_ros.io.image_source import open_source
        from photogram_ros.io.image_source import read_fix_log
        from photogram_ros.io.image_source import exif_altitude_reading
        p = self.params = declare(self, CameraParams, overrides)
        # The EXIF altitudes' reading, checked before the first photo: the rule triangulate applies.
        self._exif_reading = exif_altitude_reading(
            p.exif_altitude, None if p.takeoff_altitude_m == TAKEOFF_NOT_GIVEN else p.takeoff_altitude_m,
            p.takeoff_heights)
        self._log = read_fix_log(p.gnss_log, p.exif_sigma_m) if p.gnss_log else []
        self._log_next = 0           # the first log fix not yet published
        start_ns = int(p.video_start_unix_s * 1e9) or (self._log[0].stamp_ns if self._log else None)
        self._open = lambda: open_source(p.source, p.exif_utc_offset_h * 3600.0, p.fallback_period_s, start_ns)
        self.source = self._open()
        self.camera, camera_note = self._calibration(p)
        self.diag = Diagnostics(self)
        self.diag.set('source', p.source)
        self.diag.set('calibration', camera_note)
        self.diag.set('exif_altitude', p.exif_altitude + (f' (take-off at {p.takeoff_altitude_m:g} m '
                                                          f'{p.takeoff_heights})' if p.exif_altitude == 'relative'
                                                          else ''))
        notes = list(self.source.notes)
        if self._log:
            notes.append(f'{len(self._log)} fixes from {p.gnss_log}'
                         + ('' if p.video_start_unix_s else ', the video taken to start at its first fix'))
        for note in notes:
            self.diag.set('note', note)
            self.get_logger().info(note)
        # rate 0 relies on acknowledgements: KEEP_ALL so that unacknowledged frames are not overwritten.
        def qos():
            return qos_profiles.keep_all() if p.rate == 0 else qos_profiles.reliable(10)
        self.pub_image = self.create_publisher(Image, 'camera/image_raw', qos())
        self.pub_compressed = self.create_publisher(CompressedImage, 'camera/image_raw/compressed', qos())
        self.pub_info = self.create_publisher(CameraInfo, 'camera/camera_info', qos())
        self.pub_fix = self.create_publisher(NavSatFix, 'gps/fix', qos())
        self.finished = False
        self.stopped = False         # stop_input(): the end of flight takes no more frames
        self.waiting = False         # watch_quiet_s: the folder's photos are played, new ones are waited for
        self._quiet_since = None     # since when no new photo came (watch_quiet_s)
        self._last_scan = 0.0
        self._stored = StoredKeyframes(p.resume_keyframes_of) if p.resume_keyframes_of else None
        self._resumed: set[int] = set()   # stamps of the stored keyframes played (resume_keyframes_of)
        if self._stored is not None:
            for note in self._stored.notes:
                self.diag.set('note', note)
                self.get_logger().info(note)
        self._frames = self._after_stored(self._iterate(self.source))
        self._next = None
        self._offset_ns = 0          # added to stamps on each loop so that time never goes back
        self._first_ns = None
        self._last_ns = None
        self._wall0 = None
        self._wall0_resumed = False
        self._reported_skips = 0
        self._started = self._said_waiting = False   # the first frame waits for wait_for_subscribers
        self._timer = self.create_timer(0.005, self._tick) if p.autostart else None

    def _calibration(self, p):
        """The camera and where it came from: the calibration file, else a photo folder's EXIF."""
        from photogram_ros.core.camera import load_calibration
        from photogram_ros.io.image_source import FolderSource
        if p.calibration_file:
            try:
                return load_calibration(p.calibration_file), p.calibration_file
            except CalibrationError as exc:
                raise ConfigError(f'camera_node: parameter "calibration_file": {exc}') from exc
        why = 'a video has no EXIF'
        if isinstance(self.source, FolderSource):
            try:
                est = self.source.exif_intrinsics()
                return est.camera, f'EXIF: {est.note}'
            except CalibrationError as exc:
                why = str(exc)
        raise ConfigError(f'camera_node: set the parameter "calibration_file" to the camera calibration YAML (ROS '
                          f'or OpenCV layout; make one with photogram-ros calibrate): {why}')

    # --- frames ----------------------------------------------------------------------------------

    def _peek(self):
        """The next frame to publish, reopening the source when looping; None at the end."""
        if self.stopped:
            return None
        if self._next is not None:
            return self._next
        while True:
            try:
                frame = next(self._frames)
            except StopIteration:
                self._count_skips()
                watching = self._watch()
                if watching is not None:
                    if watching:
                        continue    # new photos in the folder
                    return None     # waiting for them (self.waiting)
                if not self.params.loop or self._last_ns is None:
                    return None
                # Next pass starts one mean frame interval after the last frame of this one.
                gap = (self._last_ns - self._first_ns) // max(self.diag.counts().get('frames', 1) - 1, 1)
                self._offset_ns = self._last_ns + max(gap, 1) - self._first_ns   # first pass had offset 0
                self.source = self._open()
                self._frames = self._iterate(self.source)
                continue
            except PhotogramError as exc:
                self.diag.problem(f'camera source: {exc}')
                return None
            self._count_skips()
            w, h = frame.image.size if isinstance(frame.image, JpegFile) else frame.image.shape[1::-1]
            if (w, h) != (self.camera.width, self.camera.height):
                self.diag.count('skipped_size_mismatch')
                self.diag.problem(f'{frame.path}: {w}x{h} image but the calibration is for '
                                  f'{self.camera.width}x{self.camera.height}: skipped')
                continue
            self._next = frame
            return frame

    def _watch(self) -> bool | None:
        """At the end of a watched folder's photos: True when new photos came (the frames go on), False while
        waiting for them, None when the folder is not watched or stayed quiet for watch_quiet_s (its end)."""
        from photogram_ros.io.image_source import FolderSource
        quiet_s = self.params.watch_quiet_s
        if quiet_s <= 0 or self.stopped or not isinstance(self.source, FolderSource):
            return None
        now = time.monotonic()
        if self._quiet_since is None:
            self._quiet_since = now
            self.diag.set('state', f'watching {self.params.source} for new photos (the end after {quiet_s:g} s '
                                   'without one)')
        if now - self._last_scan >= WATCH_PERIOD_S:
            self._last_scan = now
            added = self.source.refresh()
            self._count_skips()
            self._quiet_since = max(self._quiet_since, self.source.activity_at)   # a file being copied: not quiet
            if added:
                self._frames = self._iterate(self.source, self.source.next_index)
                self._quiet_since, self.waiting = None, False
                self.diag.count('photos_arrived', added)
                self.diag.set('state', 'playing')
                return True
        self.waiting = now - self._quiet_since < quiet_s
        return False if self.waiting else None

    def _iterate(self, source, start: int = 0):
        """The source's frames; a folder's JPEG photos larger than compressed_above_px come as JpegFile
        (bytes read, not decoded); one whose bytes are not a whole JPEG is decoded as usual (and skipped
        with the reason when that fails)."""
        from photogram_ros.io.image_source import FolderSource
        if not isinstance(source, FolderSource):
            return iter(source)
        return source.frames(lambda path: JpegFile.read(path, self.params.compressed_above_px), start)

    def _after_stored(self, frames):
        """`frames` after the map's stored keyframes without a pose (resume_keyframes_of) stamped before the first
        of them (a folder played again from its start takes its own keyframes again)."""
        if self._stored is None:
            yield from frames
            return
        frames = iter(frames)
        first = next(frames, None)
        undecoded = (lambda path: JpegFile.read(path, self.params.compressed_above_px))
        for frame in self._stored.frames(undecoded, before_ns=None if first is None else first.stamp_ns):
            self._resumed.add(frame.stamp_ns)
            yield frame
        for path, why in self._stored.skipped:
            self.diag.count('resumed_keyframes_unreadable')
            self.diag.problem(f'stored keyframe {path} not played again: {why}')
        self._stored.skipped.clear()
        if first is not None:
            yield first
            yield from frames

    def _count_skips(self) -> None:
        new = self.source.skipped[self._reported_skips:]
        other = set(getattr(self.source, 'other_camera', ()))
        for path, why in new:
            self.diag.count('skipped_other_camera' if (path, why) in other else 'skipped_unreadable')
            self.diag.problem(f'skipped {path}: {why}')
        self._reported_skips = len(self.source.skipped)

    def peek_stamp_ns(self) -> int | None:
        """The stamp the next frame will be published with; None when the source is exhausted."""
        frame = self._peek()
        return None if frame is None else frame.stamp_ns + self._offset_ns

    def _publish_log_fixes(self, until_ns: int | None) -> None:
        """The gnss_log fixes up to `until_ns` (None: all that are left), in time order."""
        while self._log_next < len(self._log) and (until_ns is None or self._log[self._log_next].stamp_ns <= until_ns):
            self.pub_fix.publish(msgs.navsatfix_from_gnss_fix(self._log[self._log_next], self.params.fix_frame_id))
            self.diag.count('fixes')
            self._log_next += 1

    def publish_next(self) -> bool:
        """Publish the next frame (image, camera_info, EXIF fix); False when the source is exhausted."""
        frame = self._peek()
        if frame is None:
            if self.waiting:   # a watched folder: no new photo yet
                return True
            self._finish()
            return False
        self._next = None
        stamp_ns = frame.stamp_ns + self._offset_ns
        if self._first_ns is None:
            self._first_ns = stamp_ns
        self._last_ns = stamp_ns
        p = self.params
        resumed = frame.stamp_ns in self._resumed
        try:
            # The fix goes first so that a consumer holding the image already has its position.
            self._publish_log_fixes(stamp_ns)
            if (p.publish_exif_fix or resumed) and frame.gps is not None:
                fix = frame.gps.gnss_fix(stamp_ns, p.exif_sigma_m, p.exif_sigma_v_m, *self._exif_reading)
                self.pub_fix.publish(msgs.navsatfix_from_gnss_fix(fix, p.fix_frame_id))
                self.diag.count('fixes')
            self.pub_info.publish(msgs.camera_info_msg(self.camera, stamp_ns, p.frame_id))
            if isinstance(frame.image, JpegFile):
                msg = CompressedImage(header=msgs.header(stamp_ns, p.frame_id), format='jpeg')
                msg.data = frame.image.data
                self.pub_compressed.publish(msg)
                self.diag.count('frames_compressed')
            else:
                self.pub_image.publish(msgs.image_msg(frame.image, stamp_ns, p.frame_id))
        except PhotogramError as exc:
            self.diag.problem(f'{frame.path}: {exc}')
            return True
        self.diag.count('frames')
        if resumed:
            self.diag.count('resumed_keyframes')
        self.diag.set('rate_hz', self.diag.rate_hz('frames'))
        self.diag.set('last_frame', frame.path)
        return True

    def _finish(self) -> None:
        if not self.finished:
            self.finished = True
            self._publish_log_fixes(None)   # the fixes after the last frame: its position is bracketed
            self.diag.set('state', 'finished')
            self.diag.publish()
            if self._timer is not None:
                self._timer.cancel()

    def start(self) -> None:
        """Publish on the timer from now on (a node made with autostart false, held until the graph's second
        process listens: `run` with --processes 2)."""
        if self._timer is None and not self.stopped:
            self._timer = self.create_timer(0.005, self._tick)

    def stop_input(self) -> None:
        """The flight is being stopped: publish no more frames (a live camera, or a looping folder, goes on
        producing on the ground; the end of flight works on what was taken)."""
        if self.stopped:
            return
        self.stopped = True
        self._next = None
        if self._timer is not None:
            self._timer.cancel()
        self.diag.set('state', 'stopped: the end of flight takes no more frames')

    def _tick(self) -> None:
        p = self.params
        if self.finished or not self._subscribed():
            return
        if p.rate == 0:
            if all(pub.wait_for_all_acked(Duration(nanoseconds=0)) for pub in (self.pub_image, self.pub_compressed)):
                self.publish_next()
            return
        frame = self._peek()
        if frame is None:
            if not self.waiting:
                self._finish()
            return
        stamp_ns = frame.stamp_ns + self._offset_ns
        now = time.monotonic()
        resumed = frame.stamp_ns in self._resumed
        # Stored keyframes go out at their own spacing (even before a device's frames), then the source's clock
        # starts afresh at its first frame (the restart's gap is not waited for).
        if self._wall0 is None or (self._wall0_resumed and not resumed):
            self._wall0, self._wall0_resumed = (now, stamp_ns), resumed
        due = self._wall0[0] + (stamp_ns - self._wall0[1]) * 1e-9 / p.rate
        if due <= now or (getattr(self.source, 'is_device', False) and not resumed):
            self.publish_next()


    def _subscribed(self) -> bool:
        """Whether a folder or file may start: wait_for_subscribers take its images (said once while not)."""
        if self._started or getattr(self.source, 'is_device', False) or not self.params.wait_for_subscribers:
            return True
        # Each topic matches on its own: the images, their camera_info and the fixes must all be taken.
        n = min(max(self.pub_image.get_subscription_count(), self.pub_compressed.get_subscription_count()),
                self.pub_info.get_subscription_count(),
                self.pub_fix.get_subscription_count() if self.params.publish_exif_fix else 1 << 30)
        self._started = n >= self.params.wait_for_subscribers
        if not self._started and not self._said_waiting:
            self._said_waiting = True
            self.get_logger().info(f'waiting for {self.params.wait_for_subscribers} subscriber(s) of the images, '
                                   'camera_info and fixes before the first frame (wait_for_subscribers)')
            self.diag.set('state', 'waiting for subscribers')
        return self._started


WATCH_PERIOD_S = 1.0   # how often a watched folder is listed again


class JpegFile:
    """A JPEG photo's bytes, undecoded, and its (width, height) from the file's header."""

    def __init__(self, data: bytes, size: tuple):
        self.data, self.size = data, size

    @classmethod
    def read(cls, path, above_px: int) -> 'JpegFile | None':
        """The photo as a JpegFile when it is a whole JPEG whose long side exceeds `above_px`; else None
        (decode it as usual)."""
        from PIL import Image as PilImage
        try:
            with PilImage.open(path) as im:
                if im.format != 'JPEG' or max(im.size) <= above_px:
                    return None
                size = im.size
            data = path.read_bytes()
        except (OSError, SyntaxError, ValueError):
            return None
        # A truncated file lacks the end-of-image marker: decode it as usual, which names the fault.
        if not data.rstrip(b'\x00').endswith(b'\xff\xd9'):
            return None
        return cls(data, size)


def _publish_all(node) -> int:
    while rclpy.ok() and not node.finished:
        rclpy.spin_once(node, timeout_sec=0.1)
    if node.finished:
        node.pub_image.wait_for_all_acked(Duration(seconds=5))
        c = node.diag.counts()
        print(f'camera_node: published {c.get("frames", 0)} frames, {c.get("fixes", 0)} EXIF fixes; skipped '
              f'{c.get("skipped_unreadable", 0)} unreadable files and {c.get("skipped_other_camera", 0)} of another '
              'camera')
    return 0


def main(argv=None) -> int:
    """Console script `camera_node`: publishes the frames of the `source` parameter."""
    return run_job(CameraNode, _publish_all, argv)

