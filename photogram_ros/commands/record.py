"""photogram-ros record: write chosen ROS 2 topics to a bag."""

from __future__ import annotations

HELP = 'record topics from ROS 2 into a rosbag2 (sqlite3 or MCAP)'


def add_arguments(p) -> None:
    p.add_argument('out', help='bag folder to create')
    p.add_argument('--topics', required=True, help='comma-separated topics to record')
    p.add_argument('--duration', type=float, default=0.0, help='stop after this many seconds (0 = until Ctrl-C)')
    p.add_argument('--count', type=int, default=0, help='stop after this many messages in total (0 = no limit)')
    p.add_argument('--discovery-timeout', type=float, default=10.0, help='seconds to wait for the topics to appear')
    p.add_argument('--mcap', action='store_true', help='write MCAP instead of sqlite3')


def run(a) -> int:
    import rclpy

    from photogram_ros.nodes.recorder import Recorder
    rclpy.init()
    rec = None
    try:
        rec = Recorder(a.out, [t.strip() for t in a.topics.split(',') if t.strip()],
                       storage='mcap' if a.mcap else 'sqlite3')
        n = rec.run(duration_s=a.duration, max_count=a.count, discovery_timeout_s=a.discovery_timeout)
        print(f'recorded {n} messages to {a.out}')
        return 0
    finally:
        if rec is not None:
            rec.close()
        rclpy.try_shutdown()
