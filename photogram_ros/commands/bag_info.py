"""photogram-ros bag-info: topics, types, counts and duration of a bag, and what a damaged one lost."""

from __future__ import annotations

HELP = 'list the topics, message types, counts and duration of a bag (and what a damaged bag lost)'


def add_arguments(p) -> None:
    p.add_argument('bag', help='rosbag2 folder (sqlite3 or MCAP), a .db3 / .mcap file, or a ROS 1 .bag')


def run(a) -> int:
    """Exit status 0, or 3 when the bag is damaged (its readable part is listed)."""
    import sys

    from photogram_ros.io.bag import BagReader
    with BagReader(a.bag) as bag:
        if bag.damaged:
            bag.verify()
        infos = sorted(bag.topics().values(), key=lambda t: t.topic)
        recorded = any(t.expected is not None for t in infos)
        print(f'{a.bag}: {bag.storage}, {bag.duration_ns * 1e-9:.1f} s readable, '
              f'{sum(t.count for t in infos)} messages'
              + (f' of {sum(t.expected or 0 for t in infos)} recorded' if recorded else '')
              + (f', ROS {bag.metadata.ros_distro}' if bag.metadata is not None and bag.metadata.ros_distro else ''))
        for t in infos:
            line = f'  {t.topic:40s} {t.msgtype:36s} {t.count:8d}'
            if t.expected is not None and t.expected != t.count:
                line += f' of {t.expected} recorded'
            print(line)
        for line in bag.health():
            print(line, file=sys.stderr)
        return 3 if bag.damaged else 0
