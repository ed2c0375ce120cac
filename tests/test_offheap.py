"""Long-lived large arrays in mappings of their own: numpy semantics, memory back on release, map tiles."""

import ctypes.util
import subprocess
import sys

import numpy as np
import pytest

from photogram_ros.core import offheap
from photogram_ros.core.fusion import Fusion, FusionConfig


def test_arrays_behave_like_numpy_and_large_ones_live_outside_the_heap():
    z = offheap.zeros((480, 640, 3), np.uint8)
    assert z.shape == (480, 640, 3) and z.dtype == np.uint8 and z.flags.writeable and z.flags.c_contiguous
    assert not z.any() and offheap.is_offheap(z) and offheap.is_offheap(z[10:, 5])
    z[1, 2] = (1, 2, 3)
    assert z.sum() == 6
    src = np.arange(200_000, dtype=np.float32).reshape(400, 500)[:, ::2]   # not contiguous
    c = offheap.copy(src)
    assert offheap.is_offheap(c) and np.array_equal(c, src) and c.flags.c_contiguous
    c[0, 0] = -1
    assert src[0, 0] == 0                                            # a copy, not a view
    small = offheap.zeros(100, np.float64)                           # below MIN_BYTES: an ordinary array
    assert not offheap.is_offheap(small) and not small.any()
    assert not offheap.is_offheap(np.zeros(10**6))


@pytest.mark.skipif(not ctypes.util.find_library('c') or sys.platform != 'linux', reason='needs glibc')
def test_released_arrays_give_their_memory_back_at_once():
    # 300 MB of 1 MB arrays, each followed by a small long-lived heap block, then released without
    # malloc_trim: the off-heap ones go back to the system, on malloc's heap they stay resident.
    code = r'''
import sys, numpy as np
from photogram_ros.core import offheap
def rss_mb():
    return int([l for l in open('/proc/self/status') if l.startswith('VmRSS')][0].split()[1]) / 1024
np.ones(2 << 20)       # freed: glibc's mmap threshold rises past 1 MB, as in any long-running process
make = (lambda: offheap.zeros(1 << 17, np.float64)) if sys.argv[1] == 'offheap' else (lambda: np.empty(1 << 17))
keep, big = [], []
for i in range(300):
    a = make(); a.fill(i); big.append(a)     # 1 MB
    keep.append(bytearray(20_000))           # long-lived, right after it
del a
before = rss_mb(); del big; after = rss_mb()
print(before - after)
'''
    def freed_mb(mode):
        out = subprocess.run([sys.executable, '-c', code, mode], check=True, capture_output=True, text=True).stdout
        return float(out.strip())

    assert freed_mb('offheap') > 250
    assert freed_mb('heap') < 100          # the test could fail: on the heap they stay resident


def test_map_tiles_live_off_the_heap():
    f = Fusion(FusionConfig(cell_m=0.1, tile_cells=256))
    pts = np.zeros(1000, dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4')])
    pts['x'], pts['y'] = np.random.default_rng(0).uniform(1, 20, (2, 1000))
    f.add(pts)
    tile = next(iter(f.tiles.values()))
    assert all(offheap.is_offheap(a) for a in tile.f.values())
    assert tile.f['n'].sum() == 1000
