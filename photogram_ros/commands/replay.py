"""photogram-ros replay: run photogram_ros on a recorded flight and write the results."""

from __future__ import annotations

HELP = 'replay a flight bag through photogram_ros and write the outputs to --out'


def add_arguments(p) -> None:
    from photogram_ros.commands.play import add_arguments as add_play_arguments
    add_play_arguments(p)
    p.set_defaults(rate=0.0)
    p.add_argument('--out', default='output/replay', help='output folder')


def run(a) -> int:
    import json
    from pathlib import Path

    import rclpy

    from photogram_ros.commands.play import player_overrides
    from photogram_ros.nodes.player_node import PlayerNode
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rclpy.init()
    node = None
    try:
        node = PlayerNode(overrides=player_overrides(a))
        summary = node.play()
        lines = summary.lines()
        print('\n'.join(lines))
        (out / 'replay_summary.json').write_text(json.dumps({
            'bag': str(a.bag), 'counts': summary.counts, 'bytes': summary.bytes, 'skipped': summary.skipped,
            'errors': summary.errors, 'wall_s': summary.wall_s, 'bag_s': summary.bag_s}, indent=1))
        return 3 if summary.errors or summary.skipped else 0
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
