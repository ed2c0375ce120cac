"""Replay throughput: messages and MB per second from the player to a subscriber in another process.

Baseline in the same run: reading the same messages from the bag without publishing (BagReader
alone), so the ratio is the cost of DDS transport and pacing on top of storage.
The lines go through bench/machine.py's ResultWriter (commit, clean-tree flag, cores, load) into --out (default
/tmp/replay_throughput.jsonl), and on stdout.
usage: .venv/bin/python bench/replay_throughput.py [BAG] [--out FILE.jsonl]
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
from machine import ResultWriter, machine_info  # noqa: E402

import rclpy  # noqa: E402

from photogram_ros.io.bag import BagReader  # noqa: E402
from photogram_ros.nodes.player_node import PlayerNode  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('bag', nargs='?', default=str(ROOT / 'bags' / 'sample_flight'))
    ap.add_argument('--out', default=None, help='the result file (JSON lines; default /tmp/replay_throughput.jsonl)')
    a = ap.parse_args()
    bag = Path(a.bag)
    w = ResultWriter.for_bench(a.out, 'replay_throughput', ['photogram_ros/io/bag.py', 'photogram_ros/nodes/player_node.py'])
    os.environ.setdefault('ROS_DOMAIN_ID', '91')
    w.write({'machine': machine_info()})
    with BagReader(bag) as r:
        topics = {t: i.msgtype for t, i in r.topics().items()}
        t0 = time.perf_counter()
        n = nbytes = 0
        for m in r.messages():
            n += 1
            nbytes += len(m.data)
        t_read = time.perf_counter() - t0
    out = Path('/tmp') / f'replay_bench_{os.getpid()}.json'
    sub = subprocess.Popen([sys.executable, str(ROOT / 'tests' / 'helpers' / 'raw_subscriber.py'), str(out), str(n),
                            '300'] + [f'{t}:{m}' for t, m in topics.items()], cwd=ROOT)
    rclpy.init()
    node = PlayerNode(overrides={'bag': str(bag), 'rate': 0.0, 'wait_for_subscribers': len(topics),
                                 'wait_timeout_s': 30.0})
    summary = node.play()
    sub.wait(timeout=300)
    received = len(json.loads(out.read_text()))
    out.unlink()
    node.destroy_node()
    rclpy.shutdown()
    w.write({'bag': bag.name, 'messages': summary.total,
                      'received_by_other_process': received, 'MB': round(nbytes / 1e6, 2),
                      'msgs_per_s': round(summary.total / summary.wall_s), 'MB_per_s': round(nbytes / 1e6 / summary.wall_s, 1),
                      'real_time_factor': round(summary.bag_s / summary.wall_s, 1),
                      'baseline_read_msgs_per_s': round(n / t_read), 'ratio_to_baseline': round(summary.wall_s / t_read, 1)})


if __name__ == '__main__':
    main()
