"""How every photogram_ros process starts rclpy and stops: the same clean exit on SIGINT and SIGTERM.

rclpy's own signal handlers shut the context down the moment a signal arrives, before any
end-of-flight work: the final adjustment could then no longer publish its poses ("publisher's
context is invalid") and stereo no longer its last pairs. So rclpy starts here without them
(`init_ros`); SIGINT and SIGTERM only ask the process to stop (`StopSignals`, or KeyboardInterrupt
for a node's console script), the end-of-flight work runs with the context alive, and rclpy shuts
down last. A process started by another one (the replay child, `run --separate`) also watches a
pipe from its parent and stops when the parent is gone, even after a kill -9 (`watch_parent`).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

import rclpy
from rclpy.executors import ExternalShutdownException

from photogram_ros.errors import PhotogramError
from photogram_ros.nodes.process_memory import limit_malloc_arenas

# Set by a parent that gives its child a pipe on stdin to watch (see watch_parent).
WATCH_PARENT_ENV = 'PHOTOGRAM_WATCH_PARENT'


def init_ros(args=None, context=None) -> None:
    """rclpy.init without rclpy's SIGINT/SIGTERM handlers (see the module docstring)."""
    from rclpy.signals import SignalHandlerOptions
    kwargs = {'context': context} if context is not None else {}
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO, **kwargs)


class StopSignals:
    """SIGINT and SIGTERM set `stop` (also when the shell started the process in the background
    with SIGINT ignored: a supervisor's SIGINT means stop). A second signal while stopping only
    says what is still being done; the work on disk is safe against a kill -9 anyway."""

    def __init__(self, what_on_stop: str = 'finishing'):
        self.stop = threading.Event()
        self.signal_name = ''
        self._what = what_on_stop
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)

    def _on_signal(self, signum, _frame) -> None:
        if self.stop.is_set():
            print(f'{signal.Signals(signum).name} again: still {self._what}; kill -9 stops at once '
                  '(the map on disk stays consistent)', file=sys.stderr, flush=True)
            return
        self.signal_name = signal.Signals(signum).name
        self.stop.set()

    def wait(self, period_s: float = 0.5, alive=lambda: True) -> None:
        """Until a signal came (or `alive()` turns false)."""
        while not self.stop.wait(period_s) and alive():
            pass


def watch_parent(on_gone, grace_s: float = 120.0) -> bool:
    """In a child given a pipe on stdin (WATCH_PARENT_ENV set): call `on_gone()` when the parent's end
    closes (the parent exited or was killed), and end the process if it is still up `grace_s` later.
    Returns whether it watches."""
    if os.environ.get(WATCH_PARENT_ENV) != '1':
        return False

    def watch():
        try:
            while os.read(sys.stdin.fileno(), 4096):
                pass
        except OSError:
            pass
        print(f'{os.path.basename(sys.argv[0]) or "child"} (pid {os.getpid()}): the parent process is gone; '
              'stopping', file=sys.stderr, flush=True)
        on_gone()
        time.sleep(grace_s)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name='watch-parent').start()
    return True


def _interrupt(*_):
    raise KeyboardInterrupt


def _start(argv) -> None:
    """A console script's process: malloc arenas capped, rclpy up with `argv` (sys.argv when None), SIGINT
    and SIGTERM as KeyboardInterrupt, and an end when the parent process ends."""
    limit_malloc_arenas()
    init_ros(args=argv if argv is not None else sys.argv)
    signal.signal(signal.SIGTERM, _interrupt)
    signal.signal(signal.SIGINT, _interrupt)
    watch_parent(lambda: os.kill(os.getpid(), signal.SIGTERM))


def run_node(cls, argv=None, on_exit=None, settle_s: float = 1.0) -> int:
    """Run one node until interrupted; then `on_exit(node)` (e.g. a final adjustment), or the node's
    own `flush()` (the tracker's last keyframes, stereo's last pairs), runs with the context alive,
    `settle_s` lets what it published leave, and the node is destroyed.

    SIGINT and SIGTERM both end the node this way. Bad configuration exits with status 2 and the
    reason on stderr.
    """
    _start(argv)
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
        signal.signal(signal.SIGINT, signal.SIG_IGN)    # the end-of-flight work is not interrupted
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if node is not None:
            end = on_exit if on_exit is not None else (lambda n: getattr(n, 'flush', lambda: None)())
            try:
                end(node)
                time.sleep(settle_s)
            except Exception as exc:   # reported; the node is still destroyed (the map flushes)
                print(f'{cls.__name__}: end of flight failed: {exc}', file=sys.stderr)
            node.destroy_node()
        rclpy.try_shutdown()


def run_job(cls, job, argv=None) -> int:
    """Run a node that does one job and ends (play a bag, publish a folder): `job(node)` returns the exit
    status. Bad configuration exits with 2, Ctrl-C or SIGTERM with 130."""
    _start(argv)
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
