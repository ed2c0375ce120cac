"""Writes this folder's recordings of the sample flight's autopilot topics (see README.md).

The sample flight (bags/sample_flight) records raw MAVLink. Its fixes (best receiver) and attitudes, as
mavlink_node decodes them, are written here as the two other autopilot interfaces publish them, each message at
the bag time of the MAVLink chunk that completed it (so the recordings line up with the sample bag's camera
frames):

- `mavros_sample_flight/`: /mavros/global_position/raw/fix (sensor_msgs/NavSatFix, ellipsoidal height, status
  FIX for every 3D fix, RTK too, as MAVROS marks it; frame base_link) and /mavros/imu/data (sensor_msgs/Imu, base_link
  FLU in ENU, MAVROS's convention; stamped on the UNIX clock as MAVROS stamps with a time sync to the FCU).
- `px4_sample_flight/`: /fmu/out/vehicle_gps_position (px4_msgs/SensorGps) and /fmu/out/vehicle_attitude
  (px4_msgs/VehicleAttitude, NED/FRD), PX4 v1.15's fields (photogram_ros/io/px4_msgs), on a boot clock 60 s before
  the bag's start, UTC time in each SensorGps.

Camera frames are not stored (they are the sample bag's): tests/test_eco_autopilot_replay.py joins them with a
recording here into one bag and replays it. MCAP, zstd chunks. Run from the repository root:
`PYTHONPATH=$PWD:$PWD/tests .venv/bin/python tests/data/autopilot/make_autopilot_bags.py`. Deterministic in
content (the MCAP files hold no write time).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

HERE = Path(__file__).parent
ROOT = HERE.parents[2]
SAMPLE_BAG = ROOT / 'bags' / 'sample_flight'

MAVROS_FIX = '/mavros/global_position/raw/fix'
MAVROS_IMU = '/mavros/imu/data'
MAVROS_ATTITUDE_SIGMA_RAD = 0.01       # MAVROS's imu/data orientation covariance is the FCU's; a plain 0.6 deg here


def write_mavros(out: Path) -> dict:
    from sensor_msgs.msg import NavSatFix, NavSatStatus
    from test_house_px4_replay import _px4_flight

    from photogram_ros import msgs
    from photogram_ros.io.bag import BagWriter, serialize
    from photogram_ros.io.mavlink_ingest import Attitude
    counts = {MAVROS_FIX: 0, MAVROS_IMU: 0}
    var = (MAVROS_ATTITUDE_SIGMA_RAD ** 2,) * 3
    with BagWriter(out, storage='mcap') as w:
        w.add_topic(MAVROS_FIX, 'sensor_msgs/msg/NavSatFix')
        w.add_topic(MAVROS_IMU, 'sensor_msgs/msg/Imu')
        for bag_ns, ev in _px4_flight(SAMPLE_BAG):
            stamp_ns = int(round(ev.t_s * 1e9))
            if isinstance(ev, Attitude):
                msg = msgs.imu_orientation_msg(stamp_ns, ev.q_enu_flu_xyzw, var, frame_id='base_link')
                w.write_raw(MAVROS_IMU, bag_ns, serialize(msg))
                counts[MAVROS_IMU] += 1
                continue
            msg = msgs.navsatfix_msg(stamp_ns, ev.lat_deg, ev.lon_deg, ev.h_m, NavSatStatus.STATUS_FIX,
                                     ev.var_enu_m2, NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN, 'base_link')
            w.write_raw(MAVROS_FIX, bag_ns, serialize(msg))
            counts[MAVROS_FIX] += 1
    return counts


def write_px4(out: Path, scratch: Path) -> dict:
    """The PX4 records of tests/test_house_px4_replay.py's bag, without its camera topics."""
    from test_house_px4_replay import _px4_bag

    from photogram_ros.io.bag import BagReader, BagWriter
    from photogram_ros.io.bag_px4 import px4_topics
    counts = _px4_bag(SAMPLE_BAG, scratch)
    with BagReader(scratch) as r, BagWriter(out, storage='mcap') as w:
        px4 = px4_topics(r.topics())
        for topic, msgtype in sorted(px4.items()):
            w.add_topic(topic, msgtype, msgdef=r.message_definition(topic))
        for m in r.messages(sorted(px4)):
            w.write_raw(m.topic, m.stamp_ns, m.data)
    return counts


def main() -> int:
    import tempfile
    for name in ('mavros_sample_flight', 'px4_sample_flight'):
        shutil.rmtree(HERE / name, ignore_errors=True)
    print('mavros:', write_mavros(HERE / 'mavros_sample_flight'))
    with tempfile.TemporaryDirectory() as tmp:
        print('px4:', write_px4(HERE / 'px4_sample_flight', Path(tmp) / 'px4_full'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
