"""Runs in its own process: subscribes to topics and writes a key of each message received, in order.

usage: python raw_subscriber.py OUT.json EXPECTED_TOTAL TIMEOUT_S TOPIC:TYPE [TOPIC:TYPE ...]

Once every subscription has matched a publisher (its own side of the DDS match, which can come later than
the publisher's under load), it writes OUT.json.ready.
"""

import json
import sys
import time

import rclpy
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from photogram_ros.io.bag import msg_class

sys.path.insert(0, __file__.rsplit('/', 1)[0])
from message_key import message_key  # noqa: E402


def main():
    out, expected, timeout = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    specs = [a.split(':', 1) for a in sys.argv[4:]]
    rclpy.init()
    node = rclpy.create_node('raw_subscriber')
    received = []
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5000, reliability=ReliabilityPolicy.RELIABLE)
    subs = [node.create_subscription(msg_class(t), topic,
                                     lambda m, topic=topic: received.append((topic, message_key(m))), qos)
            for topic, t in specs]
    deadline = time.monotonic() + timeout
    ready = False
    while time.monotonic() < deadline and len(received) < expected:
        rclpy.spin_once(node, timeout_sec=0.1)
        if not ready and all(s.get_publisher_count() > 0 for s in subs):
            ready = True
            with open(out + '.ready', 'w'):
                pass
    with open(out, 'w') as f:
        json.dump(received, f)
    del subs
    node.destroy_node()
    rclpy.shutdown()


if __name__ == '__main__':
    main()
