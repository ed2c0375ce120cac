"""The malloc arena cap is applied where glibc exists and is a no-op elsewhere."""

import ctypes.util
import os
import subprocess
import sys

import pytest

from photogram_ros.nodes import process_memory as pm
from photogram_ros.nodes.process_memory import limit_malloc_arenas


@pytest.mark.skipif(not ctypes.util.find_library('c') or sys.platform != 'linux', reason='needs glibc')
def test_arenas_are_capped_in_a_threaded_process():
    # mallopt returns 1 on success; the arena count itself is visible through malloc_info's XML.
    code = r'''
import ctypes, ctypes.util, sys, tempfile, threading
from photogram_ros.nodes.process_memory import limit_malloc_arenas
if sys.argv[1] == 'cap' and not limit_malloc_arenas(2):
    raise SystemExit('mallopt refused')
start = threading.Barrier(8)
def work():
    start.wait()    # all threads allocate at once: contention is what makes glibc open new arenas
    for _ in range(200):
        bufs = [bytearray(20_000) for _ in range(20)]
        del bufs
ts = [threading.Thread(target=work) for _ in range(8)]
[t.start() for t in ts]; [t.join() for t in ts]
libc = ctypes.CDLL(ctypes.util.find_library('c'))
libc.fdopen.restype = ctypes.c_void_p
libc.malloc_info.argtypes = (ctypes.c_int, ctypes.c_void_p)
libc.fclose.argtypes = (ctypes.c_void_p,)
fd, path = tempfile.mkstemp()
f = libc.fdopen(fd, b"w"); libc.malloc_info(0, f); libc.fclose(f)
print(open(path).read().count('<heap nr='))
'''
    def arenas(mode):
        out = subprocess.run([sys.executable, '-c', code, mode], check=True, capture_output=True, text=True).stdout
        return int(out.strip())

    assert arenas('cap') <= 2
    assert arenas('free') > 2       # the test could fail: without the cap the threads do spread out


class _FakeLibc:
    """Stands in for glibc: records what mallopt was asked."""

    def __init__(self, calls):
        self.calls = calls

    def mallopt(self, param, value):
        self.calls.append((param, value))
        return 1


@pytest.mark.parametrize('env, applied', [('3', 3), ('1', 1), (None, pm.DEFAULT_ARENAS), ('0', pm.DEFAULT_ARENAS),
                                          ('many', pm.DEFAULT_ARENAS)])
def test_environment_value_wins(monkeypatch, env, applied):
    if env is None:
        monkeypatch.delenv('MALLOC_ARENA_MAX', raising=False)
    else:
        monkeypatch.setenv('MALLOC_ARENA_MAX', env)
    calls = []
    monkeypatch.setattr(ctypes.util, 'find_library', lambda name: 'libc.so.6')
    monkeypatch.setattr(ctypes, 'CDLL', lambda name: _FakeLibc(calls))
    assert pm.arena_cap() == applied
    assert limit_malloc_arenas() is True
    assert calls == [(pm.M_ARENA_MAX, applied)]     # a set, positive MALLOC_ARENA_MAX is what mallopt gets
    calls.clear()
    assert limit_malloc_arenas(5) and calls == [(pm.M_ARENA_MAX, 5)]   # an explicit count beats both


def test_no_glibc_is_a_polite_no(monkeypatch):
    monkeypatch.setattr(ctypes.util, 'find_library', lambda name: None)
    assert limit_malloc_arenas() is False


def test_trim_gives_freed_heap_back():
    code = r'''
import gc
from photogram_ros.nodes.process_memory import trim_heap
def rss_kb():
    return int([l for l in open('/proc/self/status') if l.startswith('VmRSS')][0].split()[1])
keep, junk = [], []
for i in range(20000):      # interleave small long-lived and short-lived blocks: holes below the heap top
    keep.append(bytearray(600)); junk.append(bytearray(8000))   # > 512 B: malloc, not pymalloc
del junk; gc.collect()
before = rss_kb(); trim_heap(); after = rss_kb()
print(before - after)
'''
    out = subprocess.run([sys.executable, '-c', code], check=True, capture_output=True, text=True).stdout
    assert int(out.strip()) > 20_000      # kB: most of the ~160 MB of freed holes return to the system


def test_reuse_freed_buffers_sets_both_thresholds(monkeypatch):
    calls = []
    monkeypatch.setattr(ctypes.util, 'find_library', lambda name: 'libc.so.6')
    monkeypatch.setattr(ctypes, 'CDLL', lambda name: _FakeLibc(calls))
    assert pm.reuse_freed_buffers() is True
    assert calls == [(pm.M_MMAP_THRESHOLD, 32 << 20), (pm.M_TRIM_THRESHOLD, 64 << 20)]
    monkeypatch.setattr(ctypes.util, 'find_library', lambda name: None)
    assert pm.reuse_freed_buffers() is False


@pytest.mark.skipif(not ctypes.util.find_library('c') or sys.platform != 'linux', reason='needs glibc')
def test_temporaries_stop_faulting_under_a_fixed_trim_threshold():
    # MALLOC_TRIM_THRESHOLD_ (as Dask's nanny sets it) freezes glibc's mmap threshold at 128 KiB:
    # every 1.6 MB temporary is mapped afresh and faulted in page by page, until the thresholds are set.
    code = r'''
import resource, sys
import numpy as np
from photogram_ros.nodes.process_memory import reuse_freed_buffers
if sys.argv[1] == 'reuse' and not reuse_freed_buffers():
    raise SystemExit('mallopt refused')
x = np.ones((200, 1000))
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(1000):
    x * 1.0001 + 1.0
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
'''
    env = dict(os.environ, MALLOC_TRIM_THRESHOLD_='65536')

    def faults(mode):
        out = subprocess.run([sys.executable, '-c', code, mode], check=True, capture_output=True, text=True, env=env)
        return int(out.stdout.strip())
    assert faults('frozen') > 200_000       # the test could fail: about 400 faults per temporary
    assert faults('reuse') < 10_000
