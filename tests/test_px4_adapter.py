"""PX4 uXRCE-DDS inputs: SensorGps and VehicleAttitude become the gps/fix, gps/fix_type and mavlink/attitude that
mavlink_node publishes (ellipsoidal height, per-axis variances, RTK fix types kept; FLU body in ENU, on the UNIX
clock through the fixes' UTC times). px4_msgs is not among the PyPI wheels: the node runs here on stand-in
message classes with px4_msgs' fields, and without px4_msgs it stops with the reason."""

from __future__ import annotations

import sys
import types
from dataclasses import dataclass, field

import numpy as np
import pytest

from photogram_ros.core.rotations import R_from_quat


@dataclass
class SensorGps:        # px4_msgs/msg/SensorGps (1.15+) fields the adapter reads
    timestamp: int = 0
    time_utc_usec: int = 0
    latitude_deg: float = 0.0
    longitude_deg: float = 0.0
    altitude_msl_m: float = 0.0
    altitude_ellipsoid_m: float = 0.0
    eph: float = 0.0
    epv: float = 0.0
    fix_type: int = 0


@dataclass
class SensorGpsOld:     # px4_msgs before 1.15: 1e-7 degrees and millimetres
    timestamp: int = 0
    time_utc_usec: int = 0
    lat: int = 0
    lon: int = 0
    alt_ellipsoid: int = 0
    eph: float = 0.0
    epv: float = 0.0
    fix_type: int = 0


@dataclass
class VehicleAttitude:
    timestamp: int = 0
    q: list = field(default_factory=lambda: [1.0, 0.0, 0.0, 0.0])


def test_sensor_gps_fields_to_a_fix():
    from photogram_ros.core.px4 import fix_from_sensor_gps
    new = fix_from_sensor_gps(SensorGps(5_000_000, 1_781_000_000_123_456, 47.3977, 8.5456, 440.0, 488.0, 0.02,
                                        0.03, 6))
    old = fix_from_sensor_gps(SensorGpsOld(5_000_000, 1_781_000_000_123_456, 473977000, 85456000, 488000, 0.02,
                                           0.03, 6))
    for f in (new, old):
        assert f['lat_deg'] == pytest.approx(47.3977) and f['lon_deg'] == pytest.approx(8.5456)
        assert f['h_m'] == pytest.approx(488.0)            # the ellipsoidal one, never the MSL altitude
        assert f['stamp_ns'] == 1_781_000_000_123_456_000 and f['fix_type'] == 6 and f['status'] == 2
        assert f['var_enu_m2'] == pytest.approx([0.0004, 0.0004, 0.0009])
    assert fix_from_sensor_gps(SensorGps(fix_type=1, latitude_deg=47.0, longitude_deg=8.0)) is None
    assert fix_from_sensor_gps(SensorGps(fix_type=5, latitude_deg=47.0, longitude_deg=8.0, eph=0.0))['var_enu_m2'] \
        is None
    assert fix_from_sensor_gps(SensorGps(fix_type=3, latitude_deg=47.0, longitude_deg=8.0))['status'] == 0


@pytest.mark.parametrize('yaw_deg, pitch_deg', [(0.0, 0.0), (90.0, 0.0), (30.0, 10.0)])
def test_ned_frd_attitude_to_enu_flu(yaw_deg, pitch_deg):
    from scipy.spatial.transform import Rotation
    from photogram_ros.core.px4 import enu_flu_from_ned_frd
    # PX4: yaw from north towards east, pitch nose up, as an NED/FRD (z-y-x) rotation.
    ned = Rotation.from_euler('ZYX', [yaw_deg, pitch_deg, 0.0], degrees=True).as_quat()      # x, y, z, w
    q = enu_flu_from_ned_frd([ned[3], ned[0], ned[1], ned[2]])
    R = R_from_quat(q)
    nose = R[:, 0]           # FLU x in ENU
    heading = np.degrees(np.arctan2(nose[0], nose[1]))      # from north towards east
    assert heading == pytest.approx(yaw_deg, abs=1e-6)
    assert np.degrees(np.arcsin(nose[2])) == pytest.approx(pitch_deg, abs=1e-6)    # nose up: +z in ENU
    assert R[2, 1] == pytest.approx(0.0, abs=1e-9) and R[:, 2][2] > 0    # no roll: left level, top up


def test_clock_from_the_fixes_utc_times():
    from photogram_ros.core.px4 import Px4Clock
    c = Px4Clock()
    assert c.unix_ns(1_000) is None
    c.update(5_000_000, 1_781_000_000_000_000)
    assert c.unix_ns(5_500_000) == 1_781_000_000_500_000_000


@pytest.mark.ros
def test_adapter_node_publishes_what_mavlink_node_does(rclpy_context, monkeypatch):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import Imu, NavSatFix
    from std_msgs.msg import UInt8
    from photogram_ros.errors import ConfigError
    from photogram_ros.nodes import px4_adapter
    with pytest.raises(ConfigError, match='px4_msgs'):
        px4_adapter.px4_message_types()
    # px4_msgs stands in: std_msgs types carry the messages over DDS, the adapter's callbacks get px4's fields.
    from std_msgs.msg import Empty
    monkeypatch.setitem(sys.modules, 'px4_msgs', types.ModuleType('px4_msgs'))
    monkeypatch.setitem(sys.modules, 'px4_msgs.msg', types.SimpleNamespace(SensorGps=Empty, VehicleAttitude=Empty))
    node = px4_adapter.Px4Adapter(namespace='/drone1', context=rclpy_context)
    probe = Node('probe', context=rclpy_context)
    got = {'fix': [], 'type': [], 'att': []}
    probe.create_subscription(NavSatFix, '/drone1/gps/fix', got['fix'].append, 10)
    probe.create_subscription(UInt8, '/drone1/gps/fix_type', got['type'].append, 10)
    probe.create_subscription(Imu, '/drone1/mavlink/attitude', got['att'].append, 10)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(probe)
    try:
        import time
        end = time.monotonic() + 10
        while time.monotonic() < end and not (got['fix'] and got['att']):
            node.on_attitude(VehicleAttitude(4_000_000))            # before any UTC time: not published
            node.on_gps(SensorGps(5_000_000, 1_781_000_000_000_000, 47.3977, 8.5456, 440.0, 488.0, 0.02, 0.03, 5))
            node.on_attitude(VehicleAttitude(5_250_000, [1.0, 0.0, 0.0, 0.0]))
            ex.spin_once(timeout_sec=0.1)
        fix, att = got['fix'][0], got['att'][0]
        assert got['type'][0].data == 5 and fix.status.status == 2 and fix.altitude == pytest.approx(488.0)
        assert fix.header.stamp.sec == 1_781_000_000 and fix.position_covariance[8] == pytest.approx(0.0009)
        assert att.header.stamp.sec == 1_781_000_000 and att.header.stamp.nanosec == 250_000_000
        # Level, nose north (PX4's identity) is FLU with x north in ENU: a yaw of +90 degrees.
        R = R_from_quat([att.orientation.x, att.orientation.y, att.orientation.z, att.orientation.w])
        assert R[:, 0] == pytest.approx([0.0, 1.0, 0.0], abs=1e-9)
        assert node.diag.counts()['attitudes_before_utc'] >= 1
    finally:
        probe.destroy_node()
        node.destroy_node()
