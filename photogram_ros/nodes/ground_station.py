"""Ground station: receives the downsampled maps, poses, health and survey quality of one or more drones.

Each drone runs under its own namespace (/drone1, /drone2, ...). Its clouds are in its own `map`
frame, anchored at the origin it publishes on <ns>/map/georeference, so the station converts every
cloud to ECEF and then to one common ENU frame (the first drone's origin) before merging. Merged cells
(latest value per 0.25 m cell) are saved as PLY in a projected CRS, with each drone's track as CSV.

Survey quality, per drone: the live ortho tiles (<ns>/map/ortho_tiles, XYZ PNGs), the coverage and its
gaps (<ns>/map/coverage, GeoJSON), the live accuracy (<ns>/map/control_points: check points, GCP
residuals, fix shares, GNSS bias) and a go / no-go verdict against the limits of the parameters
(core/survey_quality.py). `status()` has every figure (status.json); the gaps are saved as
<drone>_gaps.geojson and a QGroundControl re-fly plan <drone>_refly.plan; with `web` set the page of
web/server.py shows it all on a map.
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
from sensor_msgs.msg import CompressedImage, NavSatFix, PointCloud2
from std_msgs.msg import String

from photogram_ros import msgs
from photogram_ros.core.geodesy import LocalFrame, utm_epsg
from photogram_ros.core.survey_quality import QualityLimits, go_no_go
from photogram_ros.errors import PhotogramError
from photogram_ros.nodes.diagnostics import Diagnostics
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param

CLOUD_SUFFIX = '/map/cloud_downsampled'


@dataclass
class GroundStationParams(QualityLimits):
    """The station's parameters and the go / no-go limits (core/survey_quality.py QualityLimits)."""
    namespaces: str = param('', 'Comma-separated drone namespaces to follow, e.g. "/drone1,/drone2"; empty: '
                                'every namespace that publishes map/cloud_downsampled (rediscovered each second)')
    out_dir: str = param('ground_station', 'Folder for the merged cloud, tracks and status')
    cell_m: float = param(0.25, 'Merge cell size, m', min=0.01, max=100.0)
    save_period_s: float = param(10.0, 'How often the merged cloud is written, s', min=0.5, max=3600.0)
    crs: str = param('', 'Projected CRS of the saved cloud (EPSG code); empty: UTM zone of the first drone')
    web: str = param('', 'Serve the map page on HOST:PORT (e.g. 127.0.0.1:8080, :8080 for every interface); '
                         '"" = no page')
    refly_side_overlap: float = param(0.6, 'Side overlap of the re-fly plan\'s lines', min=0.0, max=0.95)
    refly_forward_overlap: float = param(0.8, 'Forward overlap of the re-fly plan\'s camera triggers',
                                         min=0.0, max=0.95)

    def topic_namespaces(self) -> list[str]:
        return [s.strip() for s in self.namespaces.split(',') if s.strip()]


def drone_key(ns: str) -> str:
    """A namespace as it appears in the page's URLs: '/drone1' -> 'drone1', '' -> 'default'."""
    return ns.strip('/').replace('/', '_') or 'default'


@dataclass
class Drone:
    ns: str
    origin: LocalFrame | None = None
    clouds: int = 0
    points: int = 0
    poses: dict = field(default_factory=dict)    # stamp_ns -> (x, y, z) in the drone's map frame (latest)
    health: dict = field(default_factory=dict)   # node name -> (level, message)
    pending: list = field(default_factory=list)  # clouds received before the origin
    tiles: dict = field(default_factory=dict)    # (z, x, y) -> PNG bytes of the live ortho
    tiles_unsaved: set = field(default_factory=set)
    tile_bytes: int = 0
    coverage: dict | None = None                 # GeoJSON of <ns>/map/coverage
    quality: dict | None = None                  # JSON of <ns>/map/control_points


class GroundStationNode(Node):
    def __init__(self, overrides: dict | None = None, **node_kwargs):
        super().__init__('ground_station', **node_kwargs)
        self.params = declare(self, GroundStationParams, overrides)
        self.diag = Diagnostics(self)
        self.drones: dict[str, Drone] = {}
        self.frame: LocalFrame | None = None          # common ENU of the merged map
        self._cells: dict = {}                        # cell key -> [x, y, z, rgb] in the common frame
        self._lock = threading.RLock()                # ROS callbacks and the web server's threads
        self._last_save = time.monotonic()
        self.out = Path(self.params.out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 50)
        for ns in self.params.topic_namespaces():
            self._follow(ns)
        self.create_timer(1.0, self._tick)
        self.web = None
        if self.params.web:
            from photogram_ros.web.server import WebServer, parse_host_port
            self.web = WebServer(self, *parse_host_port(self.params.web)).start()
            self.get_logger().info(f'ground-station page on {self.web.url}')

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
        self.create_subscription(CompressedImage, f'{ns}/map/ortho_tiles', lambda m: self._on_tile(drone, m),
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
        self.create_subscription(String, f'{ns}/map/coverage', lambda m: self._on_document(drone, m, 'coverage'),
                                 latched)
        self.create_subscription(String, f'{ns}/map/control_points',
                                 lambda m: self._on_document(drone, m, 'quality'), latched)
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
        try:
            T, _ = msgs.T_from_pose_with_covariance(msg)
        except PhotogramError as exc:
            self.diag.problem(f'{drone.ns}: pose dropped: {exc}')
            return
        with self._lock:
            drone.poses[msgs.ns_from_time(msg.header.stamp)] = tuple(float(v) for v in T[:3, 3])

    def _on_tile(self, drone: Drone, msg: CompressedImage) -> None:
        try:
            z, x, y, png = msgs.ortho_tile_from_msg(msg)
        except PhotogramError as exc:
            self.diag.problem(f'{drone.ns}: ortho tile dropped: {exc}')
            return
        with self._lock:
            drone.tiles[(z, x, y)] = png
            drone.tiles_unsaved.add((z, x, y))
            drone.tile_bytes += len(png)
        self.diag.count('ortho_tiles')

    def _on_document(self, drone: Drone, msg: String, field_name: str) -> None:
        """A JSON document of the drone (map/coverage -> drone.coverage, map/control_points -> drone.quality)."""
        try:
            doc = msgs.json_from_msg(msg)
        except PhotogramError as exc:
            self.diag.problem(f'{drone.ns}: {field_name} dropped: {exc}')
            return
        with self._lock:
            setattr(drone, field_name, doc)

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
            status['drones'][ns or '/'] = self.drone_status(d)
            if d.poses:
                name = (ns.strip('/') or 'drone') + '_track.csv'
                rows = ['stamp_ns,x_m,y_m,z_m'] + [f'{s},{x:.3f},{y:.3f},{z:.3f}'
                                                   for s, (x, y, z) in sorted(d.poses.items())]
                (self.out / name).write_text('\n'.join(rows) + '\n')
            self._save_quality(d)
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

    # --- survey quality (status.json, the web page) ----------------------------------------------

    def _save_quality(self, d: Drone) -> None:
        """The drone's new ortho tiles (tiles/<drone>/Z/X/Y.png), gaps (GeoJSON) and re-fly plan."""
        from photogram_ros.io.mission import write_json
        key = drone_key(d.ns)
        with self._lock:
            todo = {t: d.tiles[t] for t in d.tiles_unsaved}
            d.tiles_unsaved.clear()
            cov = d.coverage
        for (z, x, y), png in todo.items():
            p = self.out / 'tiles' / key / str(z) / str(x) / f'{y}.png'
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(png)
        if cov is not None:
            write_json(self.out / f'{key}_gaps.geojson', {
                'type': 'FeatureCollection', 'properties': cov.get('properties', {}),
                'features': [f for f in cov['features'] if f['properties'].get('role') == 'gap']})
            plan = self.refly_plan(key)
            if plan is not None:
                write_json(self.out / f'{key}_refly.plan', plan)

    def _drone(self, key: str) -> Drone | None:
        return next((d for ns, d in self.drones.items() if drone_key(ns) == key), None)

    def drone_status(self, d: Drone) -> dict:
        """Every figure of one drone: counts, health, ortho, coverage and gaps, accuracy, go / no-go."""
        with self._lock:
            out = {'key': drone_key(d.ns), 'clouds': d.clouds, 'points': d.points, 'keyframes': len(d.poses),
                   'health': {k: list(v) for k, v in d.health.items()},
                   'ortho': {'tiles': len(d.tiles), 'bytes_received': d.tile_bytes,
                             'zoom': next(iter(d.tiles))[0] if d.tiles else None}}
            cov, q = d.coverage, d.quality
        figures = {}
        if cov is not None:
            props = dict(cov.get('properties', {}))
            props['gap_list'] = [{k: f['properties'][k] for k in ('kind', 'area_m2', 'min_views', 'centroid')}
                                 for f in cov['features'] if f['properties'].get('role') == 'gap']
            out['coverage'] = props
            figures.update(coverage_share=props.get('coverage_share'), largest_gap_m2=props.get('largest_gap_m2'))
        if q is not None:
            cr = q.get('check_rmse') or {}
            out['accuracy'] = {'check_rmse_h_m': cr.get('horizontal_m'), 'check_rmse_v_m': cr.get('vertical_m'),
                               'check_count': cr.get('count', 0), 'gcp_rmse': q.get('gcp_rmse'),
                               'fix_share': q.get('fix_share'), 'gnss_bias_enu_m': q.get('gnss_bias_enu_m'),
                               'check_points': q.get('check_points', []), 'gcps': q.get('gcps', []),
                               'control': _control_status(q.get('control'))}
            figures.update(check_rmse=cr if cr.get('count') else None, fix_share=q.get('fix_share'))
        out['go_no_go'] = go_no_go(figures, self.params)
        return out

    def status(self) -> dict:
        """status.json of the web page: every drone's figures (keyed by its URL name)."""
        with self._lock:
            drones = list(self.drones.values())
        return {'drones': {drone_key(d.ns): {'ns': d.ns or '/', **self.drone_status(d)} for d in drones},
                'limits': {k: getattr(self.params, k) for k in QualityLimits.__dataclass_fields__}}

    def tile(self, key: str, z: int, x: int, y: int) -> bytes | None:
        d = self._drone(key)
        with self._lock:
            return d.tiles.get((z, x, y)) if d is not None else None

    def geojson(self, key: str, kind: str) -> dict | None:
        """'coverage' (gaps, survey area), 'track' (keyframe centres) or 'targets' (check points, GCPs)."""
        d = self._drone(key)
        if d is None:
            return None
        with self._lock:
            if kind == 'coverage':
                return d.coverage or {'type': 'FeatureCollection', 'features': []}
            origin, poses, q = d.origin, sorted(d.poses.items()), d.quality
        feats = []
        if kind == 'track' and origin is not None and poses:
            lat, lon, _ = origin.enu_to_geodetic(np.array([p for _, p in poses]).reshape(-1, 3))
            feats.append({'type': 'Feature', 'properties': {'keyframes': len(poses)}, 'geometry': {
                'type': 'LineString', 'coordinates': [[float(a), float(b)] for a, b in
                                                      zip(np.atleast_1d(lon), np.atleast_1d(lat))]}})
        if kind == 'targets' and q is not None:
            for role, rows in (('check', q.get('check_points', [])), ('gcp', q.get('gcps', []))):
                for r in rows:
                    e = r['residual_enu_m']
                    feats.append({'type': 'Feature', 'geometry': {'type': 'Point',
                                                                  'coordinates': [r['lon_deg'], r['lat_deg']]},
                                  'properties': {'name': r['name'], 'role': role, 'residual_enu_m': e,
                                                 'residual_h_m': float(np.hypot(e[0], e[1])),
                                                 # a GCP used horizontally only: its height is not the survey's
                                                 'residual_v_m': float(e[2]) if r.get('use', 'full') in
                                                 ('full', 'check') else None,
                                                 'use': r.get('use'), 'images': r['images']}})
        return {'type': 'FeatureCollection', 'features': feats}

    def refly_plan(self, key: str) -> dict | None:
        """A QGroundControl plan over the drone's coverage gaps (None without gaps or flight figures)."""
        from photogram_ros.io.mission import gap_rings, refly_plan
        d = self._drone(key)
        if d is None:
            return None
        with self._lock:
            cov, origin = d.coverage, d.origin
        if cov is None or origin is None:
            return None
        props = cov.get('properties', {})
        rings = [r for r, f in zip(gap_rings(cov), [f for f in cov['features'] if f['properties'].get('role') == 'gap'])
                 if f['properties'].get('kind') == 'coverage']
        need = ('height_above_ground_m', 'footprint_width_m', 'footprint_length_m')
        if not rings or not all(props.get(k) for k in need):
            return None
        return refly_plan(rings, props['height_above_ground_m'], props['footprint_width_m'],
                          props['footprint_length_m'], (origin.lat_deg, origin.lon_deg),
                          self.params.refly_side_overlap, self.params.refly_forward_overlap)

    def destroy_node(self):
        if self.web is not None:
            self.web.stop()
        return super().destroy_node()


CONTROL_COUNTS = ('gcps', 'gcps_held', 'gcps_full', 'gcps_horizontal_only', 'gcps_rejected', 'gcps_not_seen',
                  'control_detections_rejected')


def _control_status(control: dict | None) -> dict | None:
    """What the bundle node made of the control file so far (core/control_live.py): counts and faults."""
    if not control:
        return None
    return {**{k: control.get(k) for k in CONTROL_COUNTS}, 'faults': list(control.get('faults', []))}
