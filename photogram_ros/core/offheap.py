"""Large long-lived arrays in their own memory mappings, outside malloc's heap.

A mapper process holds a few hundred MB of large arrays for minutes (map tiles, stereo's keyframe
images) while every keyframe allocates and frees as much again in temporaries (stereo pairs,
fusion, window adjustments). In glibc's heap the long-lived blocks sit between the short-lived
ones, so the freed space around them can be neither reused whole nor returned: on the 16-minute
soak (bench/memory_soak.py) the heap's free space grew from 100 to 200 MB while live memory stayed
flat. An array made here gets an anonymous mapping of its own, returned to the system the moment
the array is garbage (munmap), and never pins the heap.

Making every large allocation a mapping (a fixed M_MMAP_THRESHOLD of 128 kB) would do the same for
the temporaries too, but each temporary then costs fresh zeroed pages: it doubled the CPU time of
the bundle/stereo/map process. Only what lives long belongs here; a mapping is also at least a
page, so small arrays stay ordinary.
"""

from __future__ import annotations

import mmap

import numpy as np

MIN_BYTES = 64 * 1024   # below this an array stays on the heap (a page-granular mapping would waste)


def zeros(shape, dtype) -> np.ndarray:
    """Like np.zeros, in an anonymous mapping of its own when at least MIN_BYTES (pages come zeroed)."""
    dtype = np.dtype(dtype)
    shape = (shape,) if np.isscalar(shape) else tuple(shape)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if nbytes < MIN_BYTES:
        return np.zeros(shape, dtype)
    # Private: a plain anonymous mapping (a shared one would count as shared memory and be shared with
    # forked children). The array keeps the mmap object alive through its buffer; when the array
    # goes, so does the mapping.
    m = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    return np.frombuffer(m, dtype=dtype).reshape(shape)


def copy(a: np.ndarray) -> np.ndarray:
    """A C-contiguous copy of `a`, in a mapping of its own when at least MIN_BYTES."""
    a = np.asarray(a)
    out = zeros(a.shape, a.dtype)
    out[...] = a
    return out


def is_offheap(a: np.ndarray) -> bool:
    """Whether `a` (or the array it views) lives in a mapping made here."""
    while isinstance(a, np.ndarray):
        a = a.base
    return isinstance(a.obj if isinstance(a, memoryview) else a, mmap.mmap)
