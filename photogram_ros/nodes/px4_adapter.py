"""PX4 uXRCE-DDS adapter: a PX4 flight controller's GNSS fix and attitude onto the topics the mapper takes.

In (px4_msgs, as the uXRCE-DDS agent publishes them; best effort, as PX4 offers them):
  /fmu/out/vehicle_gps_position  px4_msgs/SensorGps
  /fmu/out/vehicle_attitude      px4_msgs/VehicleAttitude
Out (relative names: the drone's namespace prefixes them), as mavlink_node publishes them:
  gps/fix_type      std_msgs/UInt8, the full fix type (5 RTK float, 6 RTK fixed), just before each fix
  gps/fix           sensor_msgs/NavSatFix at the fix's UTC time, ellipsoidal height (REP-145), per-axis
                    variances from eph/epv (DIAGONAL_KNOWN)
  mavlink/attitude  sensor_msgs/Imu, FLU body in ENU (REP-103), stamped on the UNIX clock through the fixes'
                    UTC times (an attitude before the first timed fix is not published)
The conversions are core/px4.py. px4_msgs is not among the PyPI wheels: build it in the workspace
(github.com/PX4/px4_msgs, the branch of your PX4 release); without it the node says so and stops.
MAVROS needs no adapter: remap its topics (docs/nodes.md).
"""

from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass

from rclpy.node import Node
from sensor_msgs.msg import Imu, NavSatFix
from std_msgs.msg import UInt8

from photogram_ros import msgs
from photogram_ros.core.px4 import Px4Clock, enu_flu_from_ned_frd, fix_from_sensor_gps
from photogram_ros.errors import ConfigError
from photogram_ros.nodes import qos
from photogram_ros.nodes.diagnostics import Diagnostics
from photogram_ros.nodes.node_main import run_node
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param


@dataclass
class Px4AdapterParams:
    gps_topic: str = param('/fmu/out/vehicle_gps_position', 'PX4 SensorGps topic')
    attitude_topic: str = param('/fmu/out/vehicle_attitude', 'PX4 VehicleAttitude topic')
    frame_id: str = param('gps', 'frame_id of gps/fix')
    attitude_frame_id: str = param('base_link', 'frame_id of mavlink/attitude')
    attitude_sigma_rp_rad: float = param(0.005, 'Attitude 1-sigma, roll and pitch, rad', min=0.0, max=1.0)
    attitude_sigma_yaw_rad: float = param(0.02, 'Attitude 1-sigma, yaw, rad', min=0.0, max=3.2)


def px4_message_types():
    """(SensorGps, VehicleAttitude) of px4_msgs, imported by name: it is built from source in a PX4 workspace and
    has no rosdep key, so package.xml cannot declare it; ConfigError when it is not there."""
    try:
        module = importlib.import_module('px4_msgs.msg')
        return module.SensorGps, module.VehicleAttitude
    except (ImportError, AttributeError) as exc:
        raise ConfigError('px4_adapter needs px4_msgs (not among the PyPI wheels): build github.com/PX4/px4_msgs '
                          f'in your workspace and source it ({exc})') from exc


def fix_messages(fix: dict, stamp_ns: int, frame_id: str) -> tuple:
    """A fix of core/px4.fix_from_sensor_gps -> (gps/fix_type UInt8, gps/fix NavSatFix), as mavlink_node publishes
    them: per-axis variances from eph/epv (DIAGONAL_KNOWN), UNKNOWN without them."""
    var = fix['var_enu_m2']
    navsat = msgs.navsatfix_msg(stamp_ns, fix['lat_deg'], fix['lon_deg'], fix['h_m'], fix['status'],
                                var if var is not None else [0.0, 0.0, 0.0],
                                NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN if var is not None else
                                NavSatFix.COVARIANCE_TYPE_UNKNOWN, frame_id)
    return UInt8(data=fix['fix_type'] & 0xFF), navsat


def attitude_message(stamp_ns: int, q_enu_flu_xyzw, var_rad2, frame_id: str) -> Imu:
    """An attitude (FLU body in ENU) -> the mavlink/attitude Imu."""
    return msgs.imu_orientation_msg(stamp_ns, q_enu_flu_xyzw, var_rad2, frame_id=frame_id)


class Px4Adapter(Node):
    def __init__(self, overrides: dict | None = None, **node_kwargs):
        super().__init__('px4_adapter', **node_kwargs)
        self.p = declare(self, Px4AdapterParams, overrides)
        self.diag = Diagnostics(self)
        self.clock = Px4Clock()
        sensor_gps, vehicle_attitude = px4_message_types()
        # PX4's uXRCE-DDS topics are best effort; every topic is overridable from the parameters (nodes/qos.py).
        self.pub_fix = qos.publisher(self, NavSatFix, 'gps/fix', qos.reliable(100))
        self.pub_fix_type = qos.publisher(self, UInt8, 'gps/fix_type', qos.reliable(100))
        self.pub_att = qos.publisher(self, Imu, 'mavlink/attitude', qos.reliable(100))
        qos.subscription(self, sensor_gps, self.p.gps_topic, self.on_gps, qos.sensor_data(10))
        qos.subscription(self, vehicle_attitude, self.p.attitude_topic, self.on_attitude, qos.sensor_data(10))
        self._att_var = (self.p.attitude_sigma_rp_rad ** 2, self.p.attitude_sigma_rp_rad ** 2,
                         self.p.attitude_sigma_yaw_rad ** 2)

    def on_gps(self, msg) -> None:
        self.clock.update(int(getattr(msg, 'timestamp', 0)), int(getattr(msg, 'time_utc_usec', 0)))
        fix = fix_from_sensor_gps(msg)
        if fix is None:
            self.diag.count('fixes_without_position')
            return
        stamp = fix['stamp_ns'] if fix['stamp_ns'] is not None else self.get_clock().now().nanoseconds
        fix_type, navsat = fix_messages(fix, stamp, self.p.frame_id)
        self.pub_fix_type.publish(fix_type)
        self.pub_fix.publish(navsat)
        self.diag.count('fixes')

    def on_attitude(self, msg) -> None:
        stamp = self.clock.unix_ns(int(getattr(msg, 'timestamp', 0)))
        if stamp is None:
            self.diag.count('attitudes_before_utc')
            return
        self.pub_att.publish(attitude_message(stamp, enu_flu_from_ned_frd(msg.q), self._att_var,
                                              self.p.attitude_frame_id))
        self.diag.count('attitudes')


def main(argv=None) -> int:
    return run_node(Px4Adapter, argv)


if __name__ == '__main__':
    sys.exit(main())
