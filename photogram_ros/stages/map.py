"""The map stage: fusion of the pair clouds into the tiled map on disk, keyframe images and poses, the live
ortho tiles, the coverage and the origin of `map`, without ROS.

In (plain methods): `set_origin` (the georeference), `add_cloud` (a pair cloud in `map`: x, y, z and
optionally rgb, confidence), `add_image` (a keyframe image, saved as JPEG; one smaller than the camera, the
copy reduced for stereo, only until `add_image_jpeg` brings the full-resolution JPEG, which is saved as it
came and never replaced by a reduced one), `add_pose` (a keyframe's
map_T_cam), `add_keyframe_fix` (its GNSS position: the track for the coverage), `add_sparse` (tie points:
the ground under the keyframes), `set_camera` (the input calibration), `set_final_camera` (the camera a full
adjustment's poses were adjusted with: it replaces the input calibration in the map folder), `set_control_points`
(the bundle adjuster's check points and GCPs with their detections, kept in the map folder),
`set_cloud_placement` (the pose stereo placed a keyframe's next pair cloud with, provisional or final) and
`set_keyframe_pose` (every pose of a keyframe, provisional ones included): a keyframe whose pose moved by
replace_move_m from a fused cloud's placement, or turned final (replace_provisional), has that cloud placed again
(core/placements.py, core/fusion.py Fusion.move), by `replace_moved`; `follows_poses` says whether the stage needs
those two inputs.
Periodic (the node's timers): `replace_moved`, `flush` (changed cells and poses to disk), `stream` (block means of the
changed tiles), `stream_ortho` (PNG tiles of the live orthomosaic), `update_coverage`, `update_diag`.
Out: through `out` (a `MapOutputs`): the stream's points, the ortho tiles, the coverage GeoJSON; through
`diag` (stages/report.py): the /diagnostics keys and problems. Every method runs under `lock` (the fusion and
its tiles are not thread-safe). The map folder (io/map_store.py) is why this is a stage and not core/.
"""

from __future__ import annotations

import dataclasses
import errno
import functools
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from photogram_ros.core import gsd
from photogram_ros.core.coverage import COVERAGE, FORWARD_OVERLAP, NOT_ORIENTED, Coverage, CoverageConfig
from photogram_ros.core.fusion import Fusion, FusionConfig, downsample, pack_rgb
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.pace import CpuShare
from photogram_ros.core.placements import Placements
from photogram_ros.errors import ConfigError, PhotogramError
from photogram_ros.io import flight_inputs
from photogram_ros.io.map_store import CAMERA_FINAL, CAMERA_INPUT, MapStore
from photogram_ros.params import param
from photogram_ros.stages.report import ERROR, DiagnosticsLog

MIN_TIE_POINTS_GROUND = 20   # tie points whose median height is kept as the ground (fewer say too little)

STREAM_DTYPE = np.dtype([('x', np.float32), ('y', np.float32), ('z', np.float32), ('rgb', np.uint32),
                         ('count', np.uint32)])


@dataclass
class MapParams(FusionConfig, CoverageConfig):
    """The fusion's (core/fusion.py) and the coverage's (core/coverage.py) parameters and the node's: folder,
    origin, keyframes, streams."""
    map_dir: str = param('map', 'Folder of the persistent map (tiles, keyframes, map.json); reloaded if it exists')
    flush_interval_s: float = param(1.0, 'Changed cells are written and fsynced this often, s (the most a '
                                         'crash can lose)', min=0.05, max=600.0)
    flush_beside_fusion: bool = param(True, 'the flush runs beside the map\'s other work (the map node\'s own callback '
                                            'group): clouds are fused while the cells written are made durable '
                                            '(fsync, the slow part); false: in the one callback group of the map, '
                                            'where a cloud waits for the fsync')
    use_origin_params: bool = param(False, 'Take the map origin from origin_* instead of /map/georeference')
    origin_lat_deg: float = param(0.0, 'Latitude of the map origin, deg (with use_origin_params)',
                                  min=-90.0, max=90.0)
    origin_lon_deg: float = param(0.0, 'Longitude of the map origin, deg (with use_origin_params)',
                                  min=-180.0, max=180.0)
    origin_h_m: float = param(0.0, 'Ellipsoidal height of the map origin, m (with use_origin_params)',
                              min=-1e4, max=1e5)
    save_keyframes: bool = param(True, 'Save keyframe JPEGs and poses in map_dir (needed for the orthomosaic)')
    jpeg_quality: int = param(90, 'JPEG quality of saved keyframes', min=10, max=100)
    stream_period_s: float = param(2.0, 'Period of map/cloud_downsampled messages, s', min=0.05, max=3600.0)
    stream_downsample: int = param(4, 'Stream block size in cells (4: one point per 4x4 cells)', min=1, max=256)
    stream_max_points: int = param(50000, 'Most points per stream message; the rest follows next period',
                                   min=100, max=10_000_000)
    ortho: bool = param(True, 'Stream the live orthomosaic of the changed tiles on map/ortho_tiles')
    ortho_gsd_m: float = param(0.2, 'Ground pixel of the live ortho tiles, m: the XYZ zoom level whose pixel is '
                                    'the finest not finer than this', min=0.01, max=1000.0)
    ortho_period_s: float = param(2.0, 'Period of map/ortho_tiles batches, s', min=0.05, max=3600.0)
    ortho_max_tiles: int = param(16, 'Most ortho tiles per batch; the rest follows next period', min=1, max=10000)
    ortho_cpu_share: float = param(0.0, 'Share of one core the ortho tiles may take over 20 s (0: no limit); over '
                                        'it a batch is deferred to a later period (ortho_batches_deferred), so the '
                                        'pose chain keeps the pace; the tiles then show the newer map', min=0.0,
                                   max=256.0)
    coverage: bool = param(True, 'Follow the survey coverage and its gaps (map/coverage, /diagnostics)')
    coverage_period_s: float = param(1.0, 'Period of the coverage update and of map/coverage, s',
                                     min=0.1, max=3600.0)
    survey_area_file: str = param('', 'Survey area: a QGroundControl .plan (its Survey polygon or geofence) or a '
                                      'GeoJSON polygon; "" = the flight lines\' swaths')
    replace_move_m: float = param(0.0, 'a keyframe whose pose moved this far from the pose one of its fused clouds '
                                      'was placed with (centre shift + height x rotation, m), or whose provisional '
                                      'pose turned final, has that cloud taken out of the map and fused again at '
                                      'its new pose (0.25: about 2 cells; it keeps a record of every fused cloud); 0: '
                                      'clouds fused final stay where they were fused (the 317-photo 20 MP bench at 0.25 took the '
                                      'mapping process over the 1.5 GB bound: bench/notes_inflight_20mp.md)',
                                  min=0.0, max=1e3)
    replace_provisional: bool = param(True, 'a cloud fused with a provisional placement (stereo pair_provisional, '
                                            'before the first turn) keeps what it merged into the cells until its '
                                            'keyframe\'s pose turns final, then is taken out and fused again at the '
                                            'final pose once and its record dropped; with replace_move_m 0 a cloud '
                                            'fused with a final pose keeps no record')
    replace_memory_mb: float = param(160.0, 'memory for what each fused cloud merged into the cells (kept to place '
                                            'it again), MB; past it the oldest finally placed ones are dropped and a '
                                            'later move of theirs is counted (clouds_moved_not_replaced), a WARN',
                                     min=0.0, max=1e5)
    replace_budget_s: float = param(0.2, 'the most one replace_moved round spends placing clouds again, s (the rest '
                                         'in the next round: new clouds go first)', min=0.01, max=3600.0)
    replace_cpu_share: float = param(0.1, 'share of one core placing clouds again may take over 20 s in flight (0: no '
                                          'limit); over it the rest waits (the map\'s clouds and keyframe images go '
                                          'first: they queue in memory while the map is busy); the map\'s close '
                                          'places every one left', min=0.0, max=256.0)
    warn_unfused_keyframes: int = param(20, 'WARN on /diagnostics when this many keyframes came (images, or poses '
                                            'without save_keyframes) and '
                                            'nothing was fused since the last fused cloud (thrice as many before '
                                            'the first), with the reason', min=1, max=100000)


def _locked(method):
    """Run a MapStage method under the stage's lock."""
    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with self.lock:
            return method(self, *args, **kwargs)
    return wrapper


def _value(load):
    """`load()` when it is a function (a node's message conversion, whose errors the stage reports as its
    own), else `load` itself."""
    return load() if callable(load) else load


class MapOutputs:
    """Where the map's streams go (a node publishes them); each does nothing here."""

    def stream(self, points: np.ndarray, stamp_ns: int) -> None:
        """STREAM_DTYPE points: block means of the tiles that changed, in `map`."""

    def ortho_tile(self, z: int, x: int, y: int, png: bytes, stamp_ns: int) -> None:
        """One XYZ / Web Mercator tile of the live orthomosaic, PNG with alpha."""

    def coverage(self, doc: dict) -> None:
        """The coverage GeoJSON (io/mission.py coverage_geojson)."""


def open_store(p: MapParams) -> MapStore:
    """The map folder: an existing map keeps its cell; a new one with cell_m AUTO starts with the
    simulator's cell until the first pair cloud tells the flying height (MapStore.set_cell_m)."""
    if (Path(p.map_dir) / 'map.json').exists():
        return MapStore(p.map_dir, None if p.cell_m == gsd.AUTO else p.cell_m, p.tile_cells)
    cell = gsd.REF_LENGTHS_M['cell_m'] if p.cell_m == gsd.AUTO else p.cell_m
    return MapStore(p.map_dir, cell, p.tile_cells)


def ground_z(tie_points_map: np.ndarray | None, centre: np.ndarray) -> float | None:
    """Median height of the tie points (N, 3, map) within 30 m of a camera centre (all of them when fewer than 10
    are that close); None without tie points."""
    s = tie_points_map
    if s is None or not len(s):
        return None
    near = np.hypot(s[:, 0] - centre[0], s[:, 1] - centre[1]) < 30.0
    return float(np.median(s[near, 2] if near.sum() >= 10 else s[:, 2]))


class MapStage:
    """The map (module docstring). Raises ConfigError when the map folder or the survey area cannot be read."""

    def __init__(self, p: MapParams, diag=None, out: MapOutputs | None = None, log=None):
        """`log(text)`: what the stage says once (the map's cell); None: nowhere."""
        self.params = p
        self.diag, self.out, self._log = diag or DiagnosticsLog(), out or MapOutputs(), log or (lambda text: None)
        self._newest_cloud_ns = 0
        self.lock = threading.RLock()
        try:
            self.store = open_store(p)
        except PhotogramError as exc:
            raise ConfigError(f'map_node: {exc}') from exc
        self.gsd = None                # core.gsd.GsdSettings once derived
        self._cell_pending = p.cell_m == gsd.AUTO and not self.store.tile_keys()
        self.fusion = Fusion(self._fusion_config(self.store.cell_m), self.store)
        self._keyframes_unfused = 0    # keyframe poses since the last cloud that fused points
        self._clouds_unfused = 0       # clouds since then (that fused nothing)
        self._pose_z: dict = {}        # stamp -> camera height in map (the flying height for the GSD)
        self._provisional_z: dict = {}  # the same from provisional poses, before the first final one
        if p.use_origin_params:
            self._set_origin(LocalFrame(p.origin_lat_deg, p.origin_lon_deg, p.origin_h_m))
        self._stream_pending: set = set(self.store.tile_keys())   # a restarted map streams what it has
        self._ortho_pending: set = set(self._stream_pending)
        self.ortho = None            # core.ortho_tiles.OrthoTiler, once the origin is known
        self.coverage = None         # core.coverage.Coverage, once the camera is known
        self._cov_poses: dict = {}   # stamp -> map_T_cam not yet in the coverage
        self._cov_fixes: dict = {}   # stamp -> keyframe fix in map ENU (the track, oriented or not)
        self._cov_fixes_early: dict = {}   # stamp -> (lat, lon, h) of fixes that came before the origin
        self._oriented: dict = {}    # stamp -> map_T_cam of the oriented keyframes (attitude for stand-ins)
        self._cov_dirty = False
        self._sparse_xyz = None      # (N, 3) latest tie points: the ground under the keyframes
        self.camera = None
        self._gaps_reported: list = []   # centroids of the gaps already warned about
        self._survey_rings = None
        if p.survey_area_file:       # a bad file stops the start, naming it
            from photogram_ros.io.mission import read_survey_area
            try:
                self._survey_rings = read_survey_area(p.survey_area_file)
            except PhotogramError as exc:
                raise ConfigError(f'map_node: {exc}') from exc
        self._camera_saved = None     # (camera, its name in camera.json) last written
        self._camera_final = False    # a full adjustment's camera came: the input calibration no longer counts
        self._poses_pending: dict = {}
        self._full_jpeg: set = set()       # stamps whose full-resolution JPEG is saved (add_image_jpeg)
        self._images_saved: set = set()    # stamps with a saved image
        self._fuse_s = 0.0
        self.placements = (Placements(p.replace_move_m, int(p.replace_memory_mb * 1e6), keep_final=p.replace_move_m > 0)
                           if p.replace_move_m > 0 or p.replace_provisional else None)
        self._ortho_share = CpuShare(p.ortho_cpu_share)
        self._replace_share = CpuShare(p.replace_cpu_share)
        self._closed = False

    # --- GSD-bound geometry ----------------------------------------------------------------------

    def posed_keyframes(self) -> int:
        """Keyframes whose final pose the map has (their heights set the GSD)."""
        return len(self._pose_z)

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
        heights = self._pose_z or self._provisional_z   # before the first turn: the provisional poses' heights
        if self.camera is None or not heights:
            self.diag.problem(f'cell_m from the GSD needs camera_info and a keyframe pose before the first pair '
                              f'cloud: keeping {self.store.cell_m} m')
            return
        height = heights[max(heights)] - float(np.median(cloud_z))
        try:
            self.gsd = gsd.derive(self.camera.width, self.camera.height, self.camera.fx, height)
        except ConfigError as exc:
            self.diag.problem(f'cell_m from the GSD: {exc}; keeping {self.store.cell_m} m')
            return
        cell = self.gsd.cell_m if self.params.cell_m == gsd.AUTO else self.params.cell_m
        if cell != self.store.cell_m:
            self.store.set_cell_m(cell)
        self.fusion = Fusion(self._fusion_config(cell, self.gsd), self.store)
        self._log(f'map cell {cell} m, fusion tolerance {self.fusion.config.min_tolerance_m} m from '
                               f'the GSD: {self.gsd.summary()}')
        self.diag.set('gsd_m', self.gsd.gsd_m)

    @property
    def follows_poses(self) -> bool:
        """Whether fused clouds follow their keyframe's pose (replace_move_m or replace_provisional): the node then
        feeds set_cloud_placement and set_keyframe_pose and calls replace_moved."""
        return self.placements is not None

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
    def set_origin(self, lat_deg: float, lon_deg: float, h_m: float) -> None:
        """The georeference: the geodetic origin of `map` (ellipsoidal height); ignored with use_origin_params,
        and when the folder already holds tiles in another origin's frame (a WARN)."""
        if self.params.use_origin_params:
            return
        try:
            self._set_origin(LocalFrame(lat_deg, lon_deg, h_m))
        except PhotogramError as exc:
            self.diag.problem(f'bad georeference: {exc}')

    @_locked
    def add_cloud(self, frame_id: str, stamp_ns: int, load) -> None:
        """A pair cloud in `frame_id` ('map' or ''): `load` (or `load()`) are its points (x, y, z, optionally rgb,
        confidence; it may raise PhotogramError, ValueError, TypeError: the cloud is dropped, counted, a WARN)."""
        try:
            if frame_id not in ('map', ''):
                raise ConfigError(f'dense cloud in frame {frame_id!r}; the map fuses clouds in "map"')
            pts = _value(load)
            if self._cell_pending and pts.size:
                self._derive_cell(np.asarray(pts['z'], float))
            t0 = time.perf_counter()
            if self.placements is not None and self.placements.wants_record(stamp_ns):
                n, contribution = self.fusion.add(pts, record=True)
                self.placements.fused(stamp_ns, contribution)
            else:
                n = self.fusion.add(pts)
                if self.placements is not None:
                    self.placements.fused(stamp_ns, None)
            if n:
                self._keyframes_unfused = self._clouds_unfused = 0
            else:
                self._clouds_unfused += 1
            self._newest_cloud_ns = max(self._newest_cloud_ns, stamp_ns)
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

    @_locked
    def set_cloud_placement(self, stamp_ns: int, load, provisional: bool) -> None:
        """The pose (`load` or `load()`: map_T_cam) stereo placed its next pair cloud of keyframe `stamp_ns` with."""
        if self.placements is None:
            return
        try:
            self.placements.placed_with(stamp_ns, _value(load), provisional)
        except PhotogramError as exc:
            self.diag.problem(f'dense cloud placement rejected: {exc}')

    @_locked
    def set_keyframe_pose(self, stamp_ns: int, load, provisional: bool) -> None:
        """A keyframe's latest pose, provisional or final: its fused clouds follow it (replace_moved)."""
        try:
            T = _value(load)
            if provisional and not self._pose_z and len(self._provisional_z) < 1000:
                self._provisional_z[stamp_ns] = float(T[2, 3])   # the flying height until a final pose comes
            if self.placements is not None:
                self.placements.pose(stamp_ns, T, provisional)
        except PhotogramError as exc:
            self.diag.problem(f'keyframe pose rejected: {exc}')

    @_locked
    def replace_moved(self, budget_s: float | None = None) -> int:
        """Place again the fused clouds whose keyframe's pose moved (replace_move_m) or turned final, for at most
        `budget_s` and within replace_cpu_share (None: all, whatever the share); returns how many."""
        if self.placements is None:
            return 0
        t0, done = time.perf_counter(), 0
        for stamp, i in self.placements.due():
            if budget_s is not None and (time.perf_counter() - t0 > budget_s or self._replace_share.over()):
                self.diag.count('replace_rounds_deferred')
                break
            part = self.placements.part(stamp, i)
            if part.contribution is None:   # dropped for memory by an earlier move of this round: counted there
                continue
            T_new, provisional = self.placements.pose_of(stamp)
            if part.contribution.cell_m != self.cell_m:   # fused before the cell was derived: cannot be moved
                self.placements.cannot_follow(stamp, i)
                continue
            with self._replace_share.measure():
                _, contribution = self.fusion.move(part.contribution, T_new @ np.linalg.inv(part.map_T_cam))
            self.placements.replaced(stamp, i, contribution)
            done += 1
            self.diag.count('clouds_replaced')
            if provisional:
                self.diag.count('clouds_replaced_provisional')
        if done:
            self._stream_pending |= self.fusion.changed_tiles
            self._ortho_pending |= self.fusion.changed_tiles
            self.fusion.changed_tiles.clear()
            self._fuse_s += time.perf_counter() - t0
        return done

    def add_image(self, stamp_ns: int, load) -> None:
        """A keyframe image (`load` or `load()`: the (H, W[, 3]) array; a conversion may raise PhotogramError),
        saved as JPEG, unless the full-resolution JPEG of that keyframe came already (add_image_jpeg)."""
        if stamp_ns in self._full_jpeg:
            return
        try:
            import cv2
            img = _value(load)
            ok, buf = cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, self.params.jpeg_quality])
            if not ok:
                raise ConfigError('JPEG encoding of a keyframe failed')
            self._save_image(stamp_ns, buf.tobytes())
        except (PhotogramError, OSError) as exc:
            self._write_failed('keyframe image not saved', exc)

    def add_image_jpeg(self, stamp_ns: int, data: bytes) -> None:
        """A keyframe's full-resolution JPEG (as the camera encoded it), saved as it is: it replaces a reduced
        copy add_image saved, and no later add_image replaces it."""
        try:
            self._full_jpeg.add(stamp_ns)
            self._save_image(stamp_ns, bytes(data))
        except OSError as exc:
            self._write_failed('keyframe image not saved', exc)

    def _save_image(self, stamp_ns: int, jpeg: bytes) -> None:
        self.store.save_keyframe_image(stamp_ns, jpeg)
        if stamp_ns not in self._images_saved:
            self._images_saved.add(stamp_ns)
            self._keyframes_unfused += 1
            self.diag.count('keyframes_saved')

    @_locked
    def add_pose(self, stamp: int, load) -> None:
        """A keyframe's map_T_cam (4, 4), or a function giving it (it may raise PhotogramError). The bundle
        adjuster republishes each pose while it sits in its window: the latest is kept and written at the next
        flush, instead of an fsync per republication."""
        try:
            T = _value(load)
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
    def add_keyframe_fix(self, stamp_ns: int, lat_deg: float, lon_deg: float, h_m: float, status: int,
                         sigma_h_m: float | None = None, sigma_v_m: float | None = None) -> None:
        """A keyframe's GNSS position (NavSatStatus status; < 0: none) and its 1-sigmas, m, when known: its
        place on the track for the coverage, saved for the report and for a resumed run to feed again."""
        if status < 0:
            return
        if self.params.save_keyframes:
            try:   # the flight's own fixes, for the report's GNSS residuals per photo
                flight_inputs.append_keyframe_fix(self.store.root, stamp_ns, lat_deg, lon_deg, h_m, status,
                                                  sigma_h_m, sigma_v_m)
            except OSError as exc:
                self._write_failed('keyframe fix not saved', exc)
        if self.store.origin is None:   # the georeference comes later: kept until it does
            self._cov_fixes_early[stamp_ns] = (lat_deg, lon_deg, h_m)
            return
        try:
            self._cov_fixes[stamp_ns] = np.asarray(
                self.store.origin.geodetic_to_enu(lat_deg, lon_deg, h_m), float).reshape(3)
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
    def add_sparse(self, load) -> None:
        """Tie points (`load` or `load()`: a table with x, y, z, in `map`): the ground under the keyframes for the
        coverage; their median height kept in the map folder for the matching after landing (io/densify.py)."""
        try:
            pts = _value(load)
            xyz = np.column_stack([pts['x'], pts['y'], pts['z']]).astype(np.float64)
            self._sparse_xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
        except (PhotogramError, ValueError) as exc:
            self.diag.problem(f'sparse cloud not used for the coverage: {exc}')
            return
        if self.params.save_keyframes and len(self._sparse_xyz) >= MIN_TIE_POINTS_GROUND:
            try:
                flight_inputs.save_tie_point_ground(self.store.root, float(np.median(self._sparse_xyz[:, 2])),
                                                    len(self._sparse_xyz))
            except OSError as exc:
                self._write_failed('tie points\' ground height not saved', exc)

    @_locked
    def set_control_points(self, load) -> None:
        """The bundle adjuster's live accuracy document (`load` or `load()`: the dict; a conversion may raise
        PhotogramError): the latest is kept in the map folder (control_points.json) with the detections the
        flight report intersects again."""
        try:
            doc = _value(load)
            if self.params.save_keyframes and isinstance(doc, dict) and doc.get('detections'):
                self.store.save_control_points(doc)
        except (PhotogramError, OSError, ValueError, TypeError) as exc:
            self._write_failed('control points not saved', exc)

    @_locked
    def set_camera(self, load) -> None:
        """The calibration (`load` or `load()`: the core.camera model; a conversion may raise PhotogramError),
        saved with the keyframes until a full adjustment's camera (set_final_camera) replaces it."""
        if self._camera_final:
            return
        self._save_camera(load, CAMERA_INPUT)

    @_locked
    def set_final_camera(self, load) -> None:
        """The camera a full adjustment's poses were adjusted with (`load` as in set_camera; its
        self-calibration when it refined the intrinsics): saved as the keyframes' camera in place of the
        input calibration, which no longer replaces it; the latest one counts."""
        self._camera_final = True
        self._save_camera(load, CAMERA_FINAL)

    def _save_camera(self, load, name: str) -> None:
        try:
            cam = _value(load)
            self.camera = cam
            if not self.params.save_keyframes:
                return
            if (cam, name) != self._camera_saved:
                self.store.save_camera(cam, name)
                self._camera_saved = (cam, name)
                if name == CAMERA_INPUT:   # the calibration the flight started with, for the report's before/after
                    flight_inputs.save_input_camera(self.store.root, cam)
        except (PhotogramError, OSError) as exc:
            self._write_failed('camera info not saved', exc)

    # --- outputs ---------------------------------------------------------------------------------

    def flush(self) -> None:
        """Changed cells written under the stage's lock, made durable (fsync) outside it: fusing goes on."""
        with self.lock:
            self._save_poses()
            try:
                n = self.fusion.flush(sync=False)
                if n:
                    self.diag.count('cells_flushed', n)
            except OSError as exc:
                self._write_failed(f'map flush to {self.params.map_dir} failed', exc)
                return
        try:
            self.store.sync()
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

    def _stamp_ns(self, now_ns: int) -> int:
        """`now_ns` (the node's clock), or the newest pair cloud's stamp while that clock reads 0 (use_sim_time
        and no /clock yet)."""
        return now_ns or self._newest_cloud_ns

    @_locked
    def stream(self, listening: bool, now_ns: int = 0) -> None:
        """Block means of the changed tiles, at most stream_max_points. Nobody `listening` (no ground station
        linked): the changed tiles are kept for when one connects instead of spending a quarter second per
        period on block means."""
        if not self._stream_pending or not listening:
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
        self.out.stream(out, self._stamp_ns(now_ns))
        self.diag.count('stream_points', n)

    @_locked
    def stream_ortho(self, listening: bool, now_ns: int = 0) -> None:
        """PNGs of the XYZ tiles the changed fusion tiles touch (kept for later while nobody is `listening`)."""
        if not self._ortho_pending or self.store.origin is None or not listening:
            return
        if self._ortho_share.over():
            self.diag.count('ortho_batches_deferred')
            return
        with self._ortho_share.measure():
            self._render_ortho(now_ns)

    def _render_ortho(self, now_ns: int) -> None:
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
        stamp = self._stamp_ns(now_ns)
        colours: dict = {}   # each fusion tile's block colours, once per batch
        for t in batch:
            img = self.ortho.render(t, self.fusion.tile_records, colours)
            if not img[..., 3].any():
                continue
            ok, buf = cv2.imencode('.png', img, [cv2.IMWRITE_PNG_COMPRESSION, 6])
            if ok:
                self.out.ortho_tile(t.z, t.x, t.y, buf.tobytes(), stamp)
                self.diag.count('ortho_tiles_sent')
                self.diag.count('ortho_bytes_sent', len(buf))
        self.diag.set('ortho_render_s', time.perf_counter() - t0)

    @_locked
    def update_coverage(self) -> None:
        """The keyframes since the last update into the coverage (stand-ins for those not oriented); when it
        changed, publish_coverage."""
        if self.camera is None or self.store.origin is None:
            return
        early, self._cov_fixes_early = self._cov_fixes_early, {}
        for stamp, llh in early.items():
            self.add_keyframe_fix(stamp, *llh, 0)
        if self.coverage is None:
            from photogram_ros.io.mission import survey_area_in_map
            area = survey_area_in_map(self._survey_rings, self.store.origin) if self._survey_rings else None
            self.coverage = Coverage(self.camera, CoverageConfig(**{
                f: getattr(self.params, f) for f in CoverageConfig.__dataclass_fields__}), area)
        for stamp in list(self._cov_poses):
            T = self._cov_poses[stamp]
            gz = ground_z(self._sparse_xyz, T[:3, 3])
            if gz is None:
                continue   # waits for the first sparse cloud
            self.coverage.set_keyframe(stamp, T, gz)
            self._oriented[stamp] = T
            del self._cov_poses[stamp]
            self._cov_dirty = True
        for stamp in [s for s in self._cov_fixes if s not in self._oriented and not self.coverage.oriented(s)]:
            T = self._stand_in(stamp)
            gz = ground_z(self._sparse_xyz, T[:3, 3]) if T is not None else None
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
        self.out.coverage(doc)
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
    def update_diag(self) -> None:
        """The fusion's and the folder's figures on diagnostics; a WARN when nothing was fused for long."""
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
        if self.placements is not None:
            # Fused clouds placed with a provisional pose (before the first turn): said, and placed again final.
            d.set('keyframes_fused_provisional', self.placements.provisional_keyframes())
            d.set('replace_memory_mb', round(self.placements.nbytes / 1e6, 1))
            d.set('clouds_placement_dropped', self.placements.dropped)
            d.set('clouds_moved_not_replaced', self.placements.moved_not_replaced)
            if self.placements.moved_not_replaced:
                d.problem('keyframes moved after their clouds were fused and what those clouds merged was no longer '
                          'kept (replace_memory_mb): clouds_moved_not_replaced of them stay where they were fused '
                          'until the matching after landing (export --densify)')
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
            self.replace_moved()
            self.flush()

