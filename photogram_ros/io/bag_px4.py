"""PX4 uXRCE-DDS topics in a recording, read without px4_msgs: SensorGps and VehicleAttitude as fixes and attitudes.

A bag recorded on a PX4 drone (`ros2 bag record /fmu/out/vehicle_gps_position /fmu/out/vehicle_attitude ...`)
holds px4_msgs CDR. px4_msgs has no PyPI wheel, so the rclpy classes are missing here; rosbags reads the
records from the definitions the recording holds (rosbag2 stores them: a bag of any PX4 release reads as it
was recorded), else from those shipped with the package (photogram_ros/io/px4_msgs/*.msg, PX4 v1.15's fields),
registered into its ROS 2 Jazzy type store. `Px4Records` turns each record into what px4_adapter
publishes live, through core/px4.py's conversions: ('fix', stamp_ns, fix dict of fix_from_sensor_gps) and
('attitude', stamp_ns, q_enu_flu_xyzw) on the UNIX clock through the fixes' UTC times (Px4Clock); a record
that cannot be used comes back as ('skipped', stamp_ns, reason).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from photogram_ros.core.px4 import Px4Clock, enu_flu_from_ned_frd, fix_from_sensor_gps
from photogram_ros.errors import BagError

PX4_MSG_DIR = Path(__file__).resolve().parent / 'px4_msgs'
SENSOR_GPS = 'px4_msgs/msg/SensorGps'
VEHICLE_ATTITUDE = 'px4_msgs/msg/VehicleAttitude'
PX4_TYPES = (SENSOR_GPS, VEHICLE_ATTITUDE)
TOPIC_GPS = '/fmu/out/vehicle_gps_position'
TOPIC_ATTITUDE = '/fmu/out/vehicle_attitude'


def px4_msgdef(msgtype: str) -> str:
    """The shipped .msg text of a px4_msgs type ('px4_msgs/msg/SensorGps')."""
    path = PX4_MSG_DIR / f'{msgtype.rsplit("/", 1)[-1]}.msg'
    if msgtype not in PX4_TYPES or not path.is_file():
        raise BagError(f'no shipped definition of {msgtype!r}: photogram_ros reads {list(PX4_TYPES)}')
    return path.read_text()


def _typestore(definitions: tuple):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    for msgtype, text in definitions:
        try:
            store.register(get_types_from_msg(text, msgtype))
        except Exception as exc:   # rosbags' own parse errors
            raise BagError(f'the definition of {msgtype} cannot be read ({exc})') from exc
    return store


@lru_cache(maxsize=1)
def px4_typestore():
    """rosbags' ROS 2 Jazzy type store with SensorGps and VehicleAttitude registered from the shipped definitions."""
    return _typestore(tuple((t, px4_msgdef(t)) for t in PX4_TYPES))


def px4_topics(topics: dict) -> dict:
    """{topic: msgtype} of a bag's topics (BagReader.topics()) that are PX4 messages read here."""
    return {t: i.msgtype for t, i in topics.items() if i.msgtype in PX4_TYPES}


def serialize_px4(msg) -> bytes:
    """A message built from px4_typestore().types -> CDR, as the uXRCE-DDS agent publishes it."""
    return bytes(px4_typestore().serialize_cdr(msg, msg.__msgtype__))


class Px4Records:
    """Recorded PX4 messages (CDR) -> fixes and attitudes, in the order they are fed (see the module docstring).
    `definitions`: msgtype -> the .msg text the bag recorded (BagReader.message_definition), or None."""

    def __init__(self, definitions: dict | None = None):
        self.clock = Px4Clock()
        recorded = {t: d for t, d in (definitions or {}).items() if t in PX4_TYPES and d}
        self.recorded = sorted(recorded)      # the types read from the bag's own definitions
        self.store = (_typestore(tuple((t, recorded.get(t) or px4_msgdef(t)) for t in PX4_TYPES)) if recorded
                      else px4_typestore())

    def read(self, msgtype: str, stamp_ns: int, data: bytes) -> tuple:
        try:
            msg = self.store.deserialize_cdr(data, msgtype)
        except Exception as exc:   # rosbags raises its own errors, or struct/index errors on a record that is short
            return ('skipped', stamp_ns, f'{msgtype} record does not match its definition ({exc})')
        if msgtype == SENSOR_GPS:
            self.clock.update(int(msg.timestamp), int(msg.time_utc_usec))
            fix = fix_from_sensor_gps(msg)
            if fix is None:
                return ('skipped', stamp_ns, 'fix without a position')
            return ('fix', fix['stamp_ns'] if fix['stamp_ns'] is not None else stamp_ns, fix)
        if msgtype == VEHICLE_ATTITUDE:
            stamp = self.clock.unix_ns(int(msg.timestamp))
            if stamp is None:
                return ('skipped', stamp_ns, 'attitude before the first fix with a UTC time')
            return ('attitude', stamp, enu_flu_from_ned_frd(np.asarray(msg.q, float)))
        return ('skipped', stamp_ns, f'{msgtype} is not read')
