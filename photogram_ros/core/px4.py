"""PX4's uXRCE-DDS messages as photogram_ros takes them (ROS-free: fields in, numbers out).

- px4_msgs/SensorGps (/fmu/out/vehicle_gps_position): latitude/longitude in degrees (px4_msgs 1.15+:
  latitude_deg, longitude_deg, altitude_ellipsoid_m; before: lat, lon in 1e-7 degrees, alt_ellipsoid in mm),
  eph/epv in metres (1-sigma accuracy the receiver reports), fix_type numbered as MAVLink's GPS_FIX_TYPE,
  time_utc_usec the fix's UTC time, timestamp microseconds since PX4 booted.
- px4_msgs/VehicleAttitude (/fmu/out/vehicle_attitude): q = (w, x, y, z), the FRD body in the NED earth
  frame, timestamp microseconds since boot.

Out: the fix with its ellipsoidal height (REP-145), ENU variances and NavSatStatus (core/gnss_fix.py's
mapping: RTK float/fixed -> GBAS), and the attitude as FLU body in ENU (REP-103), what mavlink_node publishes.
`Px4Clock` puts PX4's boot clock on the UNIX clock from the fixes' UTC times.
"""

from __future__ import annotations

import numpy as np

from photogram_ros.core import gnss_fix as gf
from photogram_ros.core.rotations import R_from_quat, quat_from_R

ENU_R_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
FRD_R_FLU = np.diag([1.0, -1.0, -1.0])


def _field(msg, *names, scale: float = 1.0):
    for n in names:
        v = getattr(msg, n, None)
        if v is not None:
            return float(v) * scale
    return None


def fix_from_sensor_gps(msg) -> dict | None:
    """A SensorGps (any object with its fields) -> {'stamp_ns' (UTC, None when the receiver gave no time),
    'lat_deg', 'lon_deg', 'h_m' (ellipsoidal), 'var_enu_m2' (or None), 'fix_type', 'status'}; None without
    a position (fix type 0-1)."""
    fix_type = int(getattr(msg, 'fix_type', 0))
    lat = _field(msg, 'latitude_deg') if hasattr(msg, 'latitude_deg') else _field(msg, 'lat', scale=1e-7)
    lon = _field(msg, 'longitude_deg') if hasattr(msg, 'longitude_deg') else _field(msg, 'lon', scale=1e-7)
    h = (_field(msg, 'altitude_ellipsoid_m') if hasattr(msg, 'altitude_ellipsoid_m')
         else _field(msg, 'alt_ellipsoid', scale=1e-3))
    if fix_type < gf.FIX_2D or lat is None or lon is None or h is None or not np.isfinite([lat, lon, h]).all():
        return None
    eph, epv = _field(msg, 'eph'), _field(msg, 'epv')
    var = None
    if eph is not None and epv is not None and eph > 0 and epv > 0 and np.isfinite([eph, epv]).all():
        var = [eph ** 2, eph ** 2, epv ** 2]      # per-axis 1-sigma, as mavlink_node takes GPS_RAW_INT's h_acc
    utc = int(getattr(msg, 'time_utc_usec', 0) or 0)
    return {'stamp_ns': utc * 1000 if utc > 0 else None, 'lat_deg': lat, 'lon_deg': lon, 'h_m': h,
            'var_enu_m2': var, 'fix_type': fix_type, 'status': gf.navsat_status(fix_type)}


def enu_flu_from_ned_frd(q_wxyz) -> np.ndarray:
    """PX4's attitude quaternion (w, x, y, z: FRD body in NED) -> (x, y, z, w): FLU body in ENU (REP-103)."""
    w, x, y, z = (float(v) for v in q_wxyz)
    ned_R_frd = R_from_quat([x, y, z, w])
    return quat_from_R(ENU_R_NED @ ned_R_frd @ FRD_R_FLU)


class Px4Clock:
    """PX4's boot clock (timestamp, microseconds) on the UNIX clock: the offset of the latest fix that carried
    a UTC time (time_utc_usec - timestamp)."""

    def __init__(self):
        self.offset_us: int | None = None

    def update(self, boot_us: int, utc_us: int) -> None:
        if boot_us > 0 and utc_us > 0:
            self.offset_us = int(utc_us) - int(boot_us)

    def unix_ns(self, boot_us: int) -> int | None:
        return None if self.offset_us is None or boot_us <= 0 else (int(boot_us) + self.offset_us) * 1000
