"""Tracker core on simulator frames with ground truth (no ROS).

Frames are rendered directly with the simulator at 320x240 (same overlap per frame as 640x480 at
the same fps, four times cheaper to render). Track truth: a track's first keyframe observation is
intersected with the true terrain (the renderer's ground points) and that 3D point is projected
with the true camera pose into every later keyframe that observes the track.
"""

from __future__ import annotations

import numpy as np
import pytest

from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.core.keyframes import FixBuffer
from photogram_ros.core.rotations import invert_T, make_T, transform_points
from photogram_ros.core.tracker import FEATURE_DTYPE, Tracker, TrackerParams
from photogram_ros.errors import CalibrationError

SIZE = dict(width_px=320, height_px=240, focal_px=260.0)


class SimFrames:
    """Rendered frames of a tiny survey plus what is needed to check tracks against the truth."""

    def __init__(self, t_end_s: float, fps: float = 2.0, **faults):
        from photogram_ros.sim.render import Exposure, Renderer
        from photogram_ros.sim.scenario import _frame_times, _gain_at, build_world, preset
        self.cfg = cfg = preset('tiny', fps=fps, line_length_m=60.0, **SIZE, **faults)
        rng = np.random.default_rng(cfg.seed)
        self.flight, terrain, _ = build_world(cfg, rng)
        self.camera = cfg.camera()
        self.renderer = Renderer(terrain, self.camera)
        times, keep = _frame_times(cfg, t_end_s, rng)
        black = {int(round(t * fps)) for t in cfg.black_frames}
        self.frames = []   # (stamp_ns, image, map_T_cam)
        self.poses = {}
        for k, t in enumerate(times):
            st = self.flight.state(float(t))
            T = make_T(st.map_R_cam, st.pos_enu)
            stamp = int(round(t * 1e9)) + 1_000_000_000
            self.poses[stamp] = T
            if not keep[k]:
                continue
            if k in black:
                img = np.zeros((cfg.height_px, cfg.width_px, 3), np.uint8)
            else:
                img = self.renderer.render(T, Exposure(gain=_gain_at(cfg, t), noise_dn=cfg.noise_dn), rng)
            self.frames.append((stamp, img, T))

    def run(self, params: TrackerParams | None = None, fixes=()):
        tr = Tracker(self.camera, params)
        for f in fixes:
            tr.add_fix(f)
        kfs = []
        for stamp, img, _ in self.frames:
            kfs += tr.process(img, stamp)
        return tr, kfs + tr.flush()

    def ground(self, T, uv):
        """3D terrain points seen at sub-pixel `uv` (NaN across depth discontinuities)."""
        G = self.renderer.ground_points(T)
        w, h = self.camera.width, self.camera.height
        u0 = np.clip(np.floor(uv[:, 0]).astype(int), 0, w - 2)
        v0 = np.clip(np.floor(uv[:, 1]).astype(int), 0, h - 2)
        a, b = (uv[:, 0] - u0)[:, None], (uv[:, 1] - v0)[:, None]
        P = [G[v0, u0], G[v0, u0 + 1], G[v0 + 1, u0], G[v0 + 1, u0 + 1]]
        z = np.stack([p[:, 2] for p in P], 1)
        X = P[0] * (1 - a) * (1 - b) + P[1] * a * (1 - b) + P[2] * (1 - a) * b + P[3] * a * b
        X[~(np.nanmax(z, 1) - np.nanmin(z, 1) < 0.1)] = np.nan
        return X

    def track_errors(self, kfs) -> np.ndarray:
        """Pixel error of every keyframe observation after a track's first one."""
        points, errs = {}, []
        for kf in kfs:
            T = self.poses[kf.stamp_ns]
            obs = kf.observations
            first = np.array([int(t) not in points for t in obs['track_id']])
            if first.any():
                X = self.ground(T, np.column_stack([obs['u'][first], obs['v'][first]]))
                points.update(zip(obs['track_id'][first].tolist(), X))
            X = np.array([points[int(t)] for t in obs['track_id'][~first]]).reshape(-1, 3)
            uv, _ = self.camera.project(transform_points(invert_T(T), X))
            e = np.linalg.norm(uv - np.column_stack([obs['u'][~first], obs['v'][~first]]), axis=1)
            errs.append(e[np.isfinite(e)])
        return np.concatenate(errs)

    def true_overlap(self, kf_a, kf_b) -> float:
        G = self.renderer.ground_points(self.poses[kf_a.stamp_ns])[::4, ::4].reshape(-1, 3)
        uv, ok = self.camera.project(transform_points(invert_T(self.poses[kf_b.stamp_ns]), G))
        return float(np.mean(ok & self.camera.in_image(uv)))


@pytest.fixture(scope='module')
def survey_line():
    return SimFrames(12.0)     # the first 60 m survey line, 25 frames


@pytest.fixture(scope='module')
def faulty_flight():
    # 5 % drops, two 2-s gaps, a black frame, an exposure jump, and the 180-degree turn at 12-23 s.
    return SimFrames(26.0, drop_fraction=0.05, frame_gaps=[(3.0, 5.0), (15.0, 17.0)], black_frames=[8.0],
                     exposure_jumps=[(10.0, 1.8)], seed=11)


def test_track_accuracy_against_truth(survey_line):
    tr, kfs = survey_line.run()
    e = survey_line.track_errors(kfs)
    print(f'{len(e)} observations: median {np.median(e):.3f} px, > 2 px {np.mean(e > 2) * 100:.2f} %, '
          f'p95 {np.percentile(e, 95):.3f} px; {tr.stats.process_s / tr.stats.frames * 1e3:.1f} ms/frame')
    assert len(e) > 1000
    assert np.median(e) <= 0.3
    assert np.mean(e > 2.0) <= 0.01
    assert tr.stats.breaks == 0


def test_features_spread_over_the_grid(survey_line):
    _, kfs = survey_line.run()
    obs = kfs[0].observations
    assert obs.dtype == FEATURE_DTYPE
    cells = np.unique((obs['u'] // 40).astype(int) * 8 + (obs['v'] // 40).astype(int))
    assert len(cells) >= 0.9 * 8 * 6, 'features must cover (almost) every grid cell'
    # xn, yn are the undistorted normalized coordinates of u, v.
    xn = survey_line.camera.pixel_to_normalized(np.column_stack([obs['u'], obs['v']]))
    assert np.allclose(xn, np.column_stack([obs['xn'], obs['yn']]), atol=1e-9)
    assert len(np.unique(obs['track_id'])) == len(obs)


def test_keyframe_overlap_on_target_over_the_line(survey_line):
    for target in (0.8, 0.6):
        _, kfs = survey_line.run(TrackerParams(keyframe_overlap=target))
        true = [survey_line.true_overlap(a, b) for a, b in zip(kfs[:-1], kfs[1:])]
        print(f'target {target}: {len(kfs)} keyframes, true overlaps {np.round(true, 3).tolist()}, '
              f'estimated {np.round([k.overlap for k in kfs[1:]], 3).tolist()}')
        assert len(kfs) >= (3 if target < 0.7 else 6)
        assert np.max(np.abs(np.array(true[:-1]) - target)) <= 0.05
        # The last keyframe is the end of the stream's flush, never beyond the target.
        assert true[-1] >= target - 0.05


def test_faulty_flight_keeps_keyframes_and_graph_connected(faulty_flight):
    tr, kfs = faulty_flight.run()
    s = tr.stats
    print(f'{len(faulty_flight.frames)} frames: {s}')
    print([(k.index, round(k.overlap, 2), k.break_before, k.bridged, len(k.observations)) for k in kfs])
    assert s.unusable >= 1 and s.gaps >= 2
    assert len(kfs) >= 8
    # Connected: every keyframe shares tracks with its predecessor, or the break is reported (and bridged).
    for a, b in zip(kfs[:-1], kfs[1:]):
        shared = len(np.intersect1d(a.observations['track_id'], b.observations['track_id']))
        assert shared >= 20 or (b.break_before and not b.bridged), (a.index, b.index, shared)
    unbridged = [k for k in kfs if k.break_before and not k.bridged]
    assert not unbridged, 'every break in this flight is bridgeable by descriptor matching'
    e = faulty_flight.track_errors(kfs)
    print(f'faulty flight: median {np.median(e):.3f} px, > 2 px {np.mean(e > 2) * 100:.2f} %')
    assert np.median(e) <= 0.3 and np.mean(e > 2.0) <= 0.01
    # Keyframes keep coming after each fault (gaps at 3-5 s and 15-17 s, black frame at 8 s).
    t_kf = np.array([(k.stamp_ns - 1_000_000_000) * 1e-9 for k in kfs])
    for t_fault in (5.0, 8.0, 10.0, 17.0):
        assert np.any((t_kf > t_fault) & (t_kf < t_fault + 4.0)), t_fault


def test_break_without_any_overlap_is_reported_unbridged(survey_line):
    frames = survey_line.frames
    tr = Tracker(survey_line.camera)
    kfs = []
    for stamp, img, _ in frames[:4]:
        kfs += tr.process(img, stamp)
    # Jump to a view that shares nothing with the last keyframe (an upside-down noise image).
    rng = np.random.default_rng(0)
    noise = np.clip(rng.normal(128, 40, frames[0][1].shape), 0, 255).astype(np.uint8)
    kfs += tr.process(noise, frames[4][0]) + tr.flush()
    assert tr.stats.breaks == 1 and tr.stats.bridged == 0
    assert kfs[-1].break_before and not kfs[-1].bridged


def test_keyframe_gets_interpolated_fix(survey_line):
    fixes = [GnssFix(47.0 + k * 1e-6, 8.0, 500.0 + k, np.eye(3) * 0.01, 1_000_000_000 + k * 200_000_000, 2)
             for k in range(0, 70)]
    _, kfs = survey_line.run(fixes=fixes)
    for kf in kfs:
        w = (kf.stamp_ns - 1_000_000_000) / 200_000_000
        assert kf.fix is not None
        assert abs(kf.fix.lat_deg - (47.0 + w * 1e-6)) < 1e-12 and abs(kf.fix.h_m - (500 + w)) < 1e-9


def _fed_with_lagging_fixes(frames, speed: float, stop_s: float | None = None, params=None,
                            replay_rate: float | None = None):
    """Frames with the fixes (5 Hz from the first frame on) handed to the tracker at `speed` times real time,
    as a GNSS stream decoded late under load falls behind; none after `stop_s` (an outage). With
    `replay_rate` the frames come at that many times real time and the tracker is given that clock (a
    node's receive clock in a fast replay); without, it waits on the frame stamps."""
    t0 = frames.frames[0][0]
    stamps = [t0 + k * 200_000_000 for k in range(0, 70)]
    fixes = [GnssFix(47.0 + k * 1e-6, 8.0, 500.0, np.eye(3) * 0.01, s, 2) for k, s in enumerate(stamps)
             if stop_s is None or s < t0 + stop_s * 1e9]
    tr, kfs, given = Tracker(frames.camera, params), [], 0
    for stamp, img, _ in frames.frames:
        while given < len(fixes) and t0 + (fixes[given].stamp_ns - t0) / speed <= stamp:
            tr.add_fix(fixes[given])
            given += 1
        clock = None if replay_rate is None else t0 + int((stamp - t0) / replay_rate)
        kfs += tr.process(img, stamp, clock_ns=clock)
    return kfs


def test_keyframes_wait_for_a_lagging_fix_stream(survey_line):
    # Fixes decoded at 0.6x real time fall up to 4.8 s behind the frames (more than fix_wait_s) but keep
    # coming: every keyframe released in the stream waits for its own fix instead of going without one.
    kfs = _fed_with_lagging_fixes(survey_line, speed=0.6)
    assert len(kfs) >= 4
    assert all(kf.fix is not None and kf.fix.stamp_ns == kf.stamp_ns for kf in kfs), \
        [(kf.index, kf.fix is not None) for kf in kfs]
    # Bounded: a lag beyond fix_lag_max_s releases them without.
    kfs = _fed_with_lagging_fixes(survey_line, speed=0.6, params=TrackerParams(fix_lag_max_s=2.0))
    assert any(kf.fix is None for kf in kfs)


def test_fix_waits_are_measured_on_the_clock_the_tracker_is_given(survey_line):
    # A replay at 4x real time whose fixes are delivered at 0.6x the frames' pace: 4.8 s of stream behind
    # at the end, 1.2 s of the node's clock. Waits on the frame stamps give up (fix_lag_max_s 2 s); waits
    # on the clock keep every keyframe's fix.
    slow = TrackerParams(fix_lag_max_s=2.0)
    kfs = _fed_with_lagging_fixes(survey_line, speed=0.6, params=slow)
    assert any(kf.fix is None for kf in kfs)
    kfs = _fed_with_lagging_fixes(survey_line, speed=0.6, params=slow, replay_rate=4.0)
    assert len(kfs) >= 4 and all(kf.fix is not None and kf.fix.stamp_ns == kf.stamp_ns for kf in kfs), \
        [(kf.index, kf.fix is not None) for kf in kfs]
    # An outage is still one on that clock: after fix_wait_s of it without a new fix, keyframes go on
    # without (in the stream, not held to its end).
    kfs = _fed_with_lagging_fixes(survey_line, speed=1.0, stop_s=2.0, params=TrackerParams(fix_wait_s=0.5),
                                  replay_rate=2.0)
    late = [kf for kf in kfs if kf.stamp_ns > survey_line.frames[0][0] + 2.2e9]
    assert late and all(kf.fix is None for kf in late)


def test_keyframes_do_not_wait_through_a_gnss_outage(survey_line):
    # The fix stream stops at 4 s (an outage): the keyframes after it go without a fix once fix_wait_s
    # has passed, not after fix_lag_max_s.
    kfs = _fed_with_lagging_fixes(survey_line, speed=1.0, stop_s=4.0)
    late = [kf for kf in kfs if kf.stamp_ns > survey_line.frames[0][0] + 4.2e9]
    assert late and all(kf.fix is None for kf in late)
    last_stamp = survey_line.frames[-1][0]
    assert any(last_stamp - kf.stamp_ns < 6e9 for kf in late)    # released in the stream, not held to its end


def test_fix_buffer_refuses_to_bridge_outages():
    buf = FixBuffer(max_gap_s=1.0)
    buf.add(GnssFix(47.0, 8.0, 500.0, np.eye(3), 0, 2))
    buf.add(GnssFix(47.1, 8.0, 500.0, np.eye(3), 3_000_000_000, 2))
    assert buf.at(1_000_000_000) is None and buf.at(-5) is None
    buf.add(GnssFix(47.05, 8.0, 500.0, np.eye(3) * 4, 500_000_000, 2))
    f = buf.at(250_000_000)
    assert f.interpolated and abs(f.lat_deg - 47.025) < 1e-12 and f.cov_enu_m2[0, 0] == 4 and f.stamp_ns == 250_000_000


def test_calibration_problems_are_errors(survey_line):
    tr = Tracker(None)
    img = survey_line.frames[0][1]
    with pytest.raises(CalibrationError, match='no camera calibration'):
        tr.process(img, 1)
    tr.set_camera(survey_line.camera.scaled(2.0))
    with pytest.raises(CalibrationError, match='calibration is for 640x480'):
        tr.process(img, 1)
    tr.set_camera(survey_line.camera)
    tr.process(img, 1)
    assert tr.stats.keyframes == 1


def test_gps_distance_drives_keyframes_when_the_fix_is_good(survey_line):
    from photogram_ros.core.geodesy import LocalFrame
    cfg = survey_line.cfg
    origin = LocalFrame(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_h_m)
    fixes = []
    for t in np.arange(0.0, 12.6, 0.2):
        lat, lon, h = origin.enu_to_geodetic(survey_line.flight.state(t).pos_enu)
        fixes.append(GnssFix(float(lat), float(lon), float(h), np.eye(3) * 1e-4, int(round(t * 1e9)) + 1_000_000_000,
                             2))
    G = survey_line.renderer.ground_points(survey_line.frames[0][2])
    ground_m = float(cfg.altitude_m - np.nanmedian(G[..., 2]))
    params = TrackerParams(overlap_source='gps', ground_distance_m=ground_m)
    _, kfs = survey_line.run(params, fixes)
    true = [survey_line.true_overlap(a, b) for a, b in zip(kfs[:-1], kfs[1:])]
    print(f'GPS-driven: true overlaps {np.round(true, 3).tolist()}')
    assert len(kfs) >= 6 and np.max(np.abs(np.array(true[:-1]) - 0.8)) <= 0.05
    # A poor fix (sigma 3 m) is not trusted: the image estimate takes over and still holds the target.
    bad = [GnssFix(f.lat_deg + 2e-5, f.lon_deg, f.h_m, np.eye(3) * 9.0, f.stamp_ns, 1) for f in fixes]
    _, kfs = survey_line.run(params, bad)
    true = [survey_line.true_overlap(a, b) for a, b in zip(kfs[:-1], kfs[1:])]
    assert np.max(np.abs(np.array(true[:-1]) - 0.8)) <= 0.05
