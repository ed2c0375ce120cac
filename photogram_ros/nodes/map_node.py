"""Map node: fuses the pair clouds into the tiled map, keeps it safe on disk, streams it to the ground.

Inputs: /map/dense_cloud (PointCloud2 in `map`, fields x, y, z and optionally rgb, confidence),
/keyframes/image + /map/keyframe_pose + /camera/camera_info (saved in map_dir for the orthomosaic),
and the geodetic origin of `map`: either the parameters origin_lat_deg/origin_lon_deg/origin_h_m
(use_origin_params: true) or /map/georeference, a sensor_msgs/NavSatFix whose latitude, longitude
and altitude (ellipsoidal, REP-145) are the `map` origin, published with transient-local QoS.
A map_dir that already holds a map keeps its origin and reloads (restart after a crash).

Outputs: /map/cloud_downsampled (best effort: block means of the tiles that changed, at most
stream_max_points per message, at most one message per stream_period_s); /map/ortho_tiles (best
effort, the same way: the XYZ / Web Mercator tiles of the live orthomosaic that changed, one
CompressedImage PNG per tile named xyz/Z/X/Y, at most one batch per ortho_period_s, core/ortho_tiles.py);
/map/coverage (std_msgs/String, latched: GeoJSON of the survey's coverage and gaps, every
coverage_period_s, from the keyframe poses, the camera and the ground height of /map/sparse_cloud,
core/coverage.py; the survey area is `survey_area_file`, a QGroundControl .plan or GeoJSON, when
given); and /diagnostics (with the coverage figures; a new gap is a WARN naming its area and place).
Changed cells are flushed to disk every flush_interval_s, so a kill -9 loses at most that much.
Topic names are relative, so a drone's namespace (several drones, one ground station) prefixes them.
The streams are stamped with the node's clock (the bag's time in a replay, use_sim_time), or the newest
pair cloud's stamp while that clock has no time yet; their periods run on the steady clock, so the map
flushes and streams also while /clock stands still.
"""

from __future__ import annotations

import dataclasses
import errno
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
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, NavSatFix, PointCloud2

from photogram_ros import msgs
from photogram_ros.core import gsd
from photogram_ros.core.coverage import COVERAGE, FORWARD_OVERLAP, NOT_ORIENTED, Coverage, CoverageConfig
from photogram_ros.core.fusion import Fusion, FusionConfig, downsample, pack_rgb
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.errors import ConfigError, PhotogramError
from photogram_ros.io.map_store import MapStore
from photogram_ros.nodes.diagnostics import ERROR, Diagnostics, steady_timer
from photogram_ros.nodes.node_main import run_node
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param

TOPIC_CLOUD = 'map/dense_cloud'   # relative: a drone's namespace prefixes them
TOPIC_DOWNSAMPLED = 'map/cloud_downsampled'
TOPIC_GEOREFERENCE = 'map/georeference'
TOPIC_IMAGE = 'keyframes/image'
TOPIC_POSE = 'map/keyframe_pose'
TOPIC_INFO = 'camera/camera_info'
TOPIC_ORTHO = 'map/ortho_tiles'
TOPIC_COVERAGE = 'map/coverage'
TOPIC_SPARSE = 'map/sparse_cloud'
TOPIC_KEYFRAME_FIX = 'keyframes/fix'

STREAM_DTYPE = np.dtype([('x', np.float32), ('y', np.float32), ('z', np.float32), ('rgb', np.uint32),
                         ('count', np.uint32)])


@dataclass
class MapParams(FusionConfig, CoverageConfig):
    """The fusion's (core/fusion.py) and the coverage's (core/coverage.py) parameters and the node's: folder,
    origin, keyframes, streams."""
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
    ortho: bool = param(True, f'Stream the live orthomosaic of the changed tiles on {TOPIC_ORTHO}')
    ortho_gsd_m: float = param(0.2, 'Ground pixel of the live ortho tiles, m: the XYZ zoom level whose pixel is '
                                    'the finest not finer than this', min=0.01, max=1000.0)
    ortho_period_s: float = param(2.0, f'Period of {TOPIC_ORTHO} batches, s', min=0.05, max=3600.0)
    ortho_max_tiles: int = param(16, 'Most ortho tiles per batch; the rest follows next period', min=1, max=10000)
    coverage: bool = param(True, f'Follow the survey coverage and its gaps ({TOPIC_COVERAGE}, /diagnostics)')
    coverage_period_s: float = param(1.0, f'Period of the coverage update and of {TOPIC_COVERAGE}, s',
                                     min=0.1, max=3600.0)
    survey_area_file: str = param('', 'Survey area: a QGroundControl .plan (its Survey polygon or geofence) or a '
                                      'GeoJSON polygon; "" = the flight lines\' swaths')
    warn_unfused_keyframes: int = param(20, 'WARN on /diagnostics when this many keyframes came (images, or poses '
                                            'without save_keyframes) and '
                                            'nothing was fused since the last fused cloud (thrice as many before '
                                            'the first), with the reason', min=1, max=100000)


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
        self._newest_cloud_ns = 0
        self._lock = threading.RLock()   # callbacks run in one group, but close() may come from any thread
        try:
            self.store = self._open_store(p)
        except PhotogramError as exc:
            raise ConfigError(f'map_node: {exc}') from exc
        self.gsd = None                # core.gsd.GsdSettings once derived
        self._cell_pending = p.cell_m == gsd.AUTO and not self.store.tile_keys()
        self.fusion = Fusion(self._fusion_config(self.store.cell_m), self.store)
        self._keyframes_unfused = 0    # keyframe poses since the last cloud that fused points
        self._clouds_unfused = 0       # clouds since then (that fused nothing)
        self._pose_z: dict = {}        # stamp -> camera height in map (the flying height for the GSD)
        if p.use_origin_params:
            self._set_origin(LocalFrame(p.origin_lat_deg, p.origin_lon_deg, p.origin_h_m))
        self._stream_pending: set = set(self.store.tile_keys())   # a restarted map streams what it has
        self._ortho_pending: set = set(self._stream_pending)
        self.ortho = None            # core.ortho_tiles.OrthoTiler, once the origin is known
        self.coverage = None         # core.coverage.Coverage, once the camera is known
        self._cov_poses: dict = {}   # stamp -> map_T_cam not yet in the coverage
        self._cov_fixes: dict = {}   # stamp -> keyframe fix in map ENU (the track, oriented or not)
        self._oriented: dict = {}    # stamp -> map_T_cam of the oriented keyframes (attitude for stand-ins)
        self._cov_dirty = False
        self._sparse_xyz = None      # (N, 3) latest tie points: the ground under the keyframes
        self._camera = None
        self._gaps_reported: list = []   # centroids of the gaps already warned about
        self._survey_rings = None
        if p.survey_area_file:       # a bad file stops the start, naming it
            from photogram_ros.io.mission import read_survey_area
            try:
                self._survey_rings = read_survey_area(p.survey_area_file)
            except PhotogramError as exc:
                raise ConfigError(f'map_node: {exc}') from exc
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
        if p.save_keyframes or p.coverage:
            self.create_subscription(PoseWithCovarianceStamped, TOPIC_POSE, self._on_pose, reliable,
                                     callback_group=group)
            self.create_subscription(CameraInfo, TOPIC_INFO, self._on_info, qos_profile_sensor_data,
                                     callback_group=group)
        best_effort = QoSProfile(depth=2, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.stream_pub = self.create_publisher(PointCloud2, TOPIC_DOWNSAMPLED, best_effort)
        if p.ortho:   # one message per tile: a batch must fit the history
            self.ortho_pub = self.create_publisher(CompressedImage, TOPIC_ORTHO, QoSProfile(
                depth=p.ortho_max_tiles, reliability=ReliabilityPolicy.BEST_EFFORT))
            steady_timer(self, p.ortho_period_s, self._stream_ortho, group)
        if p.coverage:
            from std_msgs.msg import String
            self.coverage_pub = self.create_publisher(String, TOPIC_COVERAGE, latched)
            self.create_subscription(PointCloud2, TOPIC_SPARSE, self._on_sparse, QoSProfile(depth=2),
                                     callback_group=group)
            self.create_subscription(NavSatFix, TOPIC_KEYFRAME_FIX, self._on_keyframe_fix, reliable,
                                     callback_group=group)
            steady_timer(self, p.coverage_period_s, self._update_coverage, group)
        steady_timer(self, p.flush_interval_s, self.flush, group)
        steady_timer(self, p.stream_period_s, self._stream, group)
        steady_timer(self, 1.0, self._update_diag, group)
        self.get_logger().info(f'map in {p.map_dir}: {len(self.store.tile_keys())} tiles on disk, origin '
                               f'{self.store.origin}')

    # --- GSD-bound geometry ----------------------------------------------------------------------

    @staticmethod
    def _open_store(p: MapParams) -> MapStore:
        """The map folder: an existing map keeps its cell; a new one with cell_m AUTO starts with the
        simulator's cell until the first pair cloud tells the flying height (MapStore.set_cell_m)."""
        from pathlib import Path
        if (Path(p.map_dir) / 'map.json').exists():
            return MapStore(p.map_dir, None if p.cell_m == gsd.AUTO else p.cell_m, p.tile_cells)
        cell = gsd.REF_LENGTHS_M['cell_m'] if p.cell_m == gsd.AUTO else p.cell_m
        return MapStore(p.map_dir, cell, p.tile_cells)

    def _fusion_config(self, cell_m: float, settings: gsd.GsdSettings | None = None) -> FusionConfig:
        """The fusion's parameters with the cell of the store and the AUTO tolerance scaled with it."""
        cfg = FusionConfig(**{f.name: getattr(self.params, f.name) for f in dataclasses.fields(FusionConfig)})
        tol = cfg.min_tolerance_m
        if tol == gsd.AUTO:
            tol = settings.min_tolerance_m if settings is not None else gsd.tolerance_for_cell(cell_m)
        return dataclasses.replace(cfg, cell_m=float(cell_m), min_tolerance_m=tol)

    def _derive_cell(self, cloud_z: np.ndarray) -> None:
        """First pair cloud: the cell from the GSD (camera, newest keyframe height above this cloud)."""
        self._cell_pending = False
        if self._camera is None or not self._pose_z:
            self.diag.problem(f'cell_m from the GSD needs camera_info and a keyframe pose before the first pair '
                              f'cloud: keeping {self.store.cell_m} m')
            return
        height = self._pose_z[max(self._pose_z)] - float(np.median(cloud_z))
        try:
            self.gsd = gsd.derive(self._camera.width, self._camera.height, self._camera.fx, height)
        except ConfigError as exc:
            self.diag.problem(f'cell_m from the GSD: {exc}; keeping {self.store.cell_m} m')
            return
        cell = self.gsd.cell_m if self.params.cell_m == gsd.AUTO else self.params.cell_m
        if cell != self.store.cell_m:
            self.store.set_cell_m(cell)
        self.fusion = Fusion(self._fusion_config(cell, self.gsd), self.store)
        self.get_logger().info(f'map cell {cell} m, fusion tolerance {self.fusion.config.min_tolerance_m} m from '
                               f'the GSD: {self.gsd.summary()}')
        self.diag.set('gsd_m', self.gsd.gsd_m)

    @property
    def cell_m(self) -> float:
        return self.fusion.config.cell_m

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
            if self._cell_pending and pts.size:
                self._derive_cell(np.asarray(pts['z'], float))
            t0 = time.perf_counter()
            n = self.fusion.add(pts)
            if n:
                self._keyframes_unfused = self._clouds_unfused = 0
            else:
                self._clouds_unfused += 1
            self._newest_cloud_ns = max(self._newest_cloud_ns, msgs.ns_from_time(msg.header.stamp))
            self._fuse_s += time.perf_counter() - t0
            self.diag.count('clouds')
            self.diag.count('points_fused', n)
            self._stream_pending |= self.fusion.changed_tiles
            self._ortho_pending |= self.fusion.changed_tiles
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
            self._keyframes_unfused += 1
            self.store.save_keyframe_image(msgs.ns_from_time(msg.header.stamp), buf.tobytes())
            self.diag.count('keyframes_saved')
        except (PhotogramError, OSError) as exc:
            self._write_failed('keyframe image not saved', exc)

    @_locked
    def _on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        # The bundle adjuster republishes each pose while it sits in its window: keep the latest and
        # write it at the next flush, instead of an fsync per republication.
        try:
            T, _ = msgs.T_from_pose_with_covariance(msg)
            stamp = msgs.ns_from_time(msg.header.stamp)
            if stamp not in self._pose_z and not self.params.save_keyframes:
                self._keyframes_unfused += 1   # (with save_keyframes the images count, in flight order)
            self._pose_z[stamp] = float(T[2, 3])
            if self.params.save_keyframes:
                self._poses_pending[stamp] = T
            if self.params.coverage:
                self._cov_poses[stamp] = T
        except PhotogramError as exc:
            self.diag.problem(f'keyframe pose not saved: {exc}')

    def _save_poses(self) -> None:
        pending, self._poses_pending = self._poses_pending, {}
        for stamp_ns, T in pending.items():
            try:
                self.store.save_keyframe_pose(stamp_ns, T)
                self.diag.count('poses_saved')
            except OSError as exc:
                self._write_failed('keyframe pose not saved', exc)

    @_locked
    def _on_keyframe_fix(self, msg: NavSatFix) -> None:
        if self.store.origin is None or msg.status.status < 0:
            return
        try:
            f = msgs.fix_from_navsatfix(msg)
            self._cov_fixes[f['stamp_ns']] = np.asarray(
                self.store.origin.geodetic_to_enu(f['lat_deg'], f['lon_deg'], f['h_m']), float).reshape(3)
        except (PhotogramError, ValueError) as exc:
            self.diag.problem(f'keyframe fix not used for the coverage: {exc}')

    def _stand_in(self, stamp: int) -> np.ndarray | None:
        """A keyframe the adjustment has not oriented: its fix, with the attitude of the oriented keyframe
        nearest in time turned by the change of the track's heading between the two."""
        if not self._oriented:
            return None
        ref = min(self._oriented, key=lambda s: abs(s - stamp))
        T = self._oriented[ref].copy()
        dpsi = self._heading(stamp) - self._heading(ref)
        if np.isfinite(dpsi):
            c, s_ = np.cos(dpsi), np.sin(dpsi)
            T[:3, :3] = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]) @ T[:3, :3]
        T[:3, 3] = self._cov_fixes[stamp]
        return T

    def _heading(self, stamp: int) -> float:
        """Direction of travel at a keyframe, from its neighbours on the fix track, rad from east."""
        stamps = sorted(self._cov_fixes)
        if stamp not in self._cov_fixes or len(stamps) < 2:
            return float('nan')
        i = stamps.index(stamp)
        a, b = stamps[max(i - 1, 0)], stamps[min(i + 1, len(stamps) - 1)]
        d = self._cov_fixes[b] - self._cov_fixes[a]
        return float(np.arctan2(d[1], d[0])) if np.hypot(d[0], d[1]) > 0.1 else float('nan')

    @_locked
    def _on_sparse(self, msg: PointCloud2) -> None:
        try:
            pts = msgs.points_from_pointcloud2(msg)
            xyz = np.column_stack([pts['x'], pts['y'], pts['z']]).astype(np.float64)
            self._sparse_xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
        except (PhotogramError, ValueError) as exc:
            self.diag.problem(f'sparse cloud not used for the coverage: {exc}')

    def _on_info(self, msg: CameraInfo) -> None:
        try:
            cam = msgs.camera_from_info(msg)
            self._camera = cam
            if not self.params.save_keyframes:
                return
            if cam != self._camera_saved:
                self.store.save_camera(cam)
                self._camera_saved = cam
        except (PhotogramError, OSError) as exc:
            self._write_failed('camera info not saved', exc)

    # --- outputs ---------------------------------------------------------------------------------

    @_locked
    def flush(self) -> None:
        self._save_poses()
        try:
            n = self.fusion.flush()
            if n:
                self.diag.count('cells_flushed', n)
        except OSError as exc:
            self._write_failed(f'map flush to {self.params.map_dir} failed', exc)

    def _write_failed(self, what: str, exc: Exception) -> None:
        """A failed write: a full disk is an ERROR (counted in write_failures on /diagnostics, one stable
        message), anything else a WARN naming it."""
        self.diag.set('write_failures', self.store.write_failures)
        if getattr(exc, 'errno', None) == errno.ENOSPC:
            self.diag.problem(f'the disk of {self.params.map_dir} is full: map writes fail (write_failures)',
                              level=ERROR)
        else:
            self.diag.problem(f'{what}: {exc}')

    def _stamp_ns(self) -> int:
        """Now on the node's clock, or the newest pair cloud's stamp while that clock reads 0 (use_sim_time
        and no /clock yet)."""
        return self.get_clock().now().nanoseconds or self._newest_cloud_ns

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
            pts = downsample(self.fusion.tile_points(key, rec), p.stream_downsample, self.cell_m)
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
        self.stream_pub.publish(msgs.pointcloud2_msg(out, self._stamp_ns(), 'map'))
        self.diag.count('stream_points', n)

    @_locked
    def _stream_ortho(self) -> None:
        """PNGs of the XYZ tiles the changed fusion tiles touch (kept for later while nobody listens)."""
        if not self._ortho_pending or self.store.origin is None or self.ortho_pub.get_subscription_count() == 0:
            return
        from photogram_ros.core.ortho_tiles import OrthoTiler
        p = self.params
        if self.ortho is None:
            self.ortho = OrthoTiler(self.store.origin, self.cell_m, p.tile_cells, p.ortho_gsd_m)
            self.diag.set('ortho_zoom', self.ortho.zoom)
        xyz, keys = [], sorted(self._ortho_pending)
        for key in keys:
            for t in self.ortho.tiles_of_map_tile(key):
                if t not in xyz:
                    xyz.append(t)
        batch = xyz[:p.ortho_max_tiles]
        # A map tile is done once every XYZ tile it touches went out.
        self._ortho_pending = {k for k in keys if any(t not in batch for t in self.ortho.tiles_of_map_tile(k))}
        import cv2
        t0 = time.perf_counter()
        stamp = self._stamp_ns()
        for t in batch:
            img = self.ortho.render(t, self.fusion.tile_records)
            if not img[..., 3].any():
                continue
            ok, buf = cv2.imencode('.png', img, [cv2.IMWRITE_PNG_COMPRESSION, 6])
            if ok:
                self.ortho_pub.publish(msgs.ortho_tile_msg(t.z, t.x, t.y, buf.tobytes(), stamp))
                self.diag.count('ortho_tiles_sent')
                self.diag.count('ortho_bytes_sent', len(buf))
        self.diag.set('ortho_render_s', time.perf_counter() - t0)

    def _ground_z(self, centre: np.ndarray) -> float | None:
        """Median height of the tie points within 30 m of a camera (all of them when none is that close)."""
        s = self._sparse_xyz
        if s is None or not len(s):
            return None
        near = np.hypot(s[:, 0] - centre[0], s[:, 1] - centre[1]) < 30.0
        return float(np.median(s[near, 2] if near.sum() >= 10 else s[:, 2]))

    @_locked
    def _update_coverage(self) -> None:
        if self._camera is None or self.store.origin is None:
            return
        if self.coverage is None:
            from photogram_ros.io.mission import survey_area_in_map
            area = survey_area_in_map(self._survey_rings, self.store.origin) if self._survey_rings else None
            self.coverage = Coverage(self._camera, CoverageConfig(**{
                f: getattr(self.params, f) for f in CoverageConfig.__dataclass_fields__}), area)
        for stamp in list(self._cov_poses):
            T = self._cov_poses[stamp]
            gz = self._ground_z(T[:3, 3])
            if gz is None:
                continue   # waits for the first sparse cloud
            self.coverage.set_keyframe(stamp, T, gz)
            self._oriented[stamp] = T
            del self._cov_poses[stamp]
            self._cov_dirty = True
        for stamp in [s for s in self._cov_fixes if s not in self._oriented and not self.coverage.oriented(s)]:
            T = self._stand_in(stamp)
            gz = self._ground_z(T[:3, 3]) if T is not None else None
            if gz is not None:
                self.coverage.set_keyframe(stamp, T, gz, oriented=False)
                self._cov_dirty = True
        if self._cov_dirty:
            self._cov_dirty = False
            self.publish_coverage()

    def publish_coverage(self) -> None:
        """Update the coverage, publish its GeoJSON and figures, and warn about each new gap."""
        from photogram_ros.io.mission import coverage_geojson
        t0 = time.perf_counter()
        rep = self.coverage.update()
        origin = self.store.origin
        extra = {'stamp_ns': self.coverage.newest_stamp_ns, **self.coverage.flight_figures()}
        doc = coverage_geojson(rep, origin, extra)
        self.coverage_pub.publish(msgs.json_msg(doc))
        d, props = self.diag, doc['properties']
        d.set('coverage_s', time.perf_counter() - t0)
        for k in ('coverage_share', 'forward_overlap_median', 'side_overlap_min', 'survey_area_m2', 'gap_area_m2',
                  'largest_gap_m2'):
            d.set(k, float('nan') if props[k] is None else float(props[k]))
        d.set('gaps', sum(g.kind == COVERAGE for g in rep.gaps))
        d.set('not_oriented_gaps', sum(g.kind == NOT_ORIENTED for g in rep.gaps))
        for g in rep.gaps:
            if g.kind == FORWARD_OVERLAP or any(k == g.kind and np.hypot(*(g.centroid_map_m - c)) < 5.0
                                                for k, c in self._gaps_reported):
                continue
            self._gaps_reported.append((g.kind, g.centroid_map_m))
            lat, lon, _ = origin.enu_to_geodetic(np.array([*g.centroid_map_m, 0.0]))
            what = (f'seen by {g.min_views} keyframes' if g.kind == COVERAGE else
                    f'seen only by keyframes the adjustment did not orient')
            d.problem(f'{g.kind} gap of {g.area_m2:.0f} m2 at {float(lat):.6f}, {float(lon):.6f} ({what})')

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
        d.set('cell_m', self.cell_m)
        d.set('write_failures', self.store.write_failures)
        d.set('keyframes_unfused', self._keyframes_unfused)
        # Before the first fused cloud stereo waits for settled poses and a ground height: thrice as long.
        n = self.params.warn_unfused_keyframes * (1 if self.fusion.stats.points_fused else 3)
        if self._keyframes_unfused >= n:
            d.problem(self._unfused_reason(n))

    def _unfused_reason(self, n: int) -> str:
        """Why nothing was fused for `n` keyframes (a stable text: logged once)."""
        if self._clouds_unfused == 0:
            return (f'nothing fused for {n}+ keyframes: stereo_node sent no pair cloud (see its diagnostics: poses '
                    'refused for their sigma, pairs skipped for overlap or baseline, no ground height yet)')
        return (f'nothing fused for {n}+ keyframes: the pair clouds that came were rejected (points_rejected: '
                'disagreeing with the map; or below min_confidence / not finite)')

    @_locked
    def finish_coverage(self) -> None:
        """End of flight: every survey cell counts as passed; the last coverage goes out."""
        if self.coverage is not None and len(self.coverage):
            self.coverage.finish()
            self.publish_coverage()

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
