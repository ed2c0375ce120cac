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


# Commands that join a DDS domain: ROS_DOMAIN_ID is checked before they start.
ROS_COMMANDS = ('run', 'replay', 'play', 'record', 'ground-station')


class HelpFormatter(argparse.HelpFormatter):
    """`--help` shows each option's default, "(default: X)", unless its text already says it (the word
    "default") or there is nothing to show (None, False, an empty string: the option is simply off)."""

    def _get_help_string(self, action):
        text = action.help or ''
        d = action.default
        if (not action.option_strings or d is None or d is False or d == '' or d is argparse.SUPPRESS
                or isinstance(action, (argparse._HelpAction, argparse._VersionAction))
                or 'default' in text.lower()):
            return text
        return f'{text} (default: %(default)s)'


class _Parser(argparse.ArgumentParser):
    """An argument error is one line (what and where to look), exit status 2."""

    def error(self, message):
        self.exit(2, f'{self.prog}: error: {message} (see {self.prog} --help)\n')


def version() -> str:
    """The package's version (photogram_ros.__version__, which setup.py installs as its own)."""
    from photogram_ros import __version__
    return __version__


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog='photogram-ros', description='Onboard photogrammetric mapping for drones.',
                     formatter_class=HelpFormatter)
    parser.add_argument('--version', action='version', version=f'%(prog)s {version()}')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    sub.required = True
    for name, module_name in COMMANDS.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=module.HELP, description=module.HELP, formatter_class=HelpFormatter)
        module.add_arguments(p)
        p.set_defaults(run_command=module.run)
    return parser


def os_error_text(exc: OSError) -> str:
    """An OSError as a user can act on it: the path, and what is wrong with it."""
    import errno
    where = ' -> '.join(str(f) for f in (exc.filename, exc.filename2) if f) or 'a file'
    if isinstance(exc, (FileExistsError, NotADirectoryError)):
        return f'{where}: a file is in the way of a folder ({exc.strerror}): choose another path'
    if isinstance(exc, PermissionError):
        return f'{where}: permission denied: choose a path you can write'
    if exc.errno == errno.ENOSPC:
        return f'{where}: the disk is full'
    if isinstance(exc, FileNotFoundError):
        return f'{where}: no such file or folder'
    return f'{where}: {exc.strerror or exc}'


class Stopped(BaseException):
    """SIGTERM before the command installed its own handling (while it imports and checks its input); a
    BaseException, as KeyboardInterrupt, so that no `except Exception` takes it."""


def _stop_on_signals(received: list) -> None:
    """SIGTERM ends the command like Ctrl-C until the command installs its own handling (run, record,
    ground-station: they finish their work first): said in one line, not a silent exit 143. Each signal
    is also noted in `received`: an exception raised where Python cannot pass it on (a finaliser, a
    garbage-collection callback) is lost, the signal is not."""
    import signal
    import threading

    def stop(signum, frame):
        received.append(signum)
        raise Stopped() if signum == signal.SIGTERM else KeyboardInterrupt()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, stop)
        signal.signal(signal.SIGINT, stop)


def main(argv=None) -> int:
    import signal
    received: list[int] = []
    _stop_on_signals(received)
    command = ['photogram-ros']
    try:
        status = _main(argv, command)
    except KeyboardInterrupt:
        print(f'{" ".join(command)}: stopped by SIGINT', file=sys.stderr)
        return 130
    except Stopped:
        print(f'{" ".join(command)}: stopped by SIGTERM', file=sys.stderr)
        return 143
    if received and command[-1] not in ROS_COMMANDS:
        # A command without a stop of its own that went on after a signal: its exception was lost (the ROS
        # commands take SIGINT as their stop and return their own status).
        signum = received[0]
        print(f'{" ".join(command)}: stopped by {signal.Signals(signum).name}', file=sys.stderr)
        return 128 + signum
    return status


def _main(argv, command: list) -> int:
    # Cap glibc's malloc arenas before any command starts rclpy (its DDS threads would each take
    # one): see nodes/process_memory.py. Cheap and harmless for the commands without threads.
    from photogram_ros.nodes.process_memory import limit_malloc_arenas
    limit_malloc_arenas()
    args = build_parser().parse_args(argv)
    command.append(args.command)
    try:
        if args.command in ROS_COMMANDS:
            from photogram_ros.nodes.ros_domain import check_domain_env
            check_domain_env()
        return int(args.run_command(args) or 0)
    except PhotogramError as exc:
        print(f'photogram-ros {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except OSError as exc:   # a path that cannot be written or read: said in one line, no traceback
        print(f'photogram-ros {args.command}: error: {os_error_text(exc)}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
