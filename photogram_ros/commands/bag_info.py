"""photogram-ros bag-info: topics, types, counts and duration of a bag."""

from __future__ import annotations

HELP = 'list the topics, message types, counts and duration of a bag'


def add_arguments(p) -> None:
    p.add_argument('bag', help='rosbag2 folder (sqlite3 or MCAP)')


def run(a) -> int:
    from photogram_ros.io.bag import BagReader
    with BagReader(a.bag) as bag:
        print(f'{a.bag}: {bag.duration_ns * 1e-9:.1f} s')
        for t in sorted(bag.topics().values(), key=lambda t: t.topic):
            print(f'  {t.topic:40s} {t.msgtype:36s} {t.count:8d}')
    return 0
