"""Keeping the pace of the camera on a small computer: a CPU share for the work that may be shed, thread caps
and the niceness of a worker thread.

When the camera outpaces the computer (a 20 MP photo every 0.7 s on two cores), the pose chain (tracker,
bundle adjuster) and the live check points must keep up; stereo pairs and ortho tiles come after them.
`CpuShare` is how stereo_node and map_node know they are over their part: the thread CPU time their work
took in the last `window_s` seconds of wall time, against `share` of one core. Over it, stereo sheds the
pairs of a keyframe (counted, said on /diagnostics; `export --densify` and replay's map_final match every pair
again from the stored keyframes after landing) and the map defers its ortho tiles to a later period.

`limit_threads` caps OpenCV's and the BLAS libraries' thread pools (per process: the last call counts), and
`nice_this_thread` lowers the priority of the calling thread only (Linux keeps a nice value per thread; threads
it starts inherit it), so a stereo worker can yield to the pose chain in the same process.
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from dataclasses import dataclass

from photogram_ros.errors import ConfigError
from photogram_ros.params import param


@dataclass
class ThreadCaps:
    """A node's thread pools (config/companion.yaml sets them on a companion computer)."""
    cv_threads: int = param(0, 'OpenCV threads of this node\'s process (cv2.setNumThreads; 0: OpenCV\'s default, '
                               'one per core; per process: the last node started in it counts)', min=0, max=256)
    blas_threads: int = param(0, 'BLAS/OpenMP threads of this node\'s process (threadpoolctl when installed, else '
                                 'set OPENBLAS_NUM_THREADS before the start; 0: the default)', min=0, max=256)


class CpuShare:
    """The CPU seconds of guarded work over the last `window_s` s of wall time, against `share` of one core
    (0: no limit). Use `measure()` around the work; `over()` says whether new work would exceed the share."""

    def __init__(self, share: float, window_s: float = 20.0, clock=time.monotonic):
        if share < 0 or not window_s > 0:
            raise ConfigError(f'CPU share {share} must be >= 0 (0: no limit) and its window {window_s} s positive')
        self.share, self.window_s, self._clock = float(share), float(window_s), clock
        self._spent: deque = deque()   # (wall end, CPU s)
        self._lock = threading.Lock()
        self._start = clock()

    def add(self, cpu_s: float, now: float | None = None) -> None:
        with self._lock:
            self._spent.append((self._clock() if now is None else now, float(cpu_s)))

    def used(self, now: float | None = None) -> float:
        """The share of one core the work took in the last window (or since the start, when shorter)."""
        now = self._clock() if now is None else now
        with self._lock:
            while self._spent and self._spent[0][0] < now - self.window_s:
                self._spent.popleft()
            spent = sum(c for _, c in self._spent)
        return spent / max(min(self.window_s, now - self._start), 1.0)

    def over(self, now: float | None = None) -> bool:
        return self.share > 0 and self.used(now) > self.share

    def measure(self):
        """Context manager: the calling thread's CPU time inside it counts."""
        share = self

        class _M:
            def __enter__(self):
                self.t0 = time.thread_time()
                return self

            def __exit__(self, *exc):
                share.add(time.thread_time() - self.t0)
                return False
        return _M()


def limit_threads(cv_threads: int = 0, blas_threads: int = 0) -> dict:
    """Cap OpenCV's thread pool (cv2.setNumThreads) and the BLAS/OpenMP pools (threadpoolctl, when installed;
    else the value says to set the environment variables) of this process; 0 leaves one as it is. Returns
    what was set."""
    out = {}
    if cv_threads > 0:
        import cv2
        cv2.setNumThreads(int(cv_threads))
        out['cv_threads'] = cv2.getNumThreads()
    if blas_threads > 0:
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:   # not installed: the environment variables must be set before the process starts
            out['blas_threads'] = ('not set: threadpoolctl is not installed; set OPENBLAS_NUM_THREADS / '
                                   'OMP_NUM_THREADS / MKL_NUM_THREADS before the start')
            return out
        threadpool_limits(int(blas_threads))
        out['blas_threads'] = int(blas_threads)
    return out


def nice_this_thread(increment: int) -> int:
    """Lower the calling thread's priority by `increment` (Linux: per thread; elsewhere the process's). Returns
    the new nice value; 0 increment does nothing."""
    if increment < 0:
        raise ConfigError(f'niceness increment {increment} must be >= 0 (raising priority needs privileges)')
    tid = threading.get_native_id()
    if increment == 0:
        return os.getpriority(os.PRIO_PROCESS, tid)
    now = os.getpriority(os.PRIO_PROCESS, tid)
    os.setpriority(os.PRIO_PROCESS, tid, min(now + int(increment), 19))
    return os.getpriority(os.PRIO_PROCESS, tid)
