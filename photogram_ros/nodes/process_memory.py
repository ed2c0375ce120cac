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

import ctypes
import ctypes.util
import os

M_TRIM_THRESHOLD = -1     # mallopt parameter numbers, glibc's malloc.h
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8
DEFAULT_ARENAS = 2
MMAP_THRESHOLD_BYTES = 32 << 20   # glibc's own ceiling for its sliding mmap threshold on 64-bit
TRIM_THRESHOLD_BYTES = 2 * MMAP_THRESHOLD_BYTES


def _libc():
    """glibc as a ctypes library, or None (no C library found, or not one ctypes can load)."""
    name = ctypes.util.find_library('c')
    if not name:
        return None
    try:
        return ctypes.CDLL(name)
    except OSError:
        return None


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


def reuse_freed_buffers(mmap_threshold_bytes: int = MMAP_THRESHOLD_BYTES,
                        trim_threshold_bytes: int = TRIM_THRESHOLD_BYTES) -> bool:
    """Serve buffers under `mmap_threshold_bytes` from malloc's heap and give the heap's top back to the
    system only past `trim_threshold_bytes` (glibc mallopt); False without glibc.

    glibc slides its mmap threshold up to 32 MiB as large buffers are freed, so a loop of numpy
    temporaries reuses the same heap memory. Setting any threshold (MALLOC_TRIM_THRESHOLD_ in the
    environment, as Dask's nanny does for its workers) freezes the mmap threshold at 128 KiB: every
    temporary over it is then mapped, zeroed page by page and unmapped again (1.6 MB temporaries in a
    loop ran 7x slower, most of it kernel time). This sets both thresholds where glibc's sliding one
    ends up.
    """
    libc = _libc()
    try:
        return (libc is not None and bool(libc.mallopt(M_MMAP_THRESHOLD, int(mmap_threshold_bytes)))
                and bool(libc.mallopt(M_TRIM_THRESHOLD, int(trim_threshold_bytes))))
    except AttributeError:
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
