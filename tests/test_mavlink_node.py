"""The MAVLink node over real transports: UDP on loopback with a subscriber in another process, bag bytes."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from helpers.processes import reaped
from photogram_ros.io.mavlink import read_tlog
from test_mavlink_parse import sample_dir  # noqa: F401  (fixture)

SUBSCRIBER = r'''
import json, sys, time
import rclpy
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import NavSatFix
from std_msgs.msg import UInt8
out, want, timeout = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
rclpy.init()
node = rclpy.create_node('fix_listener')
fixes, types = [], []
qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE)
node.create_subscription(NavSatFix, '/gps/fix', lambda m: fixes.append(
    [m.header.stamp.sec, m.header.stamp.nanosec, m.latitude, m.longitude, m.altitude, m.status.status,
     m.position_covariance_type, list(m.position_covariance)]), qos)
node.create_subscription(UInt8, '/gps/fix_type', lambda m: types.append(m.data), qos)
print('ready', flush=True)
deadline = time.monotonic() + timeout
while time.monotonic() < deadline and len(fixes) < want:
    rclpy.spin_once(node, timeout_sec=0.1)
with open(out, 'w') as f:
    json.dump({'fixes': fixes, 'types': types}, f)
node.destroy_node()
rclpy.shutdown()
'''


def _free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(('127.0.0.1', 0))
    port = s.getsockname()[1]
    s.close()
    return port


def _spin(node, ctx, stop):
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.05)
    ex.remove_node(node)


def test_udp_loopback_to_subscriber_in_another_process(rclpy_context, sample_dir, tmp_path):  # noqa: F811
    from photogram_ros.nodes.mavlink_node import MavlinkNode
    from photogram_ros.sim.truth import GroundTruth
    gt = GroundTruth.load(sample_dir)
    want = len(gt.fixes)
    out = tmp_path / 'fixes.json'
    sub = subprocess.Popen([sys.executable, '-c', SUBSCRIBER, str(out), str(want), '60'],
                           stdout=subprocess.PIPE, env=dict(os.environ))
    stop = threading.Event()
    node = spinner = None
    try:
        with reaped(sub):
            assert sub.stdout.readline().strip() == b'ready'
            port = _free_udp_port()
            node = MavlinkNode({'url': f'udpin:127.0.0.1:{port}'}, context=rclpy_context)
            spinner = threading.Thread(target=_spin, args=(node, rclpy_context, stop), daemon=True)
            spinner.start()
            deadline = time.monotonic() + 20
            while node.pub_fix.get_subscription_count() < 1 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert node.pub_fix.get_subscription_count() >= 1, 'subscriber never matched'
            # Stream the flight's packets as the autopilot would, 20x faster than recorded.
            msgs, _ = read_tlog(sample_dir / 'flight.tlog')
            tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            t0, wall0 = msgs[0][1], time.monotonic()
            for m, t in msgs:
                delay = wall0 + (t - t0) / 20.0 - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                tx.sendto(bytes(m._msgbuf), ('127.0.0.1', port))
            tx.close()
            sub.wait(timeout=60)
    finally:
        stop.set()
        if spinner is not None:
            spinner.join(timeout=5)
        if node is not None:
            node.destroy_node()
    got = json.loads(out.read_text())
    fixes = got['fixes']
    assert len(fixes) >= 0.98 * want, f'{len(fixes)} of {want} fixes arrived'
    assert set(got['types']) == {6}                   # RTK fixed, kept in full on /gps/fix_type
    t_truth = np.array([f['t_fix_unix_s'] for f in gt.fixes])
    for sec, nsec, lat, lon, h, status, ctype, cov in fixes:
        t = sec + nsec * 1e-9
        k = int(np.argmin(np.abs(t_truth - t)))
        tr = gt.fixes[k]
        assert abs(t - tr['t_fix_unix_s']) < 0.001    # stamped at the fix epoch, not on arrival
        assert abs(lat - tr['lat_deg']) < 1e-7 and abs(lon - tr['lon_deg']) < 1e-7
        assert abs(h - tr['h_m']) < 0.002             # ellipsoidal height (REP-145)
        assert status == 2 and ctype == 2             # GBAS_FIX, DIAGONAL_KNOWN
        assert cov[0] == pytest.approx(tr['h_acc_m'] ** 2, rel=0.1) and cov[8] == pytest.approx(tr['v_acc_m'] ** 2,
                                                                                                  rel=0.1)


def test_bag_bytes_with_damage_and_diagnostics(rclpy_context, sample_dir):  # noqa: F811
    """Raw packets on /mavlink/from_fcu, a stretch of them damaged: the node keeps going and reports it."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu, NavSatFix
    from std_msgs.msg import UInt8MultiArray

    from photogram_ros import msgs as pm
    from photogram_ros.nodes.mavlink_node import MavlinkNode
    import rclpy

    msgs, _ = read_tlog(sample_dir / 'flight.tlog')
    rng = np.random.default_rng(3)
    packets = []
    for k, (m, _) in enumerate(msgs):
        b = bytearray(m._msgbuf)
        if 1000 <= k < 1300 and rng.random() < 0.5:       # a bad stretch of link
            b[int(rng.integers(len(b)))] ^= 0x5A
            if rng.random() < 0.3:
                b = bytearray(rng.integers(0, 256, 30, dtype=np.uint8).tobytes()) + b
        packets.append(bytes(b))

    node = MavlinkNode({'diagnostics_period_s': 0.2}, context=rclpy_context)
    helper = rclpy.create_node('bag_bytes', context=rclpy_context)
    qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
    pub = helper.create_publisher(UInt8MultiArray, '/mavlink/from_fcu', qos)
    fixes, att, diags = [], [], []
    helper.create_subscription(NavSatFix, '/gps/fix', fixes.append, qos)
    helper.create_subscription(Imu, '/mavlink/attitude', att.append, qos)
    helper.create_subscription(DiagnosticArray, '/diagnostics', diags.append, 10)
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(helper)
    try:
        deadline = time.monotonic() + 10
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        for b in packets:
            pub.publish(pm.bytes_msg(b))
            for _ in range(3):
                ex.spin_once(timeout_sec=0.0)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and (node.stream.stats.bytes_in < sum(map(len, packets))
                                               or len(fixes) < node.published['fix']):
            ex.spin_once(timeout_sec=0.05)
        t_end = time.monotonic() + 0.6
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
    finally:
        ex.shutdown()
        helper.destroy_node()
        node.destroy_node()
    st = node.stream.stats
    assert st.crc_errors > 50 and st.junk_bytes > 0
    gps_total = sum(1 for m, _ in msgs if m.get_type() == 'GPS_RAW_INT')
    assert 0.8 * gps_total < len(fixes) < gps_total     # the damaged stretch cost some fixes, not the rest
    assert len(att) > 600
    stamps = np.array([pm.ns_from_time(f.header.stamp) for f in fixes])
    assert np.all(np.diff(stamps) > 0)
    kv = {v.key: v.value for d in diags for s in d.status for v in s.values}
    assert int(kv['link_crc_errors']) == st.crc_errors or int(kv['link_crc_errors']) > 0
    assert kv['fix_type'] == 'RTK_FIXED' and kv['time_sync_synced'] == 'True'


def _gps_stream(mav, n=10, t0_boot=50.0, lat0=471000000):
    out = []
    for k in range(n):
        boot = t0_boot + 0.2 * k
        if k % 5 == 0:
            out.append(mav.system_time_encode(int((1_700_000_000 + boot) * 1e6), int(boot * 1000)))
        out.append(mav.gps_raw_int_encode(int(boot * 1e6), 6, lat0 + k, 85000000, 500000, 60, 90, 0, 0, 20,
                                          547000, 15, 25))
    return b''.join(m.pack(mav) for m in out)


def test_node_signing_only_correctly_signed_used(rclpy_context):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    from photogram_ros.io.mavlink import signing_key
    from photogram_ros.nodes.mavlink_node import MavlinkNode

    def signed(key, sysid):
        mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.timestamp = key, True, 1
        return mav
    good = _gps_stream(signed(signing_key('fleet secret'), 1), lat0=471000000)
    forged = _gps_stream(signed(signing_key('guess'), 1), t0_boot=52.0, lat0=461000000)
    plain = _gps_stream(mavlink2.MAVLink(None, srcSystem=1, srcComponent=1), t0_boot=54.0, lat0=451000000)
    node = MavlinkNode({'signing_key': 'fleet secret', 'diagnostics_period_s': 0.1}, context=rclpy_context)
    try:
        for chunk in (good, forged, plain):
            node.feed(chunk, None)
        node._update_diagnostics()
        st = node.stream.stats
        assert node.published['fix'] == 10                       # only the correctly signed fixes
        assert st.signature_rejected == 12 and st.unsigned_rejected == 12
        assert [f.lat_deg for f in node.ingest.latest.values()] == [pytest.approx(47.1000009)]
        status = node.diag.status()
        kv = {v.key: v.value for v in status.values}
        assert kv['link_signature_rejected'] == '12' and kv['link_unsigned_rejected'] == '12'
    finally:
        node.destroy_node()


def test_link_drops_and_comes_back(rclpy_context):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    from photogram_ros.nodes.mavlink_node import MavlinkNode
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    node = MavlinkNode({'link_timeout_s': 1.0}, context=rclpy_context)
    try:
        node.feed(_gps_stream(mav, 10, 50.0), None)
        node._update_diagnostics()
        assert {v.key: v.value for v in node.diag.status().values}['link_state'] == 'up'
        time.sleep(1.2)
        node._update_diagnostics()
        st = node.diag.status()
        assert {v.key: v.value for v in st.values}['link_state'] == 'down' and 'link lost' in st.message
        node.feed(b'\x00garbage\xfd\x09' + _gps_stream(mav, 10, 52.0), None)
        node._update_diagnostics()
        assert {v.key: v.value for v in node.diag.status().values}['link_state'] == 'up'
        assert node.published['fix'] == 20 and node.stream.stats.seq_lost == 0
    finally:
        node.destroy_node()


def test_tlog_url_as_fast_as_possible(rclpy_context, sample_dir):  # noqa: F811
    from photogram_ros.nodes.mavlink_node import MavlinkNode
    node = MavlinkNode({'url': str(sample_dir / 'flight.tlog'), 'tlog_rate': 0.0}, context=rclpy_context)
    try:
        assert node.input_done.wait(30)
        assert node.published == {'fix': 389, 'attitude': 778, 'trigger': 76}
        assert node.stream.stats.packets == 3185 and node.stream.stats.crc_errors == 0
    finally:
        node.destroy_node()
