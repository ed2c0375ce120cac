"""photogram-ros record: write chosen ROS 2 topics to a bag."""

from __future__ import annotations

HELP = 'record topics from ROS 2 into a rosbag2 (MCAP, or sqlite3), with their QoS profiles'


def add_arguments(p) -> None:
    p.add_argument('out', help='bag folder to create')
    p.add_argument('--topics', required=True, help='comma-separated topics to record')
    p.add_argument('--duration', type=float, default=0.0, help='stop after this many seconds (0 = until Ctrl-C)')
    p.add_argument('--count', type=int, default=0, help='stop after this many messages in total (0 = no limit)')
    p.add_argument('--discovery-timeout', type=float, default=10.0, help='seconds to wait for the topics to appear')
    p.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                   help='bag storage: mcap (ROS 2 Jazzy\'s default) or sqlite3')
    p.add_argument('--checkpoint', type=float, default=2.0,
                   help='seconds between commits (sqlite3) or chunk flushes (MCAP): a recording cut short by a '
                        'kill or a power loss keeps all but about its last this many seconds')


def run(a) -> int:
    import shutil
    import signal
    import threading

    import rclpy

    from photogram_ros.errors import ConfigError
    from photogram_ros.nodes.node_main import init_ros
    from photogram_ros.nodes.recorder import Recorder
    if not 0.1 <= a.checkpoint <= 600:
        raise ConfigError(f'--checkpoint {a.checkpoint}: choose 0.1 to 600 s')
    for opt, v, what in (('--duration', a.duration, 'seconds, 0 = until Ctrl-C'),
                         ('--count', a.count, 'messages, 0 = no limit')):
        if not 0 <= v < float('inf'):
            raise ConfigError(f'{opt} {v:g}: {what}')
    if not 0 < a.discovery_timeout <= 3600:
        raise ConfigError(f'--discovery-timeout {a.discovery_timeout:g}: choose more than 0 and up to 3600 s')
    topics = [t.strip() for t in a.topics.split(',') if t.strip()]
    if not topics:
        raise ConfigError('--topics names no topic: give them comma separated, e.g. --topics /gps/fix,/camera/image_raw')

    stop = threading.Event()   # SIGINT and SIGTERM end the recording between two messages: the bag closes
    for sig in (signal.SIGINT, signal.SIGTERM):   # with its metadata.yaml
        signal.signal(sig, lambda *_: stop.set())
    init_ros()
    rec = None
    discovered = False
    try:
        rec = Recorder(a.out, topics, storage=a.storage, checkpoint_s=a.checkpoint)
        n = rec.run(duration_s=a.duration, max_count=a.count, discovery_timeout_s=a.discovery_timeout, stop=stop)
        discovered = True
        print(f'recorded {n} messages to {a.out}')
        return 0
    finally:
        if rec is not None:
            rec.close()
            if not discovered and rec.count == 0:   # none of the topics appeared: no empty bag is left
                shutil.rmtree(a.out, ignore_errors=True)
        rclpy.try_shutdown()
