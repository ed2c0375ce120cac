"""What the simulated flight controller sends: real MAVLink 2 packets, encoded with pymavlink.

The autopilot's clock counts from its boot and drifts slightly against UNIX time; GPS_RAW_INT
and GLOBAL_POSITION_INT carry boot time (as ArduPilot and PX4 do), SYSTEM_TIME pairs boot and UNIX
time, CAMERA_FEEDBACK carries the UNIX time of each exposure. Every packet also gets a link
latency, so consumers must use the timestamps inside the messages, not the arrival times.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from photogram_ros.core import geoid
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.rotations import ENU_R_NED, quat_from_R
from photogram_ros.sim.gnss import FIX_RTK_FLOAT, GnssSample

AUTOPILOT_SYSID = 1
AUTOPILOT_COMPID = mavlink2.MAV_COMP_ID_AUTOPILOT1
GIMBAL_COMPID = mavlink2.MAV_COMP_ID_GIMBAL


@dataclass
class Packet:
    t_unix_s: float      # when the packet reaches the companion computer
    data: bytes
    name: str


@dataclass
class AutopilotClock:
    boot_unix_s: float
    drift_ppm: float = 5.0

    def boot_s(self, t_unix_s: float) -> float:
        return (t_unix_s - self.boot_unix_s) * (1.0 + self.drift_ppm * 1e-6)


class AutopilotLink:
    """Encodes messages from one vehicle (autopilot and gimbal components) into timed packets."""

    def __init__(self, frame: LocalFrame, clock: AutopilotClock, rng: np.random.Generator,
                 base_station_enu_m=(400.0, -300.0, -20.0)):
        self.frame = frame
        self.clock = clock
        self.rng = rng
        self.base_enu = np.asarray(base_station_enu_m, float)
        self._ap = mavlink2.MAVLink(None, srcSystem=AUTOPILOT_SYSID, srcComponent=AUTOPILOT_COMPID)
        self._gimbal = mavlink2.MAVLink(None, srcSystem=AUTOPILOT_SYSID, srcComponent=GIMBAL_COMPID)
        self._queued = []   # (t_send, t_arrive, sender, message): packed in send order at the end
        self._img_idx = 0

    def _emit(self, mav, msg, t_send_unix_s: float) -> None:
        latency = 0.004 + self.rng.exponential(0.003)
        self._queued.append((t_send_unix_s, t_send_unix_s + latency, mav, msg))

    def _boot_ms(self, t: float) -> int:
        return int(self.clock.boot_s(t) * 1000.0)

    def _boot_us(self, t: float) -> int:
        return int(self.clock.boot_s(t) * 1e6)

    def heartbeat(self, t: float) -> None:
        self._emit(self._ap, self._ap.heartbeat_encode(
            mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
            mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink2.MAV_MODE_FLAG_SAFETY_ARMED,
            3, mavlink2.MAV_STATE_ACTIVE), t)
        self._emit(self._gimbal, self._gimbal.heartbeat_encode(
            mavlink2.MAV_TYPE_GIMBAL, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, mavlink2.MAV_STATE_ACTIVE), t)

    def system_time(self, t: float) -> None:
        self._emit(self._ap, self._ap.system_time_encode(int(t * 1e6), self._boot_ms(t)), t)
        # Autopilot-initiated time sync request (tc1 = 0), as ArduPilot sends it.
        self._emit(self._ap, self._ap.timesync_encode(0, int(self.clock.boot_s(t) * 1e9)), t)

    def _geodetic(self, enu):
        lat, lon, h = self.frame.enu_to_geodetic(np.asarray(enu, float))
        return float(lat), float(lon), float(h)

    def gps(self, t_fix: float, antenna_enu: np.ndarray, vel_enu: np.ndarray, s: GnssSample,
            latency_s: float = 0.06) -> dict:
        """GPS_RAW_INT (+ GPS_RTK in RTK modes) for a fix measured at `t_fix`; returns what was sent."""
        mode = s.mode
        sent = {'t_fix_unix_s': t_fix, 'mode': mode.name, 'fix_type': mode.fix_type, 'sats': s.sats}
        if mode.fix_type < 2:
            msg = self._ap.gps_raw_int_encode(self._boot_us(t_fix), mode.fix_type, 0, 0, 0, 9999, 9999,
                                              0, 0, s.sats, 0, 0, 0, 0, 0, 0)
            self._emit(self._ap, msg, t_fix + latency_s)
            return sent
        meas = antenna_enu + s.error_enu_m
        lat, lon, h = self._geodetic(meas)
        n_geoid = float(geoid.undulation_m(lat, lon))
        speed = float(np.hypot(vel_enu[0], vel_enu[1]))
        cog = (np.degrees(np.arctan2(vel_enu[0], vel_enu[1])) + 360.0) % 360.0
        msg = self._ap.gps_raw_int_encode(
            self._boot_us(t_fix), mode.fix_type, int(round(lat * 1e7)), int(round(lon * 1e7)),
            int(round((h - n_geoid) * 1000)), int(mode.hdop * 100), int(mode.hdop * 150),
            int(speed * 100), int(cog * 100) % 36000, s.sats,
            int(round(h * 1000)), max(int(round(mode.h_acc_m * 1000)), 1),
            max(int(round(mode.v_acc_m * 1000)), 1), 5, 0, 0)
        self._emit(self._ap, msg, t_fix + latency_s)
        if mode.fix_type >= FIX_RTK_FLOAT:
            base_ned = ENU_R_NED.T @ (meas - self.base_enu)
            tow_ms = int((t_fix - 315964800.0 + 18.0) * 1000) % (7 * 86400 * 1000)
            wn = int((t_fix - 315964800.0 + 18.0) // (7 * 86400))
            rtk = self._ap.gps_rtk_encode(
                self._boot_ms(t_fix), 0, wn, tow_ms, 1 if mode.fix_type == 6 else 0, 1, s.sats,
                1, int(base_ned[0] * 1000), int(base_ned[1] * 1000), int(base_ned[2] * 1000),
                int(mode.h_acc_m * 1000), 1 if mode.fix_type == 6 else 12)
            self._emit(self._ap, rtk, t_fix + latency_s + 0.002)
        sent.update({'lat_deg': lat, 'lon_deg': lon, 'h_m': h, 'alt_msl_m': h - n_geoid,
                     'h_acc_m': mode.h_acc_m, 'v_acc_m': mode.v_acc_m})
        return sent

    def global_position(self, t: float, pos_enu: np.ndarray, vel_enu: np.ndarray, yaw_ned_rad: float,
                        home_h_m: float) -> None:
        lat, lon, h = self._geodetic(pos_enu)
        msl = h - float(geoid.undulation_m(lat, lon))
        vn, ve, vd = vel_enu[1], vel_enu[0], -vel_enu[2]
        hdg = int(((np.degrees(yaw_ned_rad) + 360.0) % 360.0) * 100)
        self._emit(self._ap, self._ap.global_position_int_encode(
            self._boot_ms(t), int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(msl * 1000)),
            int(round((h - home_h_m) * 1000)), int(vn * 100), int(ve * 100), int(vd * 100), hdg), t + 0.01)

    def attitude(self, t: float, roll: float, pitch: float, yaw: float, ned_R_frd: np.ndarray) -> None:
        yaw_wrapped = float(np.arctan2(np.sin(yaw), np.cos(yaw)))
        self._emit(self._ap, self._ap.attitude_encode(self._boot_ms(t), roll, pitch, yaw_wrapped, 0, 0, 0),
                   t + 0.005)
        x, y, z, w = quat_from_R(ned_R_frd)
        self._emit(self._ap, self._ap.attitude_quaternion_encode(self._boot_ms(t), w, x, y, z, 0, 0, 0),
                   t + 0.005)

    def camera_trigger(self, t: float, pos_enu: np.ndarray, cam_rpy_deg, home_h_m: float,
                       focal_mm: float) -> int:
        lat, lon, h = self._geodetic(pos_enu)
        msl = h - float(geoid.undulation_m(lat, lon))
        idx = self._img_idx
        self._img_idx += 1
        self._emit(self._ap, self._ap.camera_trigger_encode(int(t * 1e6), idx), t + 0.002)
        self._emit(self._ap, self._ap.camera_feedback_encode(
            int(t * 1e6), 0, 0, idx, int(round(lat * 1e7)), int(round(lon * 1e7)), float(msl),
            float(h - home_h_m), float(cam_rpy_deg[0]), float(cam_rpy_deg[1]), float(cam_rpy_deg[2]),
            float(focal_mm), 0, idx + 1), t + 0.02)
        return idx

    def sorted_packets(self) -> list[Packet]:
        """Packets in arrival order, with sequence numbers counted in send order as a real link does."""
        packets, last = [], -np.inf
        for t_send, t_arrive, mav, msg in sorted(self._queued, key=lambda q: q[0]):
            data = msg.pack(mav)
            mav.seq = (mav.seq + 1) % 256
            last = max(t_arrive, last + 1e-6)   # a serial link delays packets but never reorders them
            packets.append(Packet(last, data, msg.get_type()))
        return packets


def write_tlog(path, packets: list[Packet]) -> None:
    """Mission Planner .tlog: each packet preceded by its big-endian UNIX time in microseconds."""
    with open(path, 'wb') as f:
        for p in packets:
            f.write(struct.pack('>Q', int(p.t_unix_s * 1e6)))
            f.write(p.data)
