"""Keyframe observations straight from the simulator truth (no images, no tracker).

Ground points on the true DEM are projected into the true camera poses with the true camera model
plus pixel noise; GNSS fixes come from the true antenna position with the receiver error model of
the chosen mode. This is what the triangulation tests and benchmarks feed to the pipeline, so they
measure the adjustment alone, independent of feature tracking.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.core.incremental import ControlPoint, KeyframeRecord, lever_arm_cam_from_frd
from photogram_ros.core.rotations import R_from_rotvec, invert_T, make_T, transform_points
from photogram_ros.sim.gnss import GnssErrorModel, GnssScript
from photogram_ros.sim.scenario import SimConfig, build_world


@dataclass
class SimKeyframes:
    records: list[KeyframeRecord]
    true_map_T_cam: np.ndarray        # (K, 4, 4)
    points_map: np.ndarray            # (P, 3) true ground points; track id = row
    control: list[ControlPoint]       # all targets; role 'gcp' or 'check'
    origin: LocalFrame
    camera: PinholeCamera
    gsd_m: float
    lever_arm_cam_m: np.ndarray
    outlier_tracks: np.ndarray        # ids of the corrupted tracks


def simulate_keyframes(cfg: SimConfig, keyframe_interval_s: float = 1.0, points_per_image: int = 300,
                       pixel_sigma: float = 0.3, gnss_mode: str | None = None, outlier_fraction: float = 0.0,
                       detect_prob: float = 0.9, repeats_time_s: float | None = None,
                       gcp_sigma_m=(0.01, 0.01, 0.02), attitude_sigma_deg: float | None = 0.3, world=None) -> SimKeyframes:
    """`attitude_sigma_deg`: noise of the autopilot attitude used for the antenna offset; None
    leaves the offset out (the pipeline then uses the fixed camera-frame lever arm). `world`: the
    (flight, terrain, targets) of `build_world(cfg, default_rng(cfg.seed))`, to skip rebuilding it."""
    flight, terrain, targets = world if world is not None else build_world(cfg, np.random.default_rng(cfg.seed))
    # Observations draw from their own stream, so one world can serve several GNSS/outlier set-ups.
    rng = np.random.default_rng([cfg.seed, 1])
    cam = cfg.camera()
    origin = LocalFrame(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_h_m)
    duration = flight.duration_s if repeats_time_s is None else min(repeats_time_s, flight.duration_s)
    times = np.arange(0.0, duration, keyframe_interval_s)
    xmin, xmax, ymin, ymax = terrain.dem.extent_m
    footprint_m2 = cfg.width_px * cfg.height_px * cfg.gsd_m ** 2
    n_pts = int(points_per_image / 0.85 * (xmax - xmin) * (ymax - ymin) / footprint_m2)
    xy = np.column_stack([rng.uniform(xmin, xmax, n_pts), rng.uniform(ymin, ymax, n_pts)])
    pts = np.column_stack([xy, terrain.height_at(xy[:, 0], xy[:, 1])])
    n_bad = int(round(outlier_fraction * n_pts))
    bad_tracks = rng.choice(n_pts, n_bad, replace=False) if n_bad else np.zeros(0, int)
    is_bad = np.zeros(n_pts, bool)
    is_bad[bad_tracks] = True
    # GNSS errors from their own stream: the same receiver realization whatever the image set-up.
    gnss = GnssErrorModel(GnssScript(gnss_mode or cfg.gnss_mode), np.random.default_rng([cfg.seed, 2]))
    lever = np.asarray(cfg.lever_arm_frd_m, float)
    records, poses = [], []
    for t in times:
        st = flight.state(float(t))
        T = make_T(st.map_R_cam, st.pos_enu)
        poses.append(T)
        pc = transform_points(invert_T(T), pts)
        uv, front = cam.project(pc)
        vis = front & cam.in_image(uv, margin_px=5) & _in_fov(cam, pc) & (rng.random(n_pts) < detect_prob)
        ids = np.flatnonzero(vis)
        obs = uv[ids] + rng.normal(0.0, pixel_sigma, (len(ids), 2))
        # A gross outlier: the track jumped to another feature somewhere in the image.
        jump = is_bad[ids] & (rng.random(len(ids)) < 0.5)
        obs[jump] += rng.uniform(8.0, 60.0, (int(jump.sum()), 1)) * _unit(rng, int(jump.sum()))
        tgt = {}
        for tg in targets:
            tuv, ok = cam.project(transform_points(invert_T(T), tg.center_enu[None]))
            if ok[0] and cam.in_image(tuv, margin_px=20)[0]:
                tgt[tg.name] = tuv[0] + rng.normal(0.0, pixel_sigma, 2)
        s = gnss.sample(float(t))
        antenna = st.pos_enu + flight.body_R(st) @ lever
        lat, lon, h = origin.enu_to_geodetic(antenna + s.error_enu_m)
        cov = np.diag([s.mode.h_acc_m ** 2, s.mode.h_acc_m ** 2, s.mode.v_acc_m ** 2])
        stamp = int(round((1_780_000_000.0 + t) * 1e9))
        offset = None
        if attitude_sigma_deg is not None:
            noise = R_from_rotvec(rng.normal(0.0, np.radians(attitude_sigma_deg), 3))
            offset = noise @ flight.body_R(st) @ lever
        records.append(KeyframeRecord(stamp, ids, obs, GnssFix(float(lat), float(lon), float(h), cov),
                                      f'kf{len(records):04d}', tgt, offset))
    control = [ControlPoint(tg.name, tg.center_enu.copy(), np.asarray(gcp_sigma_m, float), tg.role)
               for tg in targets]
    return SimKeyframes(records, np.array(poses), pts, control, origin, cam, cfg.gsd_m,
                        lever_arm_cam_from_frd(lever), bad_tracks)


def _unit(rng, n):
    a = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([np.cos(a), np.sin(a)])


def in_fov(cam: PinholeCamera, points_cam: np.ndarray) -> np.ndarray:
    """Inside the field of view before distortion: the polynomial folds far-off rays back into the
    image (k1 < 0), and a real lens never sees those points."""
    z = np.where(points_cam[:, 2] > 1e-9, points_cam[:, 2], np.nan)
    u = cam.fx * points_cam[:, 0] / z + cam.cx
    v = cam.fy * points_cam[:, 1] / z + cam.cy
    m = 0.15 * max(cam.width, cam.height)
    return (u > -m) & (u < cam.width + m) & (v > -m) & (v < cam.height + m)


_in_fov = in_fov
