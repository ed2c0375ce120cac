"""Independent pieces of work run here, or as tasks of a Dask cluster (`triangulate --workers/--scheduler`).

`open_runner(workers, scheduler, log)` gives a runner for the length of a `with` block:
- workers 1 and no scheduler: `InProcessRunner`, every call made here in order (no Dask imported);
- workers N > 1: a local Dask cluster of N worker processes of one thread each (dask.distributed
  `LocalCluster`, memory per worker: the machine's memory shared out, spilled to disk past Dask's
  thresholds), closed at the end of the block;
- scheduler 'tcp://HOST:PORT': a client of that existing cluster (its workers must import
  photogram_ros and read the input files at the same paths: a shared file system).

A runner's one verb, `run(fn, calls, what, log, keep=False, on_result=None, extra=None)`, calls
fn(*args) for every tuple of `calls` and returns the results in the order of `calls`. With
keep=True the results stay where they were made (a Dask worker's memory) and handles to them come
back, to be passed as arguments of later calls (the task then runs where the data is, or the data
moves between workers, never through this process). `on_result(k, result)` sees each result as it
arrives (in any order on a cluster). Progress goes to `log` every PROGRESS_EVERY_S: done/total,
elapsed time and an estimate of the time left (`extra()` appends its text).
"""

from __future__ import annotations

import numbers
import time
from contextlib import contextmanager
from pathlib import Path

from photogram_ros.errors import ConfigError

PROGRESS_EVERY_S = 5.0
CONNECT_TIMEOUT_S = 20.0


class Progress:
    """Progress lines of `total` pieces of work: 'what: done/total (elapsed s, about N s left)'."""

    def __init__(self, log, what: str | None, total: int, where: str = ''):
        self.log, self.what, self.total, self.where = log, what, total, where
        self.t0 = self.last = time.monotonic()

    def step(self, done: int, extra: str = '') -> None:
        now = time.monotonic()
        if self.log is None or self.what is None:
            return
        if now - self.last >= PROGRESS_EVERY_S or done == self.total:
            self.last = now
            el = now - self.t0
            left = f', about {el / done * (self.total - done):.0f} s left' if 0 < done < self.total else ''
            self.log(f'{self.what}: {done}/{self.total}{extra}{self.where} ({el:.0f} s{left})')


class InProcessRunner:
    """Every call made in this process, in order."""
    workers = 1
    where = ''

    def run(self, fn, calls, what=None, log=None, keep=False, on_result=None, extra=None) -> list:
        calls = list(calls)
        prog = Progress(log, what, len(calls))
        out = []
        for k, args in enumerate(calls):
            r = fn(*args)
            out.append(r)
            if on_result is not None:
                on_result(k, r)
            prog.step(k + 1, extra() if extra else '')
        return out

    def release(self, handles) -> None:
        """Forget kept results (here: nothing to do, the caller drops its references)."""


def _single_threaded(fn, *args):
    """fn(*args) in a Dask worker thread, OpenCV's own thread pool off: the cluster's workers are
    the parallelism (one thread each on a local cluster). The worker's malloc serves large numpy
    buffers from its heap again (`reuse_freed_buffers`): Dask's nanny starts workers with
    MALLOC_TRIM_THRESHOLD_ set, which makes glibc map and unmap every buffer over 128 KiB."""
    import cv2

    from photogram_ros.io.malloc_thresholds import reuse_freed_buffers
    cv2.setNumThreads(1)
    reuse_freed_buffers()
    return fn(*args)


class DaskRunner:
    """Calls as tasks of a dask.distributed cluster (`client`)."""

    def __init__(self, client, where: str):
        self.client, self.where = client, where
        self.workers = len(client.nthreads())

    def run(self, fn, calls, what=None, log=None, keep=False, on_result=None, extra=None) -> list:
        from distributed import as_completed
        calls = list(calls)
        sent: dict = {}
        futures = [self.client.submit(_single_threaded, fn, *(self._shipped(a, sent) for a in args), pure=False)
                   for args in calls]
        index = {f.key: k for k, f in enumerate(futures)}
        prog = Progress(log, what, len(calls), f' on {self.workers} workers{self.where}')
        out = [None] * len(calls)
        done = 0
        for f in as_completed(futures):
            k = index[f.key]
            if keep:
                if f.status == 'error':
                    f.result()          # raises the task's exception here
                out[k] = f
                if on_result is not None:
                    on_result(k, f)
            else:
                out[k] = f.result()
                if on_result is not None:
                    on_result(k, out[k])
                f.release()
            done += 1
            prog.step(done, extra() if extra else '')
        return out

    def _shipped(self, arg, sent: dict):
        """The argument as a task gets it: numbers, text, paths and futures as they are; any other object
        sent to the cluster once (by identity: `sent`, kept for the calls of one run) and passed as its
        future, so that a block's records or the shared options are not pickled into every task's graph."""
        from distributed import Future
        if arg is None or isinstance(arg, (numbers.Number, str, bytes, Path, Future)):
            return arg
        if id(arg) not in sent:
            sent[id(arg)] = self.client.scatter(arg, hash=False)
        return sent[id(arg)]

    def release(self, handles) -> None:
        """Free the workers' copies of kept results."""
        for f in handles:
            if f is not None:
                f.release()


def _dask():
    try:
        import distributed
    except ImportError as e:
        raise ConfigError('--workers above 1 and --scheduler need Dask: pip install "dask[distributed]" '
                          '(requirements-pip-only.txt pins it)') from e
    return distributed


@contextmanager
def open_runner(workers: int = 1, scheduler: str | None = None, log=None):
    """A runner for `workers` local processes (1: this process, no Dask) or the cluster at `scheduler`
    ('tcp://HOST:PORT'); the local cluster is closed and the client disconnected on leaving."""
    if workers < 1:
        raise ConfigError(f'--workers takes 1 or more, got {workers}')
    if scheduler and workers != 1:
        raise ConfigError('--workers starts a local cluster and --scheduler uses an existing one: give one of them')
    if not scheduler and workers == 1:
        yield InProcessRunner()
        return
    distributed = _dask()
    if scheduler:
        if '://' not in scheduler:
            raise ConfigError(f'--scheduler takes the address a `dask scheduler` prints, tcp://HOST:PORT; got '
                              f'{scheduler!r}')
        try:
            client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as e:
            raise ConfigError(f'no Dask scheduler answered at {scheduler} within {CONNECT_TIMEOUT_S:.0f} s ({e}): '
                              'start one with `dask scheduler` and workers with `dask worker ADDRESS`') from e
        try:
            runner = DaskRunner(client, f' at {scheduler}')
            if runner.workers < 1:
                raise ConfigError(f'the Dask scheduler at {scheduler} has no workers: start some with '
                                  f'`dask worker {scheduler}`')
            if log is not None:
                log(f'Dask cluster at {scheduler}: {runner.workers} workers')
            yield runner
        finally:
            client.close()
        return
    import logging
    # On the loopback interface only, the scheduler's HTTP server on any free port (two clusters at once).
    cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host='127.0.0.1',
                                       dashboard_address='127.0.0.1:0', silence_logs=logging.ERROR)
    try:
        with distributed.Client(cluster) as client:
            client.wait_for_workers(workers)
            if log is not None:
                log(f'local Dask cluster: {workers} worker processes of 1 thread')
            yield DaskRunner(client, '')
    finally:
        cluster.close()
