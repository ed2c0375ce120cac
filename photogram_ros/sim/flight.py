"""The survey flight: a lawnmower pattern with turns, attitude jitter and a gimbal-held camera.

Positions are in the `map` ENU frame (m), times in seconds from the start of the survey. The body
frame is FRD and its attitude is aerospace roll/pitch/yaw in NED (what MAVLink reports); the camera
hangs in a gimbal that holds it near nadir (or at a set tilt) with residual jitter, its image top
pointing along the direction of flight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photogram_ros.core.rotations import ENU_R_NED, ned_R_frd_from_euler, rot_x, rot_y, rot_z

G_MPS2 = 9.81


@dataclass
class SurveyPlan:
    altitude_m: float          # above the map origin
    line_length_m: float
    line_spacing_m: float
    n_lines: int
    speed_mps: float
    turn_speed_mps: float
    heading_deg: float = 0.0   # direction of the first line, clockwise from north
    start_enu: tuple = (0.0, 0.0)
    repeats: int = 1           # fly the whole pattern this many times (long-flight tests)


@dataclass
class FlightState:
    t_s: float
    pos_enu: np.ndarray        # body/camera reference point, m
    vel_enu: np.ndarray        # m/s
    roll_rad: float            # body attitude, aerospace convention
    pitch_rad: float
    yaw_rad: float             # NED yaw, clockwise from north
    map_R_cam: np.ndarray      # optical camera to map
    on_line: bool              # False during turns


class _Jitter:
    """Smooth random angle: a sum of sinusoids with random phases (stationary, deterministic)."""

    def __init__(self, rng: np.random.Generator, sigma_rad: float, periods_s=(1.3, 2.9, 6.1, 13.0)):
        self.freqs = 2 * np.pi / np.asarray(periods_s)
        self.phases = rng.uniform(0, 2 * np.pi, len(periods_s))
        self.amp = sigma_rad * np.sqrt(2.0 / len(periods_s))

    def __call__(self, t: float) -> float:
        return float(self.amp * np.sum(np.sin(self.freqs * t + self.phases)))


class LawnmowerFlight:
    """Piecewise path of straight lines and semicircular turns flown at constant speeds."""

    def __init__(self, plan: SurveyPlan, rng: np.random.Generator, gimbal_jitter_deg: float = 0.5,
                 body_jitter_deg: float = 2.0, camera_tilt_deg: float = 0.0):
        self.plan = plan
        self.tilt_rad = np.radians(camera_tilt_deg)
        self._gj = [_Jitter(rng, np.radians(gimbal_jitter_deg)) for _ in range(3)]
        self._bj = [_Jitter(rng, np.radians(body_jitter_deg)) for _ in range(3)]
        h = np.radians(plan.heading_deg)
        self._along = np.array([np.sin(h), np.cos(h)])      # ENU unit vector of line 1
        self._across = np.array([np.cos(h), -np.sin(h)])    # to the right of line 1
        # Segments: (kind, duration_s, data)
        self.segments = []
        r = plan.line_spacing_m / 2
        for rep in range(plan.repeats):
            for k in range(plan.n_lines):
                self.segments.append(('line', plan.line_length_m / plan.speed_mps, (rep, k)))
                last = (k == plan.n_lines - 1)
                if last and rep == plan.repeats - 1:
                    break
                if last:  # fly back to the start: a straight transit across the lines
                    dist = plan.line_spacing_m * (plan.n_lines - 1)
                    self.segments.append(('return', dist / plan.speed_mps, (rep, k)))
                else:
                    self.segments.append(('turn', np.pi * r / plan.turn_speed_mps, (rep, k)))
        self._starts = np.concatenate([[0.0], np.cumsum([s[1] for s in self.segments])])

    @property
    def duration_s(self) -> float:
        return float(self._starts[-1])

    def line_endpoints(self, k: int):
        p0 = np.asarray(self.plan.start_enu, float) + self._across * self.plan.line_spacing_m * k
        p1 = p0 + self._along * self.plan.line_length_m
        return (p0, p1) if k % 2 == 0 else (p1, p0)

    def _xy_vel(self, t: float):
        i = int(np.clip(np.searchsorted(self._starts, t, side='right') - 1, 0, len(self.segments) - 1))
        kind, dur, (rep, k) = self.segments[i]
        tau = min(max(t - self._starts[i], 0.0), dur)
        if kind == 'line':
            a, b = self.line_endpoints(k)
            d = (b - a) / np.linalg.norm(b - a)
            return a + d * self.plan.speed_mps * tau, d * self.plan.speed_mps, True, 0.0
        if kind == 'return':
            a = self.line_endpoints(k)[1]
            b = self.line_endpoints(0)[0]
            d = (b - a) / np.linalg.norm(b - a)
            return a + d * self.plan.speed_mps * tau, d * self.plan.speed_mps, False, 0.0
        # Semicircle from the end of line k to the start of line k+1.
        a = self.line_endpoints(k)[1]
        b = self.line_endpoints(k + 1)[0]
        centre = (a + b) / 2
        r = self.plan.line_spacing_m / 2
        u0 = (a - centre) / r
        d_in = self._along if k % 2 == 0 else -self._along
        # Turn direction: from u0 toward d_in first.
        sign = 1.0 if (u0[0] * d_in[1] - u0[1] * d_in[0]) > 0 else -1.0
        ang = sign * self.plan.turn_speed_mps * tau / r
        c, s = np.cos(ang), np.sin(ang)
        u = np.array([c * u0[0] - s * u0[1], s * u0[0] + c * u0[1]])
        tangent = sign * np.array([-u[1], u[0]])
        centripetal = sign * self.plan.turn_speed_mps ** 2 / r
        return centre + r * u, tangent * self.plan.turn_speed_mps, False, centripetal

    def state(self, t: float) -> FlightState:
        xy, vxy, on_line, centripetal = self._xy_vel(t)
        pos = np.array([xy[0], xy[1], self.plan.altitude_m])
        vel = np.array([vxy[0], vxy[1], 0.0])
        course_enu = np.arctan2(vxy[1], vxy[0])       # CCW from east
        yaw_ned = np.pi / 2 - course_enu                # CW from north
        # A multirotor leans into turns (coordinated) and slightly nose-down when cruising.
        roll = np.arctan2(centripetal, G_MPS2) + self._bj[0](t)
        pitch = -np.radians(1.0) * np.linalg.norm(vxy) + self._bj[1](t)
        yaw = yaw_ned + 0.3 * self._bj[2](t)
        # Gimbal: camera image top along the course, z down (nadir), then tilt and jitter.
        fwd = np.array([np.cos(course_enu), np.sin(course_enu), 0.0])
        right = np.array([np.sin(course_enu), -np.cos(course_enu), 0.0])
        map_R_cam_nadir = np.column_stack([right, -fwd, [0.0, 0.0, -1.0]])
        # rot_x(+a) swings the optical axis toward the image top, i.e. forward.
        map_R_cam = (map_R_cam_nadir @ rot_x(self.tilt_rad + self._gj[0](t)) @ rot_y(self._gj[1](t))
                     @ rot_z(self._gj[2](t)))
        return FlightState(t, pos, vel, float(roll), float(pitch), float(yaw), map_R_cam, on_line)

    def body_R(self, st: FlightState) -> np.ndarray:
        """Body FRD -> map ENU rotation."""
        return ENU_R_NED @ ned_R_frd_from_euler(st.roll_rad, st.pitch_rad, st.yaw_rad)
