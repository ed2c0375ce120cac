"""Ground station: receives the downsampled maps, poses and health of one or more drones.

Each drone runs under its own namespace (/drone1, /drone2, ...). Its clouds are in its own `map`
frame, anchored at the origin it publishes on <ns>/map/georeference, so the station converts every
cloud to ECEF and then to one common ENU frame (the first drone's origin) before merging. Merged cells
(latest value per 0.25 m cell) are saved as PLY in a projected CRS, with each drone's track as CSV.
"""

from __future__ import annotations

import json
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import NavSatFix, PointCloud2

from photogram_ros import msgs
from photogram_ros.core.geodesy import LocalFrame, utm_epsg
from photogram_ros.errors import PhotogramError
from photogram_ros.nodes.diagnostics import Diagnostics
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param

CLOUD_SUFFIX = '/map/cloud_downsampled'


@dataclass
class GroundStationParams:
    namespaces: str = param('', 'Comma-separated drone namespaces to follow, e.g. "/drone1,/drone2"; empty: '
                                'every namespace that publishes map/cloud_downsampled (rediscovered each second)')
    out_dir: str = param('ground_station', 'Folder for the merged cloud, tracks and status')
    cell_m: float = param(0.25, 'Merge cell size, m', min=0.01, max=100.0)
    save_period_s: float = param(10.0, 'How often the merged cloud is written, s', min=0.5, max=3600.0)
    crs: str = param('', 'Projected CRS of the saved cloud (EPSG code); empty: UTM zone of the first drone')

    def topic_namespaces(self) -> list[str]:
        return [s.strip() for s in self.namespaces.split(',') if s.strip()]


@dataclass
class Drone:
    ns: str
    origin: LocalFrame | None = None
    clouds: int = 0
    points: int = 0
    poses: list = field(default_factory=list)    # (stamp_ns, x, y, z) in the drone's map frame
    health: dict = field(default_factory=dict)   # node name -> (level, message)
    pending: list = field(default_factory=list)  # clouds received before the origin


class GroundStationNode(Node):
    def __init__(self, overrides: dict | None = None, **node_kwargs):
        super().__init__('ground_station', **node_kwargs)
        self.params = declare(self, GroundStationParams, overrides)
        self.diag = Diagnostics(self)
        self.drones: dict[str, Drone] = {}
        self.frame: LocalFrame | None = None          # common ENU of the merged map
        self._cells: dict = {}                        # cell key -> [x, y, z, rgb] in the common frame
        self._lock = threading.Lock()
        self._last_save = time.monotonic()
        self.out = Path(self.params.out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 50)
        for ns in self.params.topic_namespaces():
            self._follow(ns)
        self.create_timer(1.0, self._tick)

    # --- discovery -------------------------------------------------------------------------------

    def _follow(self, ns: str) -> None:
        ns = '/' + ns.strip('/') if ns.strip('/') else ''
        if ns in self.drones:
            return
        drone = self.drones[ns] = Drone(ns)
        best_effort = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(PointCloud2, f'{ns}{CLOUD_SUFFIX}', lambda m: self._on_cloud(drone, m), best_effort)
        self.create_subscription(NavSatFix, f'{ns}/map/georeference', lambda m: self._on_origin(drone, m), latched)
        self.create_subscription(PoseWithCovarianceStamped, f'{ns}/map/keyframe_pose',
                                 lambda m: self._on_pose(drone, m), QoSProfile(depth=50))
        self.get_logger().info(f'following drone {ns or "/"}')

    def _discover(self) -> None:
        for name, _types in self.get_topic_names_and_types():
            if name.endswith(CLOUD_SUFFIX):
                self._follow(name[: -len(CLOUD_SUFFIX)])

    # --- inputs ----------------------------------------------------------------------------------

    def _on_origin(self, drone: Drone, msg: NavSatFix) -> None:
        try:
            drone.origin = LocalFrame(msg.latitude, msg.longitude, msg.altitude)
        except PhotogramError as exc:
            self.diag.problem(f'{drone.ns}: bad georeference: {exc}')
            return
        if self.frame is None:
            self.frame = drone.origin
        for m in drone.pending:
            self._on_cloud(drone, m)
        drone.pending.clear()

    def _on_cloud(self, drone: Drone, msg: PointCloud2) -> None:
        if drone.origin is None or self.frame is None:
            drone.pending = drone.pending[-20:] + [msg]
            return
        try:
            pts = msgs.points_from_pointcloud2(msg)
            enu = np.column_stack([pts['x'], pts['y'], pts['z']]).astype(np.float64)
            common = self.frame.ecef_to_enu(drone.origin.enu_to_ecef(enu))
            rgb = pts['rgb'] if 'rgb' in pts.dtype.names else np.zeros(len(pts), np.uint32)
        except (PhotogramError, ValueError) as exc:
            self.diag.problem(f'{drone.ns}: cloud dropped: {exc}')
            return
        ij = np.floor(common[:, :2] / self.params.cell_m).astype(np.int64)
        keys = (ij[:, 0] << 32) ^ (ij[:, 1] & 0xFFFFFFFF)
        rows = np.column_stack([common, rgb.astype(np.float64)])
        with self._lock:   # latest value per cell wins: newer clouds carry the refined map
            self._cells.update(zip(keys.tolist(), rows.tolist()))
        drone.clouds += 1
        drone.points += len(pts)
        self.diag.count('clouds')

    def _on_pose(self, drone: Drone, msg: PoseWithCovarianceStamped) -> None:
        T, _ = msgs.T_from_pose_with_covariance(msg)
        drone.poses.append((msgs.ns_from_time(msg.header.stamp), *T[:3, 3]))

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for st in msg.status:
            m = re.match(r'^(/[^/]+)/', st.name)
            ns = m.group(1) if m and m.group(1) in self.drones else ''
            if ns in self.drones:
                self.drones[ns].health[st.name] = (int.from_bytes(st.level, 'little') if isinstance(st.level, bytes)
                                                   else int(st.level), st.message)

    # --- outputs ---------------------------------------------------------------------------------

    def _tick(self) -> None:
        if not self.params.topic_namespaces():
            self._discover()
        self.diag.set('drones', len(self.drones))
        self.diag.set('merged_cells', len(self._cells))
        if time.monotonic() - self._last_save >= self.params.save_period_s:
            self.save()

    def merged_cloud(self) -> np.ndarray:
        with self._lock:
            vals = np.array(list(self._cells.values()), dtype=np.float64).reshape(-1, 4)
        return vals

    def save(self) -> None:
        """Write the merged cloud (PLY), each drone's track (CSV) and a status file."""
        from photogram_ros.io.export import GeoCloud, enu_to_crs, write_ply
        self._last_save = time.monotonic()
        status = {'drones': {}, 'merged_cells': len(self._cells), 'frame': self.frame.to_dict() if self.frame else None}
        for ns, d in self.drones.items():
            status['drones'][ns or '/'] = {'clouds': d.clouds, 'points': d.points, 'keyframes': len(d.poses),
                                          'health': {k: list(v) for k, v in d.health.items()}}
            if d.poses:
                name = (ns.strip('/') or 'drone') + '_track.csv'
                rows = ['stamp_ns,x_m,y_m,z_m'] + [f'{s},{x:.3f},{y:.3f},{z:.3f}' for s, x, y, z in d.poses]
                (self.out / name).write_text('\n'.join(rows) + '\n')
        vals = self.merged_cloud()
        if self.frame is not None and len(vals):
            crs = self.params.crs or f'EPSG:{utm_epsg(self.frame.lat_deg, self.frame.lon_deg)}'
            e, n, h = enu_to_crs(self.frame, vals[:, :3], crs)
            rgb = vals[:, 3].astype(np.uint32)
            cloud = GeoCloud(e, n, h, np.column_stack([(rgb >> 16) & 255, (rgb >> 8) & 255, rgb & 255]).astype(np.uint8),
                             np.ones(len(vals), np.uint32), np.ones(len(vals), np.float32), crs, 'ellipsoidal')
            write_ply(cloud, self.out / 'merged_cloud.ply')
            status['crs'] = crs
        (self.out / 'status.json').write_text(json.dumps(status, indent=1))
