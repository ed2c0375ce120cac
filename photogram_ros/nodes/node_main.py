"""The body of every node's console script: init, spin, and the same clean exit on SIGINT and SIGTERM."""

from __future__ import annotations

import signal
import sys

import rclpy
from rclpy.executors import ExternalShutdownException

from photogram_ros.errors import PhotogramError
from photogram_ros.nodes.process_memory import limit_malloc_arenas


def _interrupt(*_):
    raise KeyboardInterrupt


def run_node(cls, argv=None, on_exit=None) -> int:
    """Run one node until interrupted; `on_exit(node)` runs before it is destroyed (e.g. a final adjustment).

    A supervisor's SIGTERM ends the node like Ctrl-C does, so what the node holds is flushed either way.
    Bad configuration exits with status 2 and the reason on stderr.
    """
    limit_malloc_arenas()
    rclpy.init(args=argv if argv is not None else sys.argv)
    signal.signal(signal.SIGTERM, _interrupt)
    node = None
    try:
        node = cls()
        rclpy.spin(node)
        return 0
    except PhotogramError as exc:
        print(f'{cls.__name__}: {exc}', file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        if node is not None:
            if on_exit is not None:
                on_exit(node)
            node.destroy_node()
        rclpy.try_shutdown()


def run_job(cls, job, argv=None) -> int:
    """Run a node that does one job and ends (play a bag, publish a folder): `job(node)` returns the exit
    status. Bad configuration exits with 2, Ctrl-C with 130."""
    limit_malloc_arenas()
    rclpy.init(args=argv if argv is not None else sys.argv)
    node = None
    try:
        node = cls()
        return int(job(node))
    except PhotogramError as exc:
        print(f'{cls.__name__}: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
