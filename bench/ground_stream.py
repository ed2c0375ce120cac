"""Bandwidth of the ground-station streams per flight minute: live ortho tiles against the cloud stream.

Replays a flight (`photogram-ros replay`, at the bag's own speed by default: the streams' periods are
wall-clock periods, as in flight) while this process subscribes, best effort like the ground station,
to map/ortho_tiles and map/cloud_downsampled and adds up the serialized bytes of every message. The
baseline, measured in the same run, is the cloud stream that map_node already sent to the ground:
the ratio is what the ortho adds on top of it. Also the tile count and the mean tile size.
usage: .venv/bin/python bench/ground_stream.py [BAG] [--rate R]
"""

import argparse
import os
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
from machine import ResultWriter, machine_info  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('bag', nargs='?', default=str(ROOT / 'bags' / 'sample_flight'))
    ap.add_argument('--rate', type=float, default=1.0, help='bag time speed of the replay (1: as flown)')
    ap.add_argument('--out', default=None, help='the result file (JSON lines through bench/machine.py\'s ResultWriter; '
                                                'default /tmp/ground_stream.jsonl)')
    a = ap.parse_args()
    w = ResultWriter.for_bench(a.out, 'ground_stream', ['photogram_ros', 'config'])
    os.environ.setdefault('ROS_DOMAIN_ID', '227')
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CompressedImage, PointCloud2

    from photogram_ros.io.bag import BagReader
    w.write({'machine': machine_info()})
    with BagReader(a.bag) as r:
        flight_s = r.duration_ns / 1e9
    rclpy.init()
    node = Node('ground_stream_bench')
    tot = {'ortho': [0, 0], 'cloud': [0, 0]}
    be = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)

    def add(kind):
        def cb(msg):
            tot[kind][0] += 1
            tot[kind][1] += len(serialize_message(msg))
        return cb

    node.create_subscription(CompressedImage, '/map/ortho_tiles', add('ortho'), be)
    node.create_subscription(PointCloud2, '/map/cloud_downsampled', add('cloud'), be)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    stop = threading.Event()
    th = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.01) for _ in iter(stop.is_set, True)], daemon=True)
    th.start()
    with tempfile.TemporaryDirectory() as out:
        res = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', a.bag, '--out', out, '--quiet',
                              '--domain', os.environ['ROS_DOMAIN_ID'],   # this listener's: a replay has its own
                              '--rate', str(a.rate)], cwd=ROOT, capture_output=True, text=True)
    stop.set()
    th.join(5)
    if res.returncode != 0:
        print(res.stderr[-2000:], file=sys.stderr)
        return 1
    per_min = {k: v[1] / (flight_s / 60.0) for k, v in tot.items()}
    w.write({'bag': Path(a.bag).name, 'rate': a.rate, 'flight_s': round(flight_s, 1),
                      'ortho_tiles': tot['ortho'][0], 'ortho_mean_tile_kb': round(tot['ortho'][1] / max(tot['ortho'][0], 1) / 1e3, 1),
                      'ortho_mb_per_flight_min': round(per_min['ortho'] / 1e6, 3),
                      'baseline_cloud_messages': tot['cloud'][0],
                      'baseline_cloud_mb_per_flight_min': round(per_min['cloud'] / 1e6, 3),
                      'ratio_ortho_to_cloud': round(per_min['ortho'] / max(per_min['cloud'], 1), 3)})
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
