"""Simulate a survey flight end to end and write it as a bag with its ground truth beside it.

`simulate(config, out_dir)` is deterministic for a given config (seed included): the same config
always produces the same images, packets and truth, which is how `bags/` is regenerated exactly.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from photogram_ros.core import geoid
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame, utm_epsg
from photogram_ros.core.rotations import make_T, ned_R_frd_from_euler
from photogram_ros.errors import ConfigError
from photogram_ros.sim.autopilot import AutopilotClock, AutopilotLink, write_tlog
from photogram_ros.sim.flight import LawnmowerFlight, SurveyPlan
from photogram_ros.sim.gnss import MODES, GnssErrorModel, GnssScript
from photogram_ros.sim.render import Exposure, Renderer
from photogram_ros.sim.targets import draw_marker, layout_targets, level_ground, marker_corners_enu, Target
from photogram_ros.sim.terrain import Terrain, make_dem, make_texture
from photogram_ros.sim.truth import FrameTruth, GroundTruth, write_targets_file

START_UNIX_S = 1_780_000_000.0   # 2026-05-28T20:26:40Z: fixed so that bags are reproducible
TOPIC_IMAGE_RAW = '/camera/image_raw'
TOPIC_IMAGE_COMPRESSED = '/camera/image_raw/compressed'
TOPIC_CAMERA_INFO = '/camera/camera_info'
TOPIC_MAVLINK = '/mavlink/from_fcu'
TOPIC_FIX = '/gps/fix'


@dataclass
class SimConfig:
    seed: int = 7
    # Camera
    width_px: int = 640
    height_px: int = 480
    focal_px: float = 520.0
    dist: tuple = (-0.12, 0.05, 0.0005, -0.0003, -0.01)
    fps: float = 2.0
    camera_tilt_deg: float = 0.0
    noise_dn: float = 1.5
    # Flight
    altitude_m: float = 40.0
    speed_mps: float = 5.0
    turn_speed_mps: float = 2.5
    n_lines: int = 3
    line_length_m: float = 90.0
    side_overlap: float = 0.65
    heading_deg: float = 0.0
    repeats: int = 1
    gimbal_jitter_deg: float = 0.5
    lever_arm_frd_m: tuple = (0.05, 0.0, -0.20)   # camera centre -> GNSS antenna, body FRD
    # GNSS
    gnss_mode: str = 'rtk_fixed'
    gnss_changes: list = field(default_factory=list)   # [(t_s, mode)]
    gnss_outages: list = field(default_factory=list)   # [(t0_s, t1_s)]
    gps_rate_hz: float = 5.0
    # World
    origin_lat_deg: float = 47.3977
    origin_lon_deg: float = 8.5456
    origin_h_m: float = 488.0          # ellipsoidal height of the take-off point
    dem_res_m: float = 0.25
    tex_res_m: float = 0.0             # 0: about GSD / 2.5
    relief_m: float = 12.0
    n_buildings: int = 6
    n_gcp: int = 5
    n_check: int = 4
    target_size_m: float = 2.0
    # Faults (for robustness tests)
    drop_fraction: float = 0.0
    frame_gaps: list = field(default_factory=list)      # [(t0_s, t1_s)] with no frames
    black_frames: list = field(default_factory=list)    # [t_s]
    exposure_jumps: list = field(default_factory=list)  # [(t_s, gain)]
    mavlink_corruption: list = field(default_factory=list)  # [(t0_s, t1_s)] bytes flipped in the stream
    # Output
    image_transport: str = 'compressed'   # or 'raw'
    jpeg_quality: int = 90
    storage: str = 'sqlite3'              # or 'mcap'
    photos: bool = False                  # also write geotagged JPEGs + gcp_list.txt
    front_overlap: float = 0.80           # photo trigger spacing for `photos`
    ppk: bool = False                     # also write a PPK drone's photos, .pos and Timestamp.MRK in ppk/
    ppk_shutter_delay_ms: float = 0.0     # ppk/: the exposure this long after the event mark the MRK and .bin write
    ppk_sigma_scale: float = 1.0          # ppk/: factor on the .pos track's error (0: the true antenna track)
    rtk_photos: bool = False              # also write a DJI RTK drone's photos in rtk/ (RTK EXIF GPS, RtkFlag XMP)
    rtk_float_every: int = 0              # rtk/: every n-th photo FLOAT (flag 34) and rtk_float_offset_m off (0: none)
    rtk_float_offset_m: float = 1.0

    def validate(self) -> None:
        if self.gnss_mode not in MODES:
            raise ConfigError(f'gnss_mode {self.gnss_mode!r} unknown; choose from {sorted(MODES)}')
        for name in ('fps', 'altitude_m', 'speed_mps', 'turn_speed_mps', 'focal_px', 'line_length_m'):
            if not getattr(self, name) > 0:
                raise ConfigError(f'{name} must be positive (got {getattr(self, name)})')
        if not 0 <= self.side_overlap < 0.95 or not 0 <= self.front_overlap < 0.98:
            raise ConfigError('overlaps are fractions below 0.95')
        if self.n_lines < 1 or self.width_px < 32 or self.height_px < 32:
            raise ConfigError('need at least one line and images of at least 32x32 pixels')
        if self.image_transport not in ('compressed', 'raw') or self.storage not in ('sqlite3', 'mcap'):
            raise ConfigError('image_transport is compressed|raw and storage is sqlite3|mcap')

    @property
    def gsd_m(self) -> float:
        return self.altitude_m / self.focal_px

    @property
    def line_spacing_m(self) -> float:
        return self.width_px * self.gsd_m * (1.0 - self.side_overlap)

    def camera(self) -> PinholeCamera:
        return PinholeCamera(self.width_px, self.height_px, self.focal_px, self.focal_px * 1.0005,
                             (self.width_px - 1) / 2 + 0.7, (self.height_px - 1) / 2 - 1.3, tuple(self.dist))


PRESETS = {
    # The flight shipped in bags/: three lines, RTK fixed, a few MB.
    'sample': dict(fps=1.0, jpeg_quality=85),
    # A short flight for fast tests.
    'tiny': dict(n_lines=2, line_length_m=40.0, n_gcp=4, n_check=2, n_buildings=3),
    # The benchmark survey of the issues: 5 fps, longer lines.
    'survey': dict(fps=5.0, n_lines=4, line_length_m=150.0, n_buildings=10),
}


def preset(name: str, **overrides) -> SimConfig:
    if name not in PRESETS:
        raise ConfigError(f'unknown preset {name!r}; choose from {sorted(PRESETS)}')
    cfg = SimConfig(**{**PRESETS[name], **overrides})
    cfg.validate()
    return cfg


def build_world(cfg: SimConfig, rng: np.random.Generator):
    """Terrain with targets, for the area the flight covers plus a margin."""
    plan = SurveyPlan(cfg.altitude_m, cfg.line_length_m, cfg.line_spacing_m, cfg.n_lines, cfg.speed_mps,
                      cfg.turn_speed_mps, cfg.heading_deg, (0.0, 0.0), cfg.repeats)
    flight = LawnmowerFlight(plan, rng, cfg.gimbal_jitter_deg, 2.0, cfg.camera_tilt_deg)
    ts = np.linspace(0, flight.duration_s, 400)
    xy = np.array([flight.state(t).pos_enu[:2] for t in ts])
    foot = 0.5 * np.hypot(cfg.width_px, cfg.height_px) * cfg.gsd_m * 1.3 + cfg.altitude_m * np.tan(
        np.radians(abs(cfg.camera_tilt_deg)))
    x0, x1 = xy[:, 0].min() - foot, xy[:, 0].max() + foot
    y0, y1 = xy[:, 1].min() - foot, xy[:, 1].max() + foot
    # Targets within the area imaged by the survey lines (not the turns).
    half_w = 0.5 * cfg.width_px * cfg.gsd_m
    lines_x = [flight.line_endpoints(k)[0] for k in range(cfg.n_lines)]
    lx = np.array([p[0] for p in lines_x])
    ly = np.array([p[1] for p in lines_x] + [flight.line_endpoints(k)[1][1] for k in range(cfg.n_lines)])
    area = (lx.min() - 0.6 * half_w, lx.max() + 0.6 * half_w, ly.min(), ly.max())
    layout = layout_targets(rng, area, cfg.n_gcp, cfg.n_check, margin_m=cfg.target_size_m * 2)
    dem, buildings = make_dem(rng, x0, y0, x1 - x0, y1 - y0, cfg.dem_res_m, cfg.relief_m, cfg.n_buildings,
                              keep_clear=[(x, y) for _, _, x, y in layout])
    pad_m = cfg.target_size_m * 0.9
    heights = [level_ground(dem, x, y, pad_m) for _, _, x, y in layout]
    tex_res = cfg.tex_res_m or cfg.gsd_m / 2.5
    texture = make_texture(rng, dem, buildings, tex_res)
    targets = []
    for k, ((name, role, x, y), z) in enumerate(zip(layout, heights)):
        draw_marker(texture, k, x, y, cfg.target_size_m)
        targets.append(Target(name, k, role, np.array([x, y, z]), marker_corners_enu(x, y, z, cfg.target_size_m),
                              cfg.target_size_m))
    return flight, Terrain(dem, texture, buildings), targets


def _frame_times(cfg: SimConfig, duration_s: float, rng: np.random.Generator):
    n = int(np.floor(duration_s * cfg.fps)) + 1
    times = np.arange(n) / cfg.fps
    keep = np.ones(n, dtype=bool)
    if cfg.drop_fraction > 0:
        keep &= rng.random(n) >= cfg.drop_fraction
    for t0, t1 in cfg.frame_gaps:
        keep &= ~((times >= t0) & (times < t1))
    return times, keep


def _gain_at(cfg: SimConfig, t: float) -> float:
    g = 1.0 + 0.05 * np.sin(2 * np.pi * t / 37.0)   # slow auto-exposure drift
    for tj, gain in sorted(cfg.exposure_jumps):
        if t >= tj:
            g *= gain
    return float(g)


def simulate(cfg: SimConfig, out_dir: str | Path, progress=None) -> GroundTruth:
    """Simulate the flight described by `cfg` into the bag folder `out_dir` (must not exist)."""
    from photogram_ros import msgs
    from photogram_ros.io.bag import BagWriter
    from sensor_msgs.msg import NavSatFix, NavSatStatus

    cfg.validate()
    out_dir = Path(out_dir)
    if out_dir.exists():
        raise ConfigError(f'{out_dir} exists already: choose a new output folder or delete it')
    rng = np.random.default_rng(cfg.seed)
    flight, terrain, targets = build_world(cfg, rng)
    camera = cfg.camera()
    renderer = Renderer(terrain, camera)
    frame = LocalFrame(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_h_m)
    clock = AutopilotClock(boot_unix_s=START_UNIX_S - 95.3)
    link = AutopilotLink(frame, clock, rng)
    gnss = GnssErrorModel(GnssScript(cfg.gnss_mode, list(cfg.gnss_changes), list(cfg.gnss_outages)), rng)
    lever = np.asarray(cfg.lever_arm_frd_m, float)
    duration = flight.duration_s
    focal_mm = cfg.focal_px * 0.003   # a 3 um pixel pitch

    def antenna_at(st):
        return st.pos_enu + flight.body_R(st) @ lever

    # Telemetry for the whole flight (plus a second before and after, like a real log).
    fixes = []
    for t in np.arange(-1.0, duration + 1.0, 1.0):
        link.heartbeat(START_UNIX_S + t)
        link.system_time(START_UNIX_S + t)
    for t in np.arange(-1.0, duration + 1.0, 1.0 / cfg.gps_rate_hz):
        st = flight.state(max(t, 0.0))
        s = gnss.sample(t)
        sent = link.gps(START_UNIX_S + t, antenna_at(st), st.vel_enu, s)
        if 'lat_deg' in sent:
            sent['error_enu_m'] = s.error_enu_m.tolist()
        sent['antenna_enu'] = antenna_at(st).tolist()
        fixes.append(sent)
        link.global_position(START_UNIX_S + t, st.pos_enu + (s.error_enu_m if s.mode.fix_type >= 2 else 0),
                             st.vel_enu, st.yaw_rad, cfg.origin_h_m)
    for t in np.arange(-1.0, duration + 1.0, 0.1):
        st = flight.state(max(t, 0.0))
        link.attitude(START_UNIX_S + t, st.roll_rad, st.pitch_rad, st.yaw_rad,
                      ned_R_frd_from_euler(st.roll_rad, st.pitch_rad, st.yaw_rad))

    times, keep = _frame_times(cfg, duration, rng)
    black_idx = {int(round(t * cfg.fps)) for t in cfg.black_frames}
    frames = []
    bag_msgs = []  # (stamp_ns, topic, msg)
    photos = []
    for k, t in enumerate(times):
        st = flight.state(float(t))
        map_T_cam = make_T(st.map_R_cam, st.pos_enu)
        stamp_ns = int(round((START_UNIX_S + t) * 1e9))
        frames.append(FrameTruth(k, stamp_ns, map_T_cam, antenna_at(st), bool(keep[k]), k in black_idx))
        link.camera_trigger(START_UNIX_S + t, st.pos_enu,
                            np.degrees([st.roll_rad, st.pitch_rad, st.yaw_rad]), cfg.origin_h_m, focal_mm)
        if not keep[k]:
            continue
        if k in black_idx:
            img = np.zeros((cfg.height_px, cfg.width_px, 3), np.uint8)
        else:
            img = renderer.render(map_T_cam, Exposure(gain=_gain_at(cfg, t), noise_dn=cfg.noise_dn), rng)
        arrive_ns = stamp_ns + 30_000_000
        if cfg.image_transport == 'compressed':
            bag_msgs.append((arrive_ns, TOPIC_IMAGE_COMPRESSED,
                             msgs.compressed_image_msg(img, stamp_ns, quality=cfg.jpeg_quality)))
        else:
            bag_msgs.append((arrive_ns, TOPIC_IMAGE_RAW, msgs.image_msg(img, stamp_ns)))
        bag_msgs.append((arrive_ns, TOPIC_CAMERA_INFO, msgs.camera_info_msg(camera, stamp_ns)))
        if cfg.photos or cfg.ppk or cfg.rtk_photos:
            photos.append((k, img, st))
        if progress:
            progress(k + 1, len(times))

    packets = link.sorted_packets()
    packets = _corrupt(packets, cfg.mavlink_corruption, rng)
    for p in packets:
        bag_msgs.append((int(p.t_unix_s * 1e9), TOPIC_MAVLINK, msgs.bytes_msg(p.data)))
    for fx in fixes:
        if 'lat_deg' not in fx:
            continue   # outage: a real driver publishes nothing usable, the topic simply pauses
        status = NavSatStatus.STATUS_GBAS_FIX if fx['fix_type'] >= 4 else NavSatStatus.STATUS_FIX
        stamp_ns = int(round(fx['t_fix_unix_s'] * 1e9))
        var = [fx['h_acc_m'] ** 2, fx['h_acc_m'] ** 2, fx['v_acc_m'] ** 2]
        bag_msgs.append((stamp_ns + 70_000_000, TOPIC_FIX,
                         msgs.navsatfix_msg(stamp_ns, fx['lat_deg'], fx['lon_deg'], fx['h_m'], status, var,
                                            NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN)))
    bag_msgs.sort(key=lambda m: m[0])
    with BagWriter(out_dir, storage=cfg.storage) as bag:
        for stamp_ns, topic, msg in bag_msgs:
            bag.write(topic, stamp_ns, msg)
    write_tlog(out_dir / 'flight.tlog', packets)

    truth = GroundTruth(origin=frame, crs=f'EPSG:{utm_epsg(frame.lat_deg, frame.lon_deg)}', camera=camera,
                        frames=frames, targets=targets, dem=terrain.dem, gsd_m=cfg.gsd_m, lever_arm_frd_m=lever,
                        fixes=fixes, config=_config_dict(cfg), geoid_model=geoid.MODEL_NAME)
    truth.save(out_dir)
    write_targets_file(out_dir, truth)
    if cfg.photos:
        from photogram_ros.sim.photos import write_photos
        write_photos(out_dir / 'photos', photos, truth, cfg)
    if cfg.ppk:
        from photogram_ros.sim.photos import write_ppk
        write_ppk(out_dir / 'ppk', photos, truth, cfg,
                  lambda t_unix: antenna_at(flight.state(max(t_unix - START_UNIX_S, 0.0))))
    if cfg.rtk_photos:
        from photogram_ros.sim.photos import write_rtk_photos
        write_rtk_photos(out_dir / 'rtk', photos, truth, cfg)
    return truth


def _config_dict(cfg: SimConfig) -> dict:
    d = asdict(cfg)
    return json.loads(json.dumps(d))


def _corrupt(packets, intervals, rng):
    """Flip, drop and insert bytes in packets sent during the given intervals (faulty links)."""
    if not intervals:
        return packets
    from photogram_ros.sim.autopilot import Packet
    out = []
    for p in packets:
        t = p.t_unix_s - START_UNIX_S
        if any(t0 <= t < t1 for t0, t1 in intervals):
            b = bytearray(p.data)
            r = rng.random()
            if r < 0.4:
                i = int(rng.integers(len(b)))
                b[i] ^= int(rng.integers(1, 256))
            elif r < 0.6:
                b = b[: int(rng.integers(1, len(b)))]
            elif r < 0.8:
                b = bytes(rng.integers(0, 256, int(rng.integers(1, 20)), dtype=np.uint8)) + bytes(b)
            out.append(Packet(p.t_unix_s, bytes(b), p.name + '(corrupted)'))
        else:
            out.append(p)
    return out
