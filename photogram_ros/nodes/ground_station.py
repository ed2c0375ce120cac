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
web/server.py shows it all on a map, pushed over a WebSocket as it changes, over an offline base map
(`basemap`: an XYZ folder or an MBTiles file, web/basemap.py).

Trust: `drones` is the allow-list of namespaces (empty: every namespace that publishes
map/cloud_downsampled, said as a WARN at the start). Of a followed drone, a topic's message counts only
while every publisher of that topic is the node of that drone's namespace that publishes it (map_node,
bundle_node); otherwise the message is not counted, the figure keeps its last trusted value and the page
lists the unknown publisher. ROS 2 does not say which publisher sent a message, so this is a check of
the graph, not an authentication: without SROS2 (see `security_status()`) any node can take a
drone's name. Other namespaces that publish map topics are listed as unknown drones, never counted.
/diagnostics counts only while its publishers are such nodes (and the station): the block's
georeference state (bundle_node's `georeferenced`) comes from there, unless map/control_points carries
it ('georeference': 'final' / 'provisional' / 'none').
"""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, NavSatFix, PointCloud2
from std_msgs.msg import String

from photogram_ros import msgs
from photogram_ros.core.geodesy import LocalFrame, utm_epsg
from photogram_ros.core.survey_quality import (BLOCK_ADJUSTED, BLOCK_CHECK_NAME, BLOCK_CHECK_STATUSES, BLOCK_IN_FLIGHT, GEOREF_FINAL,
                                               GEOREF_NONE, GEOREF_PROVISIONAL, GEOREF_UNKNOWN, GO, WAIT, QualityLimits,
                                               go_no_go)
from photogram_ros.errors import PhotogramError
from photogram_ros.nodes import qos
from photogram_ros.nodes.diagnostics import Diagnostics
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param

CLOUD_SUFFIX = '/map/cloud_downsampled'
# The drone topics the station takes -> the node (in the drone's namespace) that publishes them.
# The drone's live position (gps/fix) comes from its MAVLink node, its camera node (a photo folder's EXIF) or an
# adapter of MAVROS / PX4 uXRCE-DDS (nodes/px4_adapter.py); a replay's player republishes the recorded one.
FIX_SUFFIX = '/gps/fix'
FIX_PUBLISHERS = ('mavlink_node', 'camera_node', 'px4_adapter', 'player')
PUBLISHER_OF = {CLOUD_SUFFIX: 'map_node', '/map/ortho_tiles': 'map_node', '/map/coverage': 'map_node',
                '/map/georeference': 'bundle_node', '/map/keyframe_pose': 'bundle_node',
                '/map/control_points': 'bundle_node', FIX_SUFFIX: FIX_PUBLISHERS}
# Nodes of a drone's namespace whose /diagnostics the station takes (graph.py's nodes and a replay's player).
DRONE_NODES = frozenset(n for v in PUBLISHER_OF.values() for n in ((v,) if isinstance(v, str) else v)) | {
    'tracker_node', 'stereo_node', 'mavlink_node', 'camera_node', 'player'}
LIVE_TRACK_STEP_M = 1.0       # the live track keeps a fix this far from the last one kept
LIVE_TRACK_MAX = 5000         # ... and at most this many (every other one dropped beyond)


def publisher_names(suffix: str) -> tuple:
    """The node names that may publish a drone's topic (PUBLISHER_OF)."""
    v = PUBLISHER_OF[suffix]
    return (v,) if isinstance(v, str) else tuple(v)
MAX_TILE_ZOOM = 24          # an ortho tile's zoom at most (about 1 cm pixels)
GEOREF_OF_DIAG = {'True': GEOREF_FINAL, 'provisional': GEOREF_PROVISIONAL, 'False': GEOREF_NONE}


@dataclass
class GroundStationParams(QualityLimits):
    """The station's parameters and the go / no-go limits (core/survey_quality.py QualityLimits)."""
    drones: str = param('', 'Allow-list: comma-separated drone namespaces, e.g. "/drone1,/drone2" ("/" for the '
                            'root namespace); others are shown as unknown, never counted. Empty: every namespace '
                            'that publishes map/cloud_downsampled (rediscovered each second)')
    out_dir: str = param('ground_station', 'Folder for the merged cloud, tracks and status')
    cell_m: float = param(0.25, 'Merge cell size, m', min=0.01, max=100.0)
    save_period_s: float = param(10.0, 'How often the merged cloud is written, s', min=0.5, max=3600.0)
    crs: str = param('', 'Projected CRS of the saved cloud (EPSG code); empty: UTM zone of the first drone')
    web: str = param('', 'Serve the map page on HOST:PORT (127.0.0.1:8080, or :8080, this machine only; '
                         '0.0.0.0:8080 every interface, with the token); "" = no page')
    web_token: str = param('', 'Token other machines must give (?token= once, then a cookie); empty: generated and '
                               'printed when the page is served beyond this machine')
    web_idle_timeout_s: float = param(20.0, 'The page\'s server closes a connection idle for this long, s',
                                      min=0.5, max=3600.0)
    web_request_timeout_s: float = param(30.0, 'Longest a request of the page may take, s', min=0.5, max=3600.0)
    web_max_connections: int = param(64, 'Open connections of the page\'s server at most', min=1, max=100000)
    basemap: str = param('', 'Offline base map under the ortho: an XYZ tile folder (Z/X/Y.png) or an .mbtiles '
                             'file; empty: none')
    refly_side_overlap: float = param(0.6, 'Side overlap of the re-fly plan\'s lines', min=0.0, max=0.95)
    refly_forward_overlap: float = param(0.8, 'Forward overlap of the re-fly plan\'s camera triggers',
                                         min=0.0, max=0.95)

    def allowed(self) -> list[str]:
        """The allow-list as namespaces: '' for the root namespace, else '/name'."""
        return [norm_ns(s) for s in self.drones.split(',') if s.strip()]


def norm_ns(ns: str) -> str:
    """'drone1', '/drone1/' -> '/drone1'; '/' or '' -> '' (the root namespace)."""
    ns = ns.strip().strip('/')
    return '/' + ns if ns else ''


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
    georef_diag: str = GEOREF_UNKNOWN            # bundle_node's `georeferenced` on /diagnostics
    tile_log: list = field(default_factory=list)  # (z, x, y) in the order they came (the page's push)
    versions: dict = field(default_factory=lambda: {'coverage': 0, 'track': 0, 'targets': 0, 'live': 0})
    position: dict | None = None                 # the latest fix of <ns>/gps/fix (lat_deg, lon_deg, h_m, ...)
    live_track: list = field(default_factory=list)   # [(lon_deg, lat_deg)] of the fixes, LIVE_TRACK_STEP_M apart
    updated_unix_s: float | None = None          # when a counted message last came
    not_counted: dict = field(default_factory=dict)   # topic -> messages not counted (unknown publishers)
    unknown_publishers: dict = field(default_factory=dict)   # topic -> ['/ns/node', ...] seen on it


class GroundStationNode(Node):
    def __init__(self, overrides: dict | None = None, **node_kwargs):
        super().__init__('ground_station', **node_kwargs)
        self.params = declare(self, GroundStationParams, overrides)
        self.diag = Diagnostics(self)
        self.drones: dict[str, Drone] = {}
        self.unknown: dict[str, dict] = {}            # namespace not on the allow-list -> {topic: [publishers]}
        self.diag_unknown: list[str] = []             # unknown publishers of /diagnostics (health not counted)
        self.frame: LocalFrame | None = None          # common ENU of the merged map
        self._cells: dict = {}                        # cell key -> [x, y, z, rgb] in the common frame
        self._lock = threading.RLock()                # ROS callbacks and the web server's thread
        self._held: dict = {}                         # (drone ns, topic suffix) -> (message, publisher gids)
        self._warned: set = set()
        self._last_save = time.monotonic()
        self.out = Path(self.params.out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.security = security_status()
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 50)
        for ns in self.params.allowed():
            self._follow(ns)
        if not self.params.allowed():
            self.get_logger().warning('no allow-list (drones): every namespace that publishes map/cloud_downsampled '
                                      'is followed as a drone; name them with --drones /drone1,/drone2')
        (self.get_logger().info if self.security['enabled'] else self.get_logger().warning)(
            'ROS 2 security: ' + self.security['summary'])
        self.create_timer(1.0, self._tick)
        self.web = None
        if self.params.web:
            from photogram_ros.web.server import WebLimits, WebServer, parse_host_port
            basemap = None
            if self.params.basemap:
                from photogram_ros.web.basemap import open_basemap
                basemap = open_basemap(self.params.basemap)
            limits = WebLimits(idle_timeout_s=self.params.web_idle_timeout_s,
                               request_timeout_s=self.params.web_request_timeout_s,
                               max_connections=self.params.web_max_connections)
            self.web = WebServer(self, *parse_host_port(self.params.web), token=self.params.web_token or None,
                                 limits=limits, basemap=basemap).start()
            self.get_logger().info(f'ground-station page on {self.web.url}')

    # --- discovery and trust ---------------------------------------------------------------------

    def _follow(self, ns: str) -> None:
        ns = norm_ns(ns)
        if ns in self.drones:
            return
        drone = self.drones[ns] = Drone(ns)
        # Over the radio link: each drone's topics overridable from the parameters (nodes/qos.py).
        def sub(msg_type, suffix, handler, profile):
            qos.subscription(self, msg_type, f'{ns}{suffix}', lambda m: self._take(drone, suffix, m, handler), profile)

        sub(PointCloud2, CLOUD_SUFFIX, self._on_cloud, qos.best_effort(5))
        sub(NavSatFix, '/map/georeference', self._on_origin, qos.latched())
        sub(PoseWithCovarianceStamped, '/map/keyframe_pose', self._on_pose, qos.reliable(50))
        sub(CompressedImage, '/map/ortho_tiles', self._on_tile, qos.best_effort(100))
        sub(String, '/map/coverage', lambda d, m: self._on_document(d, m, 'coverage'), qos.latched())
        sub(String, '/map/control_points', lambda d, m: self._on_document(d, m, 'quality'), qos.latched())
        sub(NavSatFix, FIX_SUFFIX, self._on_fix, qos.best_effort(10))
        self.get_logger().info(f'following drone {ns or "/"}')

    def _publishers_of(self, topic: str) -> list:
        try:
            return self.get_publishers_info_by_topic(topic)
        except Exception:   # noqa: BLE001 (a graph query during shutdown)
            return []

    def _foreign(self, drone_ns: str, suffix: str) -> tuple[list[str], frozenset]:
        """Publishers of the drone's topic other than the drone's own node for it, and every publisher's gid."""
        want_ns, wanted = drone_ns or '/', publisher_names(suffix)
        infos = self._publishers_of(f'{drone_ns}{suffix}')
        bad = [f'{i.node_namespace.rstrip("/")}/{i.node_name}' for i in infos
               if i.node_namespace != want_ns or i.node_name not in wanted]
        own = [i.node_name for i in infos if i.node_namespace == want_ns and i.node_name in wanted]
        for name in sorted(set(own)):
            if own.count(name) > 1:   # two nodes of the drone's node name: one is not the drone's
                bad.append(f'{want_ns.rstrip("/")}/{name} ({own.count(name)} nodes of that name)')
        return bad, frozenset(bytes(i.endpoint_gid) for i in infos)

    def _take(self, drone: Drone, suffix: str, msg, handler) -> None:
        """A message of a followed drone: counted when every publisher of its topic is the drone's own node."""
        bad, gids = self._foreign(drone.ns, suffix)
        if bad:
            with self._lock:
                drone.not_counted[suffix] = drone.not_counted.get(suffix, 0) + 1
                drone.unknown_publishers[suffix] = sorted(set(bad))
                if all('_UNKNOWN_' in b for b in bad):
                    # A publisher whose node name discovery has not brought yet: decided on the next tick.
                    self._held[(drone.ns, suffix)] = (msg, gids, handler)
            key = (drone.ns, suffix, tuple(sorted(set(bad))))
            if key not in self._warned:
                self._warned.add(key)
                self.diag.problem(f'{drone.ns}{suffix}: published also by {", ".join(sorted(set(bad)))} '
                                  f'(not {" or ".join(publisher_names(suffix))} of {drone.ns or "/"}): its messages '
                                  'are not counted')
            self._notify()
            return
        with self._lock:
            drone.unknown_publishers.pop(suffix, None)
            drone.updated_unix_s = time.time()
        handler(drone, msg)
        self._notify()

    def _retry_held(self) -> None:
        """Messages held while a publisher's node name was unknown: counted if the same publishers are now
        all the drone's own node; dropped if another node is among them."""
        for (ns, suffix), (msg, gids, handler) in list(self._held.items()):
            bad, now = self._foreign(ns, suffix)
            if any('_UNKNOWN_' in b for b in bad) and now == gids:
                continue
            del self._held[(ns, suffix)]
            if not bad and now == gids and ns in self.drones:
                drone = self.drones[ns]
                with self._lock:
                    drone.not_counted[suffix] -= 1
                    drone.unknown_publishers.pop(suffix, None)
                    drone.updated_unix_s = time.time()
                handler(drone, msg)
                self._notify()

    def _discover(self) -> None:
        """Follow new drones (no allow-list); list namespaces outside the allow-list that publish map topics."""
        allowed = self.params.allowed()
        unknown: dict[str, dict] = {}
        for name, _types in self.get_topic_names_and_types():
            suffix = next((s for s in PUBLISHER_OF if name.endswith(s)), None)
            if suffix is None:
                continue
            ns = norm_ns(name[: -len(suffix)])
            if not allowed and suffix == CLOUD_SUFFIX:
                self._follow(ns)
            if ns not in self.drones:
                pubs = [f'{i.node_namespace.rstrip("/")}/{i.node_name}' for i in self._publishers_of(name)]
                if pubs:
                    unknown.setdefault(ns or '/', {})[name] = pubs
        with self._lock:
            self.unknown = unknown

    def _notify(self) -> None:
        if self.web is not None:
            self.web.notify()

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
        drone.versions['track'] += 1
        drone.versions['targets'] += 1

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
            drone.versions['track'] += 1

    def _on_fix(self, drone: Drone, msg: NavSatFix) -> None:
        """The drone's live position: the latest fix, and its track (a fix kept LIVE_TRACK_STEP_M from the last)."""
        if msg.status.status < 0 or not (np.isfinite(msg.latitude) and np.isfinite(msg.longitude)
                                         and -90 <= msg.latitude <= 90 and -180 <= msg.longitude <= 180):
            return      # no fix
        lat, lon = float(msg.latitude), float(msg.longitude)
        with self._lock:
            drone.position = {'lat_deg': lat, 'lon_deg': lon, 'h_m': float(msg.altitude),
                              'status': int(msg.status.status), 'stamp_ns': msgs.ns_from_time(msg.header.stamp),
                              'received_unix_s': time.time()}
            last = drone.live_track[-1] if drone.live_track else None
            if last is None or np.hypot((lon - last[0]) * 111_320.0 * np.cos(np.radians(lat)),
                                        (lat - last[1]) * 110_540.0) >= LIVE_TRACK_STEP_M:
                drone.live_track.append((lon, lat))
                if len(drone.live_track) > LIVE_TRACK_MAX:
                    drone.live_track = drone.live_track[::2]
            drone.versions['live'] += 1

    def _on_tile(self, drone: Drone, msg: CompressedImage) -> None:
        try:
            z, x, y, png = msgs.ortho_tile_from_msg(msg)
            if not (0 <= z <= MAX_TILE_ZOOM and x < 2 ** z and y < 2 ** z):
                raise PhotogramError(f'tile {z}/{x}/{y} is no XYZ tile (zoom 0-{MAX_TILE_ZOOM}, x, y < 2^zoom)')
        except PhotogramError as exc:
            self.diag.problem(f'{drone.ns}: ortho tile dropped: {exc}')
            return
        with self._lock:
            drone.tiles[(z, x, y)] = png
            drone.tiles_unsaved.add((z, x, y))
            drone.tile_bytes += len(png)
            drone.tile_log.append((z, x, y))
        self.diag.count('ortho_tiles')

    def _on_document(self, drone: Drone, msg: String, field_name: str) -> None:
        """A JSON document of the drone (map/coverage -> drone.coverage, map/control_points -> drone.quality)."""
        try:
            doc = msgs.json_from_msg(msg)
            if not isinstance(doc, dict):
                raise PhotogramError(f'a JSON object expected, got {type(doc).__name__}')
        except PhotogramError as exc:
            self.diag.problem(f'{drone.ns}: {field_name} dropped: {exc}')
            return
        with self._lock:
            setattr(drone, field_name, doc)
            drone.versions['coverage' if field_name == 'coverage' else 'targets'] += 1

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        """Health of the followed drones' nodes and bundle_node's georeference state, counted only while every
        publisher of /diagnostics is a drone node of a followed namespace or this station."""
        me = (self.get_namespace(), self.get_name())
        followed = {ns or '/' for ns in self.drones}
        bad = sorted({f'{i.node_namespace.rstrip("/")}/{i.node_name}' for i in self._publishers_of('/diagnostics')
                      if (i.node_namespace, i.node_name) != me
                      and not (i.node_namespace in followed and i.node_name in DRONE_NODES)})
        with self._lock:
            self.diag_unknown = bad
        if bad:
            return
        for st in msg.status:
            ns, _, node = st.name.rpartition('/')
            drone = self.drones.get(ns)
            if drone is None or node not in DRONE_NODES:   # this station's own status, or no drone node
                continue
            level = int.from_bytes(st.level, 'little') if isinstance(st.level, bytes) else int(st.level)
            with self._lock:
                drone.health[st.name] = (level, st.message)
                if node == PUBLISHER_OF['/map/control_points']:
                    geo = next((kv.value for kv in st.values if kv.key == 'georeferenced'), None)
                    if geo in GEOREF_OF_DIAG and GEOREF_OF_DIAG[geo] != drone.georef_diag:
                        drone.georef_diag = GEOREF_OF_DIAG[geo]
                        drone.versions['targets'] += 1
                        self._notify()

    # --- outputs ---------------------------------------------------------------------------------

    def _tick(self) -> None:
        self._discover()
        self._retry_held()
        self.diag.set('drones', len(self.drones))
        self.diag.set('merged_cells', len(self._cells))
        self.diag.set('unknown_drones', ','.join(sorted(self.unknown)))
        for d in list(self.drones.values()):
            self._diagnose(d, self.drone_status(d))
        if self.web is not None:
            self.diag.set('web_connections', self.web.connections)
            self.diag.set('web_refused_requests', self.web.refused_requests)
        if time.monotonic() - self._last_save >= self.params.save_period_s:
            self.save()

    def _diagnose(self, d: Drone, st: dict) -> None:
        """The drone's verdict and figures on /diagnostics: the same numbers as status.json and the page."""
        key = st['key']
        g = st['go_no_go']
        self.diag.set(f'{key}_verdict', g['verdict'])
        self.diag.set(f'{key}_reasons', '; '.join(g['reasons']))
        for c in g['checks']:
            name = c['name'].split(' (')[0].replace(',', '').replace(' ', '_')
            self.diag.set(f'{key}_{name}', 'not measured' if c['value'] is None else repr(c['value']))
        for name, value in diagnostic_figures(st).items():
            self.diag.set(f'{key}_{name}', diagnostic_text(value))

    def merged_cloud(self) -> np.ndarray:
        with self._lock:
            vals = np.array(list(self._cells.values()), dtype=np.float64).reshape(-1, 4)
        return vals

    def save(self) -> None:
        """Write the merged cloud (PLY), each drone's track (CSV) and a status file."""
        from photogram_ros.io.export import GeoCloud, enu_to_crs, write_ply
        self._last_save = time.monotonic()
        status = {'drones': {}, 'merged_cells': len(self._cells), 'frame': self.frame.to_dict() if self.frame else None,
                  'generated_unix_s': time.time(), 'unknown_drones': self.unknown,
                  'diagnostics_unknown_publishers': self.diag_unknown, 'security': self.security}
        for ns, d in list(self.drones.items()):
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
        from photogram_ros.web.server import finite
        tmp = self.out / 'status.json.tmp'
        tmp.write_text(json.dumps(finite(status), indent=1))
        os.replace(tmp, self.out / 'status.json')

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
        """Every figure of one drone: counts, health, ortho, coverage and gaps, accuracy, go / no-go, and which
        publishers were not counted. The page, status.json and /diagnostics all show these numbers."""
        with self._lock:
            out = {'key': drone_key(d.ns), 'clouds': d.clouds, 'points': d.points, 'keyframes': len(d.poses),
                   'health': {k: list(v) for k, v in d.health.items()},
                   'ortho': {'tiles': len(d.tiles), 'bytes_received': d.tile_bytes,
                             'zoom': next(iter(d.tiles))[0] if d.tiles else None},
                   'updated_unix_s': d.updated_unix_s, 'versions': dict(d.versions),
                   'not_counted': dict(d.not_counted), 'unknown_publishers': dict(d.unknown_publishers)}
            cov, q, geo_diag = d.coverage, d.quality, d.georef_diag
            if d.position is not None:
                out['position'] = {**d.position, 'age_s': round(time.time() - d.position['received_unix_s'], 1),
                                   'track_points': len(d.live_track)}
        figures = {}
        if cov is not None:
            props = dict(cov.get('properties', {}))
            props['gap_list'] = [{k: f['properties'].get(k) for k in ('kind', 'area_m2', 'min_views', 'centroid')}
                                 for f in cov.get('features', []) if f.get('properties', {}).get('role') == 'gap']
            out['coverage'] = props
            props['low_forward_overlap'] = low_forward_overlap(props)
            figures.update(coverage_share=_number(props.get('coverage_share')),
                           gaps=[{'kind': g['kind'], 'area_m2': _number(g['area_m2']), 'min_views': g['min_views']}
                                 for g in props['gap_list']],
                           low_forward_overlap=props['low_forward_overlap'])
        geo = q.get('georeference') if q is not None else None
        geo = geo if geo in (GEOREF_FINAL, GEOREF_PROVISIONAL, GEOREF_NONE) else geo_diag
        if q is not None:
            cr = q.get('check_rmse') or {}
            out['accuracy'] = {'check_rmse_h_m': _number(cr.get('horizontal_m')),
                               'check_rmse_v_m': _number(cr.get('vertical_m')),
                               'check_count': int(_number(cr.get('count')) or 0), 'gcp_rmse': q.get('gcp_rmse'),
                               'fix_share': q.get('fix_share'), 'gnss_bias_enu_m': q.get('gnss_bias_enu_m'),
                               'check_points': q.get('check_points', []), 'gcps': q.get('gcps', []),
                               'control': _control_status(q.get('control')), 'stamp_ns': q.get('stamp_ns'),
                               'georeference': geo}
            figures.update(check_rmse={'horizontal_m': out['accuracy']['check_rmse_h_m'],
                                       'vertical_m': out['accuracy']['check_rmse_v_m'],
                                       'count': out['accuracy']['check_count']},
                           fix_share=q.get('fix_share'))
            if q.get('block') in (BLOCK_IN_FLIGHT, BLOCK_ADJUSTED):
                figures['block'] = q['block']
            check = q.get('block_check')
            if isinstance(check, dict) and check.get('status') in BLOCK_CHECK_STATUSES:
                figures['block_check'] = {'status': check['status'], 'summary': str(check.get('summary', ''))[:400]}
        figures['georeference'] = geo
        out['go_no_go'] = with_node_errors(go_no_go(figures, self.params), out['health'])
        return out

    def status(self) -> dict:
        """status.json of the web page: every drone's figures (keyed by its URL name), the unknown publishers,
        the limits, and when it was made."""
        with self._lock:
            drones = list(self.drones.values())
            unknown, diag_unknown = dict(self.unknown), list(self.diag_unknown)
        return {'drones': {drone_key(d.ns): {'ns': d.ns or '/', **self.drone_status(d)} for d in drones},
                'unknown_drones': unknown, 'diagnostics_unknown_publishers': diag_unknown,
                'security': self.security, 'generated_unix_s': time.time(),
                'limits': {k: getattr(self.params, k) for k in QualityLimits.__dataclass_fields__}}

    def tiles_since(self, key: str, seq: int) -> tuple[int, list]:
        """Ortho tiles of the drone that came after the first `seq` -> (new seq, [[z, x, y], ...] distinct)."""
        d = self._drone(key)
        if d is None:
            return 0, []
        with self._lock:
            new = d.tile_log[seq:]
            n = len(d.tile_log)
        return n, [list(t) for t in dict.fromkeys(new)]

    def tile(self, key: str, z: int, x: int, y: int) -> bytes | None:
        d = self._drone(key)
        with self._lock:
            return d.tiles.get((z, x, y)) if d is not None else None

    def geojson(self, key: str, kind: str) -> dict | None:
        """'coverage' (gaps, survey area), 'track' (keyframe centres), 'targets' (check points, GCPs) or 'live'
        (the drone's live position as a Point and its GNSS track as a LineString)."""
        d = self._drone(key)
        if d is None:
            return None
        with self._lock:
            if kind == 'coverage':
                return d.coverage or {'type': 'FeatureCollection', 'features': []}
            origin, poses, q = d.origin, sorted(d.poses.items()), d.quality
            position, live = (dict(d.position) if d.position else None), list(d.live_track)
        feats = []
        if kind == 'live':
            if len(live) >= 2:
                feats.append({'type': 'Feature', 'properties': {'role': 'track', 'fixes': len(live)},
                              'geometry': {'type': 'LineString', 'coordinates': [list(p) for p in live]}})
            if position is not None:
                feats.append({'type': 'Feature', 'properties': {'role': 'position', 'h_m': position['h_m'],
                                                                'status': position['status'],
                                                                'drone': drone_key(d.ns)},
                              'geometry': {'type': 'Point', 'coordinates': [position['lon_deg'], position['lat_deg']]}})
        if kind == 'track' and origin is not None and poses:
            lat, lon, _ = origin.enu_to_geodetic(np.array([p for _, p in poses]).reshape(-1, 3))
            feats.append({'type': 'Feature', 'properties': {'keyframes': len(poses)}, 'geometry': {
                'type': 'LineString', 'coordinates': [[float(a), float(b)] for a, b in
                                                      zip(np.atleast_1d(lon), np.atleast_1d(lat))]}})
        if kind == 'targets' and q is not None:
            for role, rows in (('check', q.get('check_points', [])), ('gcp', q.get('gcps', []))):
                for r in rows:
                    try:
                        e = [float(v) for v in r['residual_enu_m']][:3]
                        lon, lat = float(r['lon_deg']), float(r['lat_deg'])
                    except (KeyError, TypeError, ValueError):
                        continue
                    feats.append({'type': 'Feature', 'geometry': {'type': 'Point', 'coordinates': [lon, lat]},
                                  'properties': {'name': str(r.get('name')), 'role': role, 'residual_enu_m': e,
                                                 'residual_h_m': float(np.hypot(e[0], e[1])),
                                                 # a GCP used horizontally only: its height is not the survey's
                                                 'residual_v_m': float(e[2]) if r.get('use', 'full') in
                                                 ('full', 'check') else None,
                                                 'use': r.get('use'), 'images': r.get('images')}})
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


def diagnostic_figures(st: dict) -> dict:
    """The figures of a drone_status() that /diagnostics carries beside the checks, under flat names, with the
    values of status.json (the page shows the same)."""
    a = st.get('accuracy') or {}
    gcp = a.get('gcp_rmse') or {}
    cov = st.get('coverage') or {}
    bias = a.get('gnss_bias_enu_m')
    return {'check_rmse_h_m': a.get('check_rmse_h_m'), 'check_rmse_v_m': a.get('check_rmse_v_m'),
            'check_count': a.get('check_count'), 'georeference': a.get('georeference'),
            'gcp_rmse_h_m': _number(gcp.get('horizontal_m')), 'gcp_rmse_v_m': _number(gcp.get('vertical_m')),
            'gcp_count': gcp.get('count'),
            'gnss_bias_enu_m': [_number(v) for v in bias] if isinstance(bias, list) else None,
            'coverage_share': _number(cov.get('coverage_share')),
            'gaps': [[g.get('kind'), _number(g.get('area_m2'))] for g in cov.get('gap_list', [])]
                    if cov else None,
            'warnings': (st.get('go_no_go') or {}).get('warnings') or [],
            'updated_unix_s': st.get('updated_unix_s')}


BLOCK_CHECK_MESSAGE = 'block check: '   # stages/block_health.py: the adjuster's block check on /diagnostics


def with_node_errors(g: dict, health: dict) -> dict:
    """A verdict with the drone's nodes that say ERROR on /diagnostics: each is a reason, and the verdict is
    not GO while one does (a node's error is no figure to judge: WAIT, the reason says which node and why).
    A failed block check the verdict already reasons on (from the quality document) is not said twice."""
    block_failed = any(c.get('name') == BLOCK_CHECK_NAME and not c.get('passes') for c in g.get('checks', ()))
    errors = [f'{name.lstrip("/")} ERROR: {msg}' for name, (level, msg) in sorted(health.items())
              if level == 2 and not (block_failed and str(msg).startswith(BLOCK_CHECK_MESSAGE))]
    if not errors:
        return g
    return {**g, 'verdict': WAIT if g['verdict'] == GO else g['verdict'], 'reasons': g['reasons'] + errors}


def low_forward_overlap(props: dict) -> list[dict]:
    """The coverage's keyframe pairs below the target forward overlap -> [{'overlap', 'area_m2',
    'stamps_ns'}]:
    area_m2 is the stretch of the swath between the two keyframes (footprint width x their distance,
    (1 - overlap) x footprint length)."""
    w, length = _number(props.get('footprint_width_m')), _number(props.get('footprint_length_m'))
    out = []
    for row in props.get('low_forward_pairs') or []:
        try:
            a, b, o = int(row[0]), int(row[1]), float(row[2])
        except (TypeError, ValueError, IndexError):
            continue
        area = w * max(1.0 - o, 0.0) * length if w and length else None
        out.append({'overlap': o, 'area_m2': None if area is None else round(area, 1), 'stamps_ns': [a, b]})
    return out


def diagnostic_text(value) -> str:
    """A figure as /diagnostics says it: 'not measured', a string as it is, a number in full (repr)."""
    return 'not measured' if value is None else value if isinstance(value, str) else repr(value)


def _number(v):
    """A figure from a drone's document as a float (None when it is not a finite number)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    v = float(v)
    return v if np.isfinite(v) else None


def security_status() -> dict:
    """What the installed ROS 2 middleware offers for security (SROS2: authentication, access control,
    encryption) and whether this process asked for it (ROS_SECURITY_ENABLE / ROS_SECURITY_ENCLAVE).

    'headline' says in one line whether the DDS traffic is authenticated and encrypted; 'summary' adds why
    and what to do. 'refuse' is set when security is asked for and the middleware cannot give it (rcl would
    refuse to create the node: "This Fast DDS version doesn't have the security libraries")."""
    import sys
    rmw = os.environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    asked = os.environ.get('ROS_SECURITY_ENABLE', '').lower() == 'true'
    enclave = os.environ.get('ROS_SECURITY_ENCLAVE', '')
    keystore = os.environ.get('ROS_SECURITY_KEYSTORE', '')
    sros2 = any((Path(p) / 'sros2').is_dir() for p in sys.path if p)   # the keystore / enclave tools
    plugins = _dds_security_plugins() if rmw.startswith('rmw_fastrtps') else None
    enabled = asked and bool(keystore) and bool(enclave) and plugins is not False
    env = 'ROS_SECURITY_ENABLE=true, ROS_SECURITY_KEYSTORE, ROS_SECURITY_ENCLAVE'
    plain = 'DDS traffic NOT authenticated, NOT encrypted'
    why = (": any node on this ROS_DOMAIN_ID can publish a drone's topics under its names; the allow-list "
           'and the publisher check keep out nodes with other names, not impostors.')
    howto = ('For authenticated, encrypted topics use a ROS 2 installation whose Fast DDS has the security '
             f'plugins (the Debian/ROS packages) with ros-jazzy-sros2, and set {env}.')
    refuse = ''
    if plugins is False:
        headline = plain + ' (SROS2 is not available with this ROS 2 installation)'
        summary = (f'{plain}{why} SROS2 is NOT AVAILABLE here: the installed Fast DDS (libfastrtps of the PyPI '
                   'ROS wheels) is built without the DDS security plugins (authentication, access control, '
                   f'encryption). {howto}')
        if asked:
            refuse = ('ROS_SECURITY_ENABLE=true, but the installed Fast DDS (the PyPI ROS wheels) has no DDS '
                      'security plugins, so the station cannot authenticate or encrypt its topics. ' + howto
                      + ' Or unset ROS_SECURITY_ENABLE to run without security.')
    elif enabled:
        headline = f'DDS traffic authenticated and encrypted (SROS2 enclave {enclave}, as its governance says)'
        summary = (f'{headline}: ROS_SECURITY_ENABLE=true, enclave {enclave} in {keystore} ({rmw}); rcl '
                   "refuses to start when the enclave's files are missing")
    else:
        headline = plain + (' (ROS_SECURITY_ENABLE is not set)' if not asked else ' (no keystore or enclave)')
        summary = plain + why + (' ROS_SECURITY_ENABLE is not set. ' if not asked else
                                 ' ROS_SECURITY_ENABLE=true without ROS_SECURITY_KEYSTORE and ROS_SECURITY_ENCLAVE. ')
        summary += (f'The sros2 tools are installed: create a keystore and enclaves and set {env}.' if sros2 else
                    'The sros2 package (keystore and enclave tools) is not installed. ' + howto)
    return {'enabled': enabled, 'authenticated': enabled, 'encrypted': enabled, 'asked': asked, 'rmw': rmw,
            'sros2_installed': sros2, 'dds_security_plugins': plugins, 'headline': headline,
            'summary': summary, 'refuse': refuse}


def _dds_security_plugins() -> bool | None:
    """Does the Fast DDS library rclpy loads carry the DDS security plugins (builtin.PKI-DH)? None: not found
    (another middleware, or a layout this does not know)."""
    import sys
    for d in (Path(sys.prefix) / 'lib', Path('/opt/ros/jazzy/lib')):
        for lib in sorted(d.glob('libfastrtps.so.*')) + sorted(d.glob('libfastdds.so.*')):
            try:
                return b'builtin.PKI-DH' in lib.read_bytes()
            except OSError:
                continue
    return None


CONTROL_COUNTS = ('gcps', 'gcps_held', 'gcps_full', 'gcps_horizontal_only', 'gcps_rejected', 'gcps_not_seen',
                  'control_detections_rejected')


def _control_status(control: dict | None) -> dict | None:
    """What the bundle node made of the control file so far (core/control_live.py): counts and faults."""
    if not control:
        return None
    return {**{k: control.get(k) for k in CONTROL_COUNTS}, 'faults': list(control.get('faults', []))}
