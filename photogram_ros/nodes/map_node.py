"""Map node: fuses the pair clouds into the tiled map, keeps it safe on disk, streams it to the ground.

Inputs: /map/dense_cloud (PointCloud2 in `map`, fields x, y, z and optionally rgb, confidence),
/keyframes/image + /map/keyframe_pose + /camera/camera_info (saved in map_dir for the orthomosaic; a
keyframe image reduced for stereo is replaced by its full-resolution JPEG from /keyframes/image/compressed,
saved as it came; once
/map/camera_final, the camera of the bundle adjuster's full adjustment, comes, that one is saved instead;
/map/control_points, the bundle adjuster's check points with their detections, saved for the report),
and the geodetic origin of `map`: either the parameters origin_lat_deg/origin_lon_deg/origin_h_m
(use_origin_params: true) or /map/georeference, a sensor_msgs/NavSatFix whose latitude, longitude
and altitude (ellipsoidal, REP-145) are the `map` origin, published with transient-local QoS.
A map_dir that already holds a map keeps its origin and reloads (restart after a crash).

/map/dense_cloud_pose (PoseWithCovarianceStamped: the pose stereo placed its next pair cloud of that keyframe
with, provisional or final by its covariance) and every pose on /map/keyframe_pose, provisional ones included:
a fused cloud whose keyframe's pose moved by replace_move_m, or turned final (replace_provisional), is taken out
of the map and fused again at the new pose (stages/map.py replace_moved, every 0.5 s); /diagnostics says keyframes_fused_provisional
(keyframes whose clouds are placed with a provisional pose now) and counts clouds_replaced.

Outputs: /map/cloud_downsampled (best effort: block means of the tiles that changed, at most
stream_max_points per message, at most one message per stream_period_s); /map/ortho_tiles (best
effort, the same way: the XYZ / Web Mercator tiles of the live orthomosaic that changed, one
CompressedImage PNG per tile named xyz/Z/X/Y, at most one batch per ortho_period_s, core/ortho_tiles.py);
/map/coverage (std_msgs/String, latched: GeoJSON of the survey's coverage and gaps, every
coverage_period_s, from the keyframe poses, the camera and the ground height of /map/sparse_cloud,
core/coverage.py; the survey area is `survey_area_file`, a QGroundControl .plan or GeoJSON, when
given); and /diagnostics (with the coverage figures; a new gap is a WARN naming its area and place).
Changed cells are flushed to disk every flush_interval_s, so a kill -9 loses at most that much; with
flush_beside_fusion the flush has a callback group of its own, so clouds are fused while it syncs.
Topic names are relative, so a drone's namespace (several drones, one ground station) prefixes them.
The node is an adapter: the map is the ROS-free stage (stages/map.py), which it feeds from the topics
and whose streams it publishes.
The streams are stamped with the node's clock (the bag's time in a replay, use_sim_time), or the newest
pair cloud's stamp while that clock has no time yet; their periods run on the steady clock, so the map
flushes and streams also while /clock stands still.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, NavSatFix, PointCloud2

from photogram_ros import msgs
from photogram_ros.core.pace import ThreadCaps, limit_threads
from photogram_ros.nodes import qos
from photogram_ros.nodes.diagnostics import Diagnostics, steady_timer
from photogram_ros.nodes.node_main import run_node
from photogram_ros.nodes.ros_params import declare
from photogram_ros.nodes.stage_diagnostics import StageDiagnostics
from photogram_ros.stages.map import STREAM_DTYPE, MapOutputs, MapStage  # noqa: F401  (STREAM_DTYPE: the node's)
from photogram_ros.stages.map import MapParams as MapStageParams

TOPIC_CLOUD = 'map/dense_cloud'   # relative: a drone's namespace prefixes them
TOPIC_CLOUD_POSE = 'map/dense_cloud_pose'
TOPIC_DOWNSAMPLED = 'map/cloud_downsampled'
TOPIC_GEOREFERENCE = 'map/georeference'
TOPIC_IMAGE = 'keyframes/image'
TOPIC_IMAGE_FULL = 'keyframes/image/compressed'   # the full-resolution JPEG when keyframes/image is reduced
TOPIC_POSE = 'map/keyframe_pose'
TOPIC_INFO = 'camera/camera_info'
TOPIC_CAMERA_FINAL = 'map/camera_final'
TOPIC_CONTROL_POINTS = 'map/control_points'
TOPIC_ORTHO = 'map/ortho_tiles'
TOPIC_COVERAGE = 'map/coverage'
TOPIC_SPARSE = 'map/sparse_cloud'
TOPIC_KEYFRAME_FIX = 'keyframes/fix'


@dataclass
class MapParams(MapStageParams, ThreadCaps):
    """The node's parameters: the map stage's (stages/map.py: fusion, coverage, folder, origin, streams) and its
    process's thread pools (core/pace.py)."""


class _Publishers(MapOutputs):
    """The map's streams as messages on the node's topics."""

    def __init__(self, node: Node, p: MapParams):
        self.stream_pub = node.create_publisher(PointCloud2, TOPIC_DOWNSAMPLED, qos.best_effort(2))
        self.ortho_pub = self.coverage_pub = None
        if p.ortho:   # one message per tile: a batch must fit the history
            self.ortho_pub = node.create_publisher(CompressedImage, TOPIC_ORTHO, qos.best_effort(p.ortho_max_tiles))
        if p.coverage:
            from std_msgs.msg import String
            self.coverage_pub = node.create_publisher(String, TOPIC_COVERAGE, qos.latched())

    def stream(self, points, stamp_ns):
        self.stream_pub.publish(msgs.pointcloud2_msg(points, stamp_ns, 'map'))

    def ortho_tile(self, z, x, y, png, stamp_ns):
        self.ortho_pub.publish(msgs.ortho_tile_msg(z, x, y, png, stamp_ns))

    def coverage(self, doc):
        self.coverage_pub.publish(msgs.json_msg(doc))


class MapNode(Node):
    def __init__(self, overrides: dict | None = None, **node_kwargs):
        super().__init__('map_node', **node_kwargs)
        p = self.params = declare(self, MapParams, overrides)
        self.diag = Diagnostics(self)
        self.pubs = _Publishers(self, p)
        self.stage = MapStage(p, StageDiagnostics(self.diag), self.pubs, self.get_logger().info)
        for k, v in limit_threads(p.cv_threads, p.blas_threads).items():
            self.diag.set(k, v)
        group = MutuallyExclusiveCallbackGroup()   # the map is not thread-safe; graph.py spins multi-threaded
        # KEEP_ALL: the map is the sink that persists the flight; a burst of pair clouds while it is
        # fusing must queue, not overwrite clouds that were never fused. A cloud's placement is published
        # before it (subscribed first: taken first when both wait).
        self.create_subscription(PoseWithCovarianceStamped, TOPIC_CLOUD_POSE, self._on_cloud_pose, qos.keep_all(),
                                 callback_group=group)
        self.create_subscription(PointCloud2, TOPIC_CLOUD, self._on_cloud, qos.keep_all(), callback_group=group)
        self.create_subscription(NavSatFix, TOPIC_GEOREFERENCE, self._on_georeference, qos.latched(),
                                 callback_group=group)
        if p.save_keyframes:
            self.create_subscription(Image, TOPIC_IMAGE, self._on_image, qos.keep_all(), callback_group=group)
            self.create_subscription(CompressedImage, TOPIC_IMAGE_FULL, self._on_image_jpeg, qos.keep_all(),
                                     callback_group=group)
        if p.save_keyframes or p.coverage or self.stage.follows_poses:
            self.create_subscription(PoseWithCovarianceStamped, TOPIC_POSE, self._on_pose, qos.keep_all(),
                                     callback_group=group)
            self.create_subscription(CameraInfo, TOPIC_INFO, self._on_info, qos.sensor_data(5),
                                     callback_group=group)
            self.create_subscription(CameraInfo, TOPIC_CAMERA_FINAL, self._on_final_camera, qos.latched(),
                                     callback_group=group)
        if p.save_keyframes:
            from std_msgs.msg import String
            self.create_subscription(String, TOPIC_CONTROL_POINTS, self._on_control_points, qos.latched(),
                                     callback_group=group)
        if p.ortho:
            steady_timer(self, p.ortho_period_s, self._stream_ortho, group)
        if p.coverage:
            self.create_subscription(PointCloud2, TOPIC_SPARSE, self._on_sparse, qos.reliable(2),
                                     callback_group=group)
            self.create_subscription(NavSatFix, TOPIC_KEYFRAME_FIX, self._on_keyframe_fix, qos.keep_all(),
                                     callback_group=group)
            steady_timer(self, p.coverage_period_s, self._update_coverage, group)
        if self.stage.follows_poses:
            steady_timer(self, 0.5, self._replace_moved, group)
        # The flush holds the stage's lock only while it writes; its fsync runs outside it (stages/map.py flush),
        # and in a group of its own (flush_beside_fusion) the clouds are fused meanwhile.
        steady_timer(self, p.flush_interval_s, self.flush,
                     MutuallyExclusiveCallbackGroup() if p.flush_beside_fusion else group)
        steady_timer(self, p.stream_period_s, self._stream, group)
        steady_timer(self, 1.0, self._update_diag, group)
        self.get_logger().info(f'map in {p.map_dir}: {len(self.store.tile_keys())} tiles on disk, origin '
                               f'{self.store.origin}')

    # The stage's state, as the node's (tests, the graph and the probes read it).
    store = property(lambda self: self.stage.store)
    fusion = property(lambda self: self.stage.fusion)
    coverage = property(lambda self: self.stage.coverage)
    gsd = property(lambda self: self.stage.gsd)
    cell_m = property(lambda self: self.stage.cell_m)
    _camera = property(lambda self: self.stage.camera)
    posed_keyframes = property(lambda self: self.stage.posed_keyframes())

    # --- inputs ----------------------------------------------------------------------------------

    def _on_georeference(self, msg: NavSatFix) -> None:
        self.stage.set_origin(msg.latitude, msg.longitude, msg.altitude)

    def _on_cloud(self, msg: PointCloud2) -> None:
        self.stage.add_cloud(msg.header.frame_id, msgs.ns_from_time(msg.header.stamp),
                             lambda: msgs.points_from_pointcloud2(msg))

    def _on_cloud_pose(self, msg: PoseWithCovarianceStamped) -> None:
        self.stage.set_cloud_placement(msgs.ns_from_time(msg.header.stamp),
                                       lambda: msgs.T_from_pose_with_covariance(msg)[0], msgs.pose_is_provisional(msg))

    def _replace_moved(self) -> None:
        self.stage.replace_moved(self.params.replace_budget_s)

    def _on_image(self, msg: Image) -> None:
        self.stage.add_image(msgs.ns_from_time(msg.header.stamp), lambda: msgs.image_from_msg(msg))

    def _on_image_jpeg(self, msg: CompressedImage) -> None:
        self.stage.add_image_jpeg(msgs.ns_from_time(msg.header.stamp), bytes(msg.data))

    def _on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        provisional = msgs.pose_is_provisional(msg)
        self.stage.set_keyframe_pose(msgs.ns_from_time(msg.header.stamp),
                                     lambda: msgs.T_from_pose_with_covariance(msg)[0], provisional)
        if not (self.params.save_keyframes or self.params.coverage):
            return
        if provisional:
            # The roll about the first line is not known yet: not draped; the turn republishes it final.
            self.diag.count('poses_provisional_held')
            return
        self.stage.add_pose(msgs.ns_from_time(msg.header.stamp), lambda: msgs.T_from_pose_with_covariance(msg)[0])

    def _on_keyframe_fix(self, msg: NavSatFix) -> None:
        sigma_h_m, sigma_v_m = msgs.fix_sigmas_m(msg)
        self.stage.add_keyframe_fix(msgs.ns_from_time(msg.header.stamp), msg.latitude, msg.longitude, msg.altitude,
                                    msg.status.status, sigma_h_m, sigma_v_m)

    def _on_sparse(self, msg: PointCloud2) -> None:
        self.stage.add_sparse(lambda: msgs.points_from_pointcloud2(msg))

    def _on_info(self, msg: CameraInfo) -> None:
        self.stage.set_camera(lambda: msgs.camera_from_info(msg))

    def _on_final_camera(self, msg: CameraInfo) -> None:
        self.stage.set_final_camera(lambda: msgs.camera_from_info(msg))

    def _on_control_points(self, msg) -> None:
        self.stage.set_control_points(lambda: msgs.json_from_msg(msg))

    # --- outputs ---------------------------------------------------------------------------------

    def flush(self) -> None:
        self.stage.flush()

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _stream(self) -> None:
        self.stage.stream(self.pubs.stream_pub.get_subscription_count() > 0, self._now_ns())

    def _stream_ortho(self) -> None:
        self.stage.stream_ortho(self.pubs.ortho_pub.get_subscription_count() > 0, self._now_ns())

    def _update_coverage(self) -> None:
        self.stage.update_coverage()

    def publish_coverage(self) -> None:
        self.stage.publish_coverage()

    def _update_diag(self) -> None:
        self.stage.update_diag()

    def finish_coverage(self) -> None:
        """End of flight: every survey cell counts as passed; the last coverage goes out."""
        self.stage.finish_coverage()

    def close(self) -> None:
        """Flush everything to disk (shutdown, SIGINT, SIGTERM)."""
        self.stage.close()

    def destroy_node(self):
        self.close()
        return super().destroy_node()


def main(argv=None) -> int:
    """Console script `map_node`."""
    return run_node(MapNode, argv)


if __name__ == '__main__':
    sys.exit(main())
