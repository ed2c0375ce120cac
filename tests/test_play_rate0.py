"""`photogram-ros play --rate 0` keeps up with an ordinary subscriber in another process.

The subscriber is what a user writes: rclpy, reliable, KEEP_LAST 1000, a plain callback, started before
the player. Before, the player published the 11,865 IMU messages of the real Husky bag in about a
second, before discovery had even matched the subscriber (it got 0 to 2,659 of them); now it waits
for the match and paces by acknowledgement windows, and every message arrives, in order.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from conftest import ROOT, shared_data

pytestmark = pytest.mark.ros

SUBSCRIBER = r'''
import json, sys, time
import rclpy
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu
out, ready, depth, expected, timeout = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
rclpy.init()
node = rclpy.create_node('ordinary_imu_subscriber')
got = []
qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)
node.create_subscription(Imu, '/imu/data', lambda m: got.append(
    [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, m.linear_acceleration.z]), qos)
open(ready, 'w').close()
deadline = time.monotonic() + timeout
while time.monotonic() < deadline and len(got) < expected:
    rclpy.spin_once(node, timeout_sec=0.1)
json.dump(got, open(out, 'w'))
node.destroy_node()
rclpy.shutdown()
'''


def _bag_imu(bag) -> list:
    from photogram_ros.io.bag import BagReader, deserialize
    with BagReader(bag) as r:
        return [[m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, m.linear_acceleration.z]
                for m in (deserialize(x.msgtype, x.data) for x in r.messages(['/imu/data']))]


def test_play_rate0_delivers_every_message_to_a_keep_last_subscriber(tmp_path):
    bag = shared_data('bags', 'husky_gps_imu_sqlite3')
    expected = _bag_imu(bag)
    assert len(expected) == 11_865
    out, ready = tmp_path / 'got.json', tmp_path / 'ready'
    sub = subprocess.Popen([sys.executable, '-c', SUBSCRIBER, str(out), str(ready), '1000', str(len(expected)), '240'],
                           cwd=ROOT)
    try:
        deadline = time.monotonic() + 60
        while not ready.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert ready.exists(), 'the subscriber did not start'
        # All three topics of the bag: the two nobody subscribes to are played too, without waiting on them.
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'play', str(bag), '--rate', '0'], cwd=ROOT,
                           capture_output=True, text=True, timeout=300)
        wall = time.monotonic() - t0
        assert r.returncode == 0, r.stdout + r.stderr
        sub.wait(timeout=120)
    finally:
        if sub.poll() is None:
            sub.kill()
    print(r.stdout, f'(command {wall:.1f} s)')
    assert '/imu/data: 11865 messages' in r.stdout and '1 subscribers' in r.stdout
    assert '/fix: 989 messages' in r.stdout
    got = json.loads(out.read_text())
    assert len(got) == len(expected), f'{len(got)} of {len(expected)} messages arrived'
    assert got == expected    # every message, in the bag's order
