"""Map node: fuses the pair clouds into the tiled map, keeps it safe on disk, streams it to the ground.

Inputs: /map/dense_cloud (PointCloud2 in `map`, fields x, y, z and optionally rgb, confidence),
/keyframes/image + /map/keyframe_pose + /camera/camera_info (saved in map_dir for the orthomosaic),
and the geodetic origin of `map`: either the parameters origin_lat_deg/origin_lon_deg/origin_h_m
(use_origin_params: true) or /map/georeference, a sensor_msgs/NavSatFix whose latitude, longitude
and altitude (ellipsoidal, REP-145) are the `map` origin, published with transient-local QoS.
A map_dir that already holds a map keeps its origin and reloads (restart after a crash).

Outputs: /map/cloud_downsampled (best effort: block means of the tiles that changed, at most
stream_max_points per message, at most one message per stream_period_s) and /diagnostics.
Changed cells are flushed to disk every flush_interval_s, so a kill -9 loses at most that much.
Topic names are relative, so a drone's namespace (several drones, one ground station) prefixes them.
"""

from __future__ import annotations

import sys
import functools
import threading
import time
from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, NavSatFix, PointCloud2

from photogram_ros import msgs
from photogram_ros.core.fusion import Fusion, FusionConfig, downsample, pack_rgb
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.errors import ConfigError, PhotogramError
from photogram_ros.io.map_store import MapStore
from photogram_ros.nodes.diagnostics import Diagnostics
from photogram_ros.nodes.node_main import run_node
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param

TOPIC_CLOUD = 'map/dense_cloud'   # relative: a drone's namespace prefixes them
TOPIC_DOWNSAMPLED = 'map/cloud_downsampled'
TOPIC_GEOREFERENCE = 'map/georeference'
TOPIC_IMAGE = 'keyframes/image'
TOPIC_POSE = 'map/keyframe_pose'
TOPIC_INFO = 'camera/camera_info'

STREAM_DTYPE = np.dtype([('x', np.float32), ('y', np.float32), ('z', np.float32), ('rgb', np.uint32),
                         ('count', np.uint32)])


@dataclass
class MapParams(FusionConfig):
    """The fusion's parameters (core/fusion.py FusionConfig) and the node's: folder, origin, keyframes, stream."""
    map_dir: str = param('map', 'Folder of the persistent map (tiles, keyframes, map.json); reloaded if it exists')
    flush_interval_s: float = param(1.0, 'Changed cells are written and fsynced this often, s (the most a '
                                         'crash can lose)', min=0.05, max=600.0)
    use_origin_params: bool = param(False, 'Take the map origin from origin_* instead of /map/georeference')
    origin_lat_deg: float = param(0.0, 'Latitude of the map origin, deg (with use_origin_params)',
                                  min=-90.0, max=90.0)
    origin_lon_deg: float = param(0.0, 'Longitude of the map origin, deg (with use_origin_params)',
                                  min=-180.0, max=180.0)
    origin_h_m: float = param(0.0, 'Ellipsoidal height of the map origin, m (with use_origin_params)',
                              min=-1e4, max=1e5)
    save_keyframes: bool = param(True, 'Save keyframe JPEGs and poses in map_dir (needed for the orthomosaic)')
    jpeg_quality: int = param(90, 'JPEG quality of saved keyframes', min=10, max=100)
    stream_period_s: float = param(2.0, f'Period of {TOPIC_DOWNSAMPLED} messages, s', min=0.05, max=3600.0)
    stream_downsample: int = param(4, 'Stream block size in cells (4: one point per 4x4 cells)', min=1, max=256)
    stream_max_points: int = param(50000, 'Most points per stream message; the rest follows next period',
                                   min=100, max=10_000_000)


def _locked(method):
    """Run a MapNode method under the node's lock (the fusion and its tiles are not thread-safe)."""
    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)
    return wrapper


class MapNode(Node):
    def __init__(self, overrides: dict | None = None, **node_kwargs):
        super().__init__('map_node', **node_kwargs)
        self.params: MapParams = declare(self, MapParams, overrides)
        p = self.params
        self.diag = Diagnostics(self)
        self._lock = threading.RLock()   # callbacks run in one group, but close() may come from any thread
        try:
            self.store = MapStore(p.map_dir, p.cell_m, p.tile_cells)
        except PhotogramError as exc:
            raise ConfigError(f'map_node: {exc}') from exc
        self.fusion = Fusion(p, self.store)
        if p.use_origin_params:
            self._set_origin(LocalFrame(p.origin_lat_deg, p.origin_lon_deg, p.origin_h_m))
        self._stream_pending: set = set(self.store.tile_keys())   # a restarted map streams what it has
        self._camera_saved = None
        self._poses_pending: dict = {}
        self._fuse_s = 0.0
        self._closed = False
        group = MutuallyExclusiveCallbackGroup()   # the map is not thread-safe; graph.py spins multi-threaded
        # KEEP_ALL: the map is the sink that persists the flight; a burst of pair clouds while it is
        # fusing must queue, not overwrite clouds that were never fused.
        reliable = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(PointCloud2, TOPIC_CLOUD, self._on_cloud, reliable, callback_group=group)
        self.create_subscription(NavSatFix, TOPIC_GEOREFERENCE, self._on_georeference, latched,
                                 callback_group=group)
        if p.save_keyframes:
            self.create_subscription(Image, TOPIC_IMAGE, self._on_image, reliable, callback_group=group)
            self.create_subscription(PoseWithCovarianceStamped, TOPIC_POSE, self._on_pose, reliable,
                                     callback_group=group)
            self.create_subscription(CameraInfo, TOPIC_INFO, self._on_info, qos_profile_sensor_data,
                                     callback_group=group)
        best_effort = QoSProfile(depth=2, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.stream_pub = self.create_publisher(PointCloud2, TOPIC_DOWNSAMPLED, best_effort)
        self.create_timer(p.flush_interval_s, self.flush, callback_group=group)
        self.create_timer(p.stream_period_s, self._stream, callback_group=group)
        self.create_timer(1.0, self._update_diag, callback_group=group)
        self.get_logger().info(f'map in {p.map_dir}: {len(self.store.tile_keys())} tiles on disk, origin '
                               f'{self.store.origin}')

    # --- inputs ----------------------------------------------------------------------------------

    def _set_origin(self, frame: LocalFrame) -> None:
        old = self.store.origin
        if old is not None and np.allclose([old.lat_deg, old.lon_deg, old.h_m],
                                           [frame.lat_deg, frame.lon_deg, frame.h_m], atol=1e-9):
            return
        if old is not None and self.store.tile_keys():
            self.diag.problem(f'map origin changed from {old} to {frame} although {self.store.root} holds '
                              'tiles in the old frame; keeping the old origin')
            return
        self.store.set_origin(frame)

    @_locked
    def _on_georeference(self, msg: NavSatFix) -> None:
        if self.params.use_origin_params:
            return
        try:
            self._set_origin(LocalFrame(msg.latitude, msg.longitude, msg.altitude))
        except PhotogramError as exc:
            self.diag.problem(f'bad georeference: {exc}')

    @_locked
    def _on_cloud(self, msg: PointCloud2) -> None:
        try:
            if msg.header.frame_id not in ('map', ''):
                raise ConfigError(f'dense cloud in frame {msg.header.frame_id!r}; the map fuses clouds in "map"')
            pts = msgs.points_from_pointcloud2(msg)
            t0 = time.perf_counter()
            n = self.fusion.add(pts)
            self._fuse_s += time.perf_counter() - t0
            self.diag.count('clouds')
            self.diag.count('points_fused', n)
            self._stream_pending |= self.fusion.changed_tiles
            self.fusion.changed_tiles.clear()
        except PhotogramError as exc:
            self.diag.count('clouds_dropped')
            self.diag.problem(f'dense cloud dropped: {exc}')
        except (ValueError, TypeError) as exc:
            self.diag.count('clouds_dropped')
            self.diag.problem(f'dense cloud dropped (malformed): {exc}')

    def _on_image(self, msg: Image) -> None:
        try:
            import cv2
            img = msgs.image_from_msg(msg)
            ok, buf = cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, self.params.jpeg_quality])
            if not ok:
                raise ConfigError('JPEG encoding of a keyframe failed')
            self.store.save_keyframe_image(msgs.ns_from_time(msg.header.stamp), buf.tobytes())
            self.diag.count('keyframes_saved')
        except (PhotogramError, OSError) as exc:
            self.diag.problem(f'keyframe image not saved: {exc}')

    @_locked
    def _on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        # The bundle adjuster republishes each pose while it sits in its window: keep the latest and
        # write it at the next flush, instead of an fsync per republication.
        try:
            T, _ = msgs.T_from_pose_with_covariance(msg)
            self._poses_pending[msgs.ns_from_time(msg.header.stamp)] = T
        except PhotogramError as exc:
            self.diag.problem(f'keyframe pose not saved: {exc}')

    def _save_poses(self) -> None:
        pending, self._poses_pending = self._poses_pending, {}
        for stamp_ns, T in pending.items():
            try:
                self.store.save_keyframe_pose(stamp_ns, T)
                self.diag.count('poses_saved')
            except OSError as exc:
                self.diag.problem(f'keyframe pose not saved: {exc}')

    def _on_info(self, msg: CameraInfo) -> None:
        try:
            cam = msgs.camera_from_info(msg)
            if cam != self._camera_saved:
                self.store.save_camera(cam)
                self._camera_saved = cam
        except (PhotogramError, OSError) as exc:
            self.diag.problem(f'camera info not saved: {exc}')

    # --- outputs ---------------------------------------------------------------------------------

    @_locked
    def flush(self) -> None:
        self._save_poses()
        try:
            n = self.fusion.flush()
            if n:
                self.diag.count('cells_flushed', n)
        except OSError as exc:
            self.diag.problem(f'map flush to {self.params.map_dir} failed: {exc}')

    @_locked
    def _stream(self) -> None:
        # Nobody listening (no ground station linked): keep the changed tiles for when one connects
        # instead of spending a quarter second per period on block means.
        if not self._stream_pending or self.stream_pub.get_subscription_count() == 0:
            return
        p = self.params
        parts, total = [], 0
        for key in sorted(self._stream_pending):
            rec = self.fusion.tile_records(key)
            self._stream_pending.discard(key)
            if rec is None:
                continue
            pts = downsample(self.fusion.tile_points(key, rec), p.stream_downsample, p.cell_m)
            parts.append(pts)
            total += pts['x'].size
            if total >= p.stream_max_points:
                break
        if not total:
            return
        cat = {k: np.concatenate([q[k] for q in parts]) for k in ('x', 'y', 'z', 'r', 'g', 'b', 'n')}
        out = np.zeros(min(total, p.stream_max_points), dtype=STREAM_DTYPE)
        n = out.size
        for k in ('x', 'y', 'z'):
            out[k] = cat[k][:n]
        out['rgb'] = pack_rgb(cat['r'][:n], cat['g'][:n], cat['b'][:n])
        out['count'] = cat['n'][:n]
        self.stream_pub.publish(msgs.pointcloud2_msg(out, self.get_clock().now().nanoseconds, 'map'))
        self.diag.count('stream_points', n)

    @_locked
    def _update_diag(self) -> None:
        st = self.fusion.stats
        d = self.diag
        d.set('points_in', st.points_in)
        d.set('points_rejected', st.points_rejected)
        d.set('cells_rebuilt', st.cells_replaced)
        d.set('tiles_in_memory', len(self.fusion.tiles))
        d.set('tiles_on_disk', len(self.store.tile_keys()))
        d.set('tiles_evicted', st.tiles_evicted)
        d.set('memory_mb', self.fusion.memory_bytes / 1e6)
        d.set('disk_mb', self.store.disk_bytes() / 1e6)
        d.set('fuse_points_per_s', st.points_in / self._fuse_s if self._fuse_s > 0 else 0.0)
        d.set('clouds_per_s', d.rate_hz('clouds'))
        d.set('origin', str(self.store.origin.to_dict()) if self.store.origin else 'unknown')

    @_locked
    def close(self) -> None:
        """Flush everything to disk (shutdown, SIGINT, SIGTERM)."""
        if not self._closed:
            self._closed = True
            self.flush()

    def destroy_node(self):
        self.close()
        return super().destroy_node()


def main(argv=None) -> int:
    """Console script `map_node`."""
    return run_node(MapNode, argv)


if __name__ == '__main__':
    sys.exit(main())
