"""glibc's malloc thresholds for processes that churn large numpy buffers (a Dask worker, a mapper node), and
glibc itself as a ctypes library. nodes/process_memory.py builds the mapper's arena cap and heap trimming on it.
"""

from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD = -1     # mallopt parameter numbers, glibc's malloc.h
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 << 20   # glibc's own ceiling for its sliding mmap threshold on 64-bit
TRIM_THRESHOLD_BYTES = 2 * MMAP_THRESHOLD_BYTES


def libc():
    """glibc as a ctypes library, or None (no C library found, or not one ctypes can load)."""
    name = ctypes.util.find_library('c')
    if not name:
        return None
    try:
        return ctypes.CDLL(name)
    except OSError:
        return None


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
    lib = libc()
    try:
        return (lib is not None and bool(lib.mallopt(M_MMAP_THRESHOLD, int(mmap_threshold_bytes)))
                and bool(lib.mallopt(M_TRIM_THRESHOLD, int(trim_threshold_bytes))))
    except AttributeError:
        return False
