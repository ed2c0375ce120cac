"""Keep a long-running mapper process's memory flat (cap glibc's malloc arenas) and its large
buffers cheap (glibc's mmap and trim thresholds).

glibc gives each thread that contends for the heap its own arena, up to 8 per core. The graph's
executor threads, DDS threads and the bundle worker each free large numpy buffers that another
thread allocated, so every arena ends up holding its own fragmented free space. On a 30-minute
replay that alone grew the process by about 14 MB per flight minute until it levelled off near
1 GB (bench/memory_soak.py); with two arenas the same flight stays flat. numpy, OpenCV and scipy do
their heavy work outside malloc's locks, so the cap costs no measurable speed.
"""

from __future__ import annotations

import os

from photogram_ros.io.malloc_thresholds import (M_MMAP_THRESHOLD, M_TRIM_THRESHOLD, MMAP_THRESHOLD_BYTES,
                                                TRIM_THRESHOLD_BYTES, reuse_freed_buffers)
from photogram_ros.io.malloc_thresholds import libc as _libc

# What this module offers; the malloc thresholds come from io/malloc_thresholds.py.
__all__ = ['DEFAULT_ARENAS', 'M_ARENA_MAX', 'M_MMAP_THRESHOLD', 'M_TRIM_THRESHOLD', 'MMAP_THRESHOLD_BYTES',
           'TRIM_THRESHOLD_BYTES', 'arena_cap', 'limit_malloc_arenas', 'reuse_freed_buffers', 'start_heap_trimmer',
           'trim_heap']

M_ARENA_MAX = -8
DEFAULT_ARENAS = 2


def arena_cap(arenas: int | None = None) -> int:
    """The arena count `limit_malloc_arenas` applies: `arenas` if given, else a positive integer in
    MALLOC_ARENA_MAX, else DEFAULT_ARENAS."""
    if arenas is None:
        env = os.environ.get('MALLOC_ARENA_MAX', '')
        arenas = int(env) if env.isdigit() and int(env) > 0 else DEFAULT_ARENAS
    return int(arenas)


def limit_malloc_arenas(arenas: int | None = None) -> bool:
    """Cap glibc's malloc arenas at `arena_cap(arenas)` (MALLOC_ARENA_MAX, when set, wins over the
    default); False where there is no glibc.

    Applies to arenas created from now on, so call it before the graph starts its threads.
    """
    arenas = arena_cap(arenas)
    libc = _libc()
    try:
        return libc is not None and bool(libc.mallopt(M_ARENA_MAX, arenas))
    except AttributeError:              # musl or another libc without mallopt
        return False


def trim_heap() -> bool:
    """Give the free pages inside malloc's heaps back to the system (glibc malloc_trim); False without glibc.

    Freed numpy buffers leave holes between live blocks that RSS keeps counting; trimming releases
    whole free pages wherever they are, in a few milliseconds.
    """
    libc = _libc()
    try:
        return libc is not None and bool(libc.malloc_trim(0))
    except AttributeError:
        return False


def start_heap_trimmer(period_s: float = 20.0):
    """A daemon thread that trims the heap every `period_s` seconds; returns its stop event."""
    import threading
    stop = threading.Event()

    def loop():
        while not stop.wait(period_s):
            trim_heap()

    threading.Thread(target=loop, name='heap_trimmer', daemon=True).start()
    return stop
