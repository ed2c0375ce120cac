"""`photogram-ros`: one command with a subcommand per job.

Each subcommand lives in `photogram_ros/commands/<name>.py` with `HELP`, `add_arguments(parser)`
and `run(args) -> int`; heavy imports stay inside `run` so that `--help` is instant.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from photogram_ros.errors import PhotogramError

COMMANDS = {
    'simulate': 'photogram_ros.commands.simulate',
    'run': 'photogram_ros.commands.run',
    'replay': 'photogram_ros.commands.replay',
    'play': 'photogram_ros.commands.play',
    'ground-station': 'photogram_ros.commands.ground_station',
    'record': 'photogram_ros.commands.record',
    'bag-info': 'photogram_ros.commands.bag_info',
    'triangulate': 'photogram_ros.commands.triangulate',
    'geotag': 'photogram_ros.commands.geotag',
    'calibrate': 'photogram_ros.commands.calibrate',
    'export': 'photogram_ros.commands.export',
    'fixes': 'photogram_ros.commands.fixes',
    'import-frames': 'photogram_ros.commands.import_frames',
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='photogram-ros', description='Onboard photogrammetric mapping for drones.')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    sub.required = True
    for name, module_name in COMMANDS.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv=None) -> int:
    # Cap glibc's malloc arenas before any command starts rclpy (its DDS threads would each take
    # one): see nodes/process_memory.py. Cheap and harmless for the commands without threads.
    from photogram_ros.nodes.process_memory import limit_malloc_arenas
    limit_malloc_arenas()
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except PhotogramError as exc:
        print(f'photogram-ros {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
