"""photogram-ros play: publish a bag's topics onto ROS 2 with the recorded timing."""

from __future__ import annotations

HELP = 'publish the topics of a bag with their recorded timing (no mapping)'


def add_arguments(p) -> None:
    p.add_argument('bag', help='rosbag2 folder (sqlite3 or MCAP)')
    p.add_argument('--rate', type=float, default=1.0,
                   help='speed factor; 0 = as fast as subscribers keep up: waits until the subscribers that exist are '
                        'matched, then publishes --ack-window messages per topic per acknowledgement round trip')
    p.add_argument('--topics', default='', help='comma-separated topics to play (default: all)')
    p.add_argument('--exclude', default='', help='comma-separated topics not to play')
    p.add_argument('--remap', default='', help='comma-separated renames /from:=/to')
    p.add_argument('--loop', action='store_true', help='play again from the start when the bag ends')
    p.add_argument('--no-clock', action='store_true', help='do not publish /clock')
    p.add_argument('--wait-for-subscribers', type=int, default=0, help='wait for N subscribers before playing')
    p.add_argument('--ack-window', type=int, default=10,
                   help='--rate 0: messages per topic between waits for the acknowledgements (1,000-2,000 messages/s '
                        'a topic with 10; larger is faster and can overrun KEEP_LAST subscribers)')


def player_overrides(a) -> dict:
    return {'bag': a.bag, 'rate': float(a.rate), 'topics': a.topics, 'exclude': a.exclude, 'remap': a.remap,
            'loop': bool(a.loop), 'publish_clock': not a.no_clock, 'wait_for_subscribers': a.wait_for_subscribers,
            'ack_window': a.ack_window}


def run(a) -> int:
    import rclpy

    from photogram_ros.nodes.player_node import PlayerNode, PlayerParams
    from photogram_ros.params import from_dict
    from photogram_ros.errors import ConfigError
    if not 0 <= a.rate <= 10000:   # nan too
        raise ConfigError(f'--rate {a.rate:g}: the speed factor, 0 (as fast as subscribers acknowledge) to 10000')
    from_dict(PlayerParams, player_overrides(a), where='play').check()   # before ROS starts: one line, exit 2
    rclpy.init()
    node = None
    try:
        node = PlayerNode(overrides=player_overrides(a))
        summary = node.play()
        print('\n'.join(summary.lines()))
        return 3 if summary.errors or summary.skipped else 0
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
