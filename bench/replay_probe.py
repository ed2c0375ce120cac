"""Measuring hooks for the replay benchmarks (e2e_realtime.py, memory_soak.py); not a benchmark itself.

Node methods are wrapped with timers from outside, so the nodes carry no benchmark code and the
figures come from the very run being measured. Each wrapped call records wall time and the calling
thread's CPU time: with the GIL and other engineers' jobs on 2 cores, wall time inside a method
includes waiting, CPU time does not.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import threading
import time
from collections import defaultdict, deque
from dataclasses import asdict
from pathlib import Path

CACHE = Path('/tmp/photogram_bench_cache')


class Timer:
    def __init__(self):
        self.calls = 0
        self.wall_s = 0.0
        self.cpu_s = 0.0
        self.max_wall_s = 0.0
        self._lock = threading.Lock()

    def add(self, wall_s: float, cpu_s: float) -> None:
        with self._lock:
            self.calls += 1
            self.wall_s += wall_s
            self.cpu_s += cpu_s
            self.max_wall_s = max(self.max_wall_s, wall_s)

    def as_dict(self, run_wall_s: float) -> dict:
        return {'calls': self.calls, 'wall_s': round(self.wall_s, 2), 'cpu_s': round(self.cpu_s, 2),
                'wall_fraction': round(self.wall_s / run_wall_s, 3), 'cpu_fraction': round(self.cpu_s / run_wall_s, 3),
                'ms_per_call': round(1e3 * self.wall_s / max(self.calls, 1), 1),
                'max_ms': round(1e3 * self.max_wall_s, 1)}


class Probe:
    """Timers around the nodes' per-message work, keyframe -> fused-cloud latency, the live graph."""

    # (module, class, method, timer name); nested names (e.g. stereo_pair inside stereo_callbacks) overlap.
    TIMED = [
        ('photogram_ros.nodes.mavlink_node', 'MavlinkNode', '_on_bytes', 'mavlink_packet'),
        ('photogram_ros.nodes.tracker_node', 'TrackerNode', '_handle', 'tracker_frame'),
        ('photogram_ros.core.tracker', 'Tracker', 'process', 'tracker_core_process'),
        ('photogram_ros.nodes.tracker_node', 'TrackerNode', '_publish_keyframe', 'tracker_publish_keyframe'),
        ('photogram_ros.nodes.bundle_node', 'BundleNode', '_process', 'bundle_keyframe'),
        ('photogram_ros.nodes.bundle_node', 'BundleNode', 'full_adjustment', 'bundle_full_adjustment'),
        ('photogram_ros.nodes.bundle_node', 'BundleNode', '_on_features', 'bundle_cb_features'),
        ('photogram_ros.nodes.bundle_node', 'BundleNode', '_on_fix', 'bundle_cb_fix'),
        ('photogram_ros.nodes.bundle_node', 'BundleNode', '_wake', 'bundle_cb_timer'),
        ('photogram_ros.nodes.bundle_node', 'BundleNode', '_process_batch', 'bundle_batch'),
        ('photogram_ros.nodes.stereo_node', 'StereoNode', '_run_pair', 'stereo_pair'),
        ('photogram_ros.nodes.stereo_node', 'StereoNode', '_on_image', 'stereo_cb_image'),
        ('photogram_ros.nodes.stereo_node', 'StereoNode', '_on_pose', 'stereo_cb_pose'),
        ('photogram_ros.nodes.stereo_node', 'StereoNode', '_on_sparse', 'stereo_cb_sparse'),
        ('photogram_ros.nodes.map_node', 'MapNode', '_on_cloud', 'map_cloud'),
        ('photogram_ros.nodes.map_node', 'MapNode', '_on_image', 'map_save_keyframe_image'),
        ('photogram_ros.nodes.map_node', 'MapNode', '_on_pose', 'map_save_pose'),
        ('photogram_ros.nodes.map_node', 'MapNode', 'flush', 'map_flush'),
        ('photogram_ros.nodes.map_node', 'MapNode', '_stream', 'map_stream'),
    ]

    def __init__(self):
        self.timers: dict[str, Timer] = defaultdict(Timer)
        self._saved = []
        self.graph = None
        self.kf_published: dict[int, float] = {}   # keyframe stamp -> monotonic time tracker published it
        self.kf_order: list[int] = []
        self.kf_fused: dict[int, tuple[float, int]] = {}   # stamp -> (monotonic, newest image stamp then)
        self.newest_image_ns = 0
        self.first_image_ns = 0
        self._pairs: dict[int, deque] = defaultdict(deque)   # cloud stamp (newer kf) -> older kf stamps
        self.image_times: list = []   # (monotonic, newest image stamp then): flight time of a moment
        self.child_figures: dict = {}
        self._lock = threading.Lock()

    # --- installing ------------------------------------------------------------------------------

    def _patch(self, cls, name, fn):
        self._saved.append((cls, name, cls.__dict__[name]))
        setattr(cls, name, fn)

    def install(self) -> 'Probe':
        import importlib
        for module, cls_name, method, key in self.TIMED:
            cls = getattr(importlib.import_module(module), cls_name)
            self._patch(cls, method, self._timed(cls.__dict__[method], self.timers[key]))
        self._install_latency()
        from photogram_ros.nodes.graph import Graph
        orig_init = Graph.__init__
        probe = self

        def init(graph_self, *a, **k):
            orig_init(graph_self, *a, **k)
            probe.graph = graph_self
        self._patch(Graph, '__init__', init)
        return self

    def uninstall(self) -> None:
        for cls, name, fn in reversed(self._saved):
            setattr(cls, name, fn)
        self._saved.clear()

    @staticmethod
    def _timed(fn, timer: Timer):
        def wrapper(*a, **k):
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                timer.add(time.perf_counter() - t0, time.thread_time() - c0)
        wrapper.__wrapped__ = fn
        return wrapper

    def _install_latency(self) -> None:
        from photogram_ros import msgs
        from photogram_ros.nodes.map_node import MapNode
        from photogram_ros.nodes.stereo_node import StereoNode
        from photogram_ros.nodes.tracker_node import TrackerNode
        probe = self

        on_image = TrackerNode.__dict__['_on_image']

        def tracker_on_image(node, msg):
            s = msgs.ns_from_time(msg.header.stamp)
            with probe._lock:
                probe.newest_image_ns = max(probe.newest_image_ns, s)
                probe.first_image_ns = probe.first_image_ns or s
                probe.image_times.append((time.monotonic(), probe.newest_image_ns))
            return on_image(node, msg)
        self._patch(TrackerNode, '_on_image', tracker_on_image)

        publish_kf = TrackerNode.__dict__['_publish_keyframe']

        def tracker_publish(node, kf, frame_id):
            with probe._lock:
                if kf.stamp_ns not in probe.kf_published:
                    probe.kf_published[kf.stamp_ns] = time.monotonic()
                    probe.kf_order.append(kf.stamp_ns)
            return publish_kf(node, kf, frame_id)
        self._patch(TrackerNode, '_publish_keyframe', tracker_publish)

        # The pair cloud carries only the newer keyframe's stamp: remember the older one, in publish order.
        run_pair = StereoNode.__dict__['_run_pair']   # already timed by install()

        def stereo_run_pair(node, a, b, height_m):
            before = node.diag.counts().get('pairs_done', 0)
            with probe._lock:
                probe._pairs[b.stamp_ns].append(a.stamp_ns)
            try:
                return run_pair(node, a, b, height_m)
            finally:
                if node.diag.counts().get('pairs_done', 0) == before:   # no cloud was published
                    with probe._lock:
                        probe._pairs[b.stamp_ns].pop()
        self._patch(StereoNode, '_run_pair', stereo_run_pair)

        on_cloud = MapNode.__dict__['_on_cloud']

        def map_on_cloud(node, msg):
            try:
                return on_cloud(node, msg)
            finally:
                b = msgs.ns_from_time(msg.header.stamp)
                now = time.monotonic()
                with probe._lock:
                    q = probe._pairs.get(b)
                    a = q.popleft() if q else None
                    for s in (a, b):
                        if s is not None and s not in probe.kf_fused:
                            probe.kf_fused[s] = (now, probe.newest_image_ns)
        self._patch(MapNode, '_on_cloud', map_on_cloud)

    # --- a child process (ReplayOptions.child_roles) --------------------------------------------

    CHILD_ENV = 'PHOTOGRAM_PROBE_CHILD_OUT'
    # Optional: a JSON-lines file the child appends a memory sample to every few seconds
    # (monotonic time, which both processes share, RSS, malloc figures, what its nodes hold).
    CHILD_SAMPLES_ENV = 'PHOTOGRAM_PROBE_CHILD_SAMPLES'
    CHILD_TRACEMALLOC_ENV = 'PHOTOGRAM_PROBE_CHILD_TRACEMALLOC'

    @staticmethod
    def child_sitecustomize(folder: Path, bench_dir: Path) -> Path:
        """A sitecustomize.py that installs a Probe in every Python process started with `folder` on
        PYTHONPATH and CHILD_ENV set, and writes its figures there at exit: the nodes stay free of
        benchmark code and the child's timers come from the very run being measured."""
        folder.mkdir(parents=True, exist_ok=True)
        (folder / 'sitecustomize.py').write_text(
            'import os, sys\n'
            f'if os.environ.get({Probe.CHILD_ENV!r}):\n'
            f'    sys.path.insert(0, {str(bench_dir)!r})\n'
            '    import atexit\n'
            '    from replay_probe import Probe\n'
            '    _probe = Probe().install()\n'
            f'    atexit.register(_probe.dump_child, os.environ[{Probe.CHILD_ENV!r}])\n'
            f'    if os.environ.get({Probe.CHILD_SAMPLES_ENV!r}):\n'
            f'        _probe.start_child_sampler(os.environ[{Probe.CHILD_SAMPLES_ENV!r}])\n'
            # The next sitecustomize on the path (bench/module_trace's, when bench/machine.py traces the
            # modules a bench runs) would be shadowed by this one: run it too.
            'try:\n'
            '    import photogram_module_trace\n'
            '    photogram_module_trace.chain_next_sitecustomize(__file__)\n'
            'except ImportError:\n'
            '    pass\n')
        return folder

    def start_child_sampler(self, path: str, period_s: float = 3.0) -> None:
        """A daemon thread appending {t (monotonic), rss_mb, hwm_mb, malloc..., holdings} lines to `path`.

        With CHILD_TRACEMALLOC_ENV = N the child traces its Python allocations: it snapshots when the
        file `path`.settle appears and again when `path`.end appears (the parent creates them at the
        settle time and the end of the bag), then writes the N sites that grew most to `path`.sites.json
        and the largest live blocks to `path`.big_blocks.json. At each mark it also writes glibc's
        malloc_info XML to `path`.malloc_info_MARK.xml.
        """
        n_sites = int(os.environ.get(Probe.CHILD_TRACEMALLOC_ENV, '0') or 0)
        if n_sites:
            import tracemalloc
            tracemalloc.start(8)

        def loop():
            snaps = {}
            with open(path, 'a') as f:
                while True:
                    rss, hwm = RssSampler.read()
                    try:
                        h = memory_holdings(self)
                    except Exception as exc:   # a node being destroyed must not end the sampling
                        h = {'error': repr(exc)}
                    for mark in ('settle', 'end'):
                        if mark not in snaps and os.path.exists(f'{path}.{mark}'):
                            # glibc's own account of its heaps (free chunks by size, per arena)
                            malloc_info_xml(f'{path}.malloc_info_{mark}.xml')
                            snaps[mark] = None
                            if n_sites:
                                import tracemalloc
                                snaps[mark] = tracemalloc.take_snapshot()
                                if mark == 'end' and snaps.get('settle') is not None:
                                    Path(f'{path}.sites.json').write_text(json.dumps(
                                        growth_sites(snaps['settle'], snaps['end'], n_sites)))
                                    Path(f'{path}.big_blocks.json').write_text(json.dumps(
                                        big_blocks(snaps['end'], n_sites)))
                    if n_sites:
                        import tracemalloc
                        h['traced_mb'] = round(tracemalloc.get_traced_memory()[0] / 2**20, 1)
                    f.write(json.dumps({'t': time.monotonic(), 'rss_mb': rss, 'hwm_mb': hwm, **rss_parts(),
                                        **malloc_stats(), **h}) + '\n')
                    f.flush()
                    time.sleep(period_s)
        threading.Thread(target=loop, name='child-rss-sampler', daemon=True).start()

    def dump_child(self, path: str) -> None:
        import resource
        r = resource.getrusage(resource.RUSAGE_SELF)
        out = {'timers': {k: [t.calls, t.wall_s, t.cpu_s, t.max_wall_s] for k, t in self.timers.items()},
               'kf_fused': {str(k): v[0] for k, v in self.kf_fused.items()},
               'cpu_s': r.ru_utime + r.ru_stime, 'peak_rss_mb': RssSampler.read()[1]}
        Path(path).write_text(json.dumps(out))

    def merge_child(self, path: str) -> bool:
        """Adds the child's timers and fused keyframes (flight time looked up at the moment of fusing)."""
        import bisect
        if not Path(path).exists():
            return False
        d = json.loads(Path(path).read_text())
        for k, (calls, wall, cpu, mx) in d['timers'].items():
            t = self.timers[k]
            t.calls += calls
            t.wall_s += wall
            t.cpu_s += cpu
            t.max_wall_s = max(t.max_wall_s, mx)
        times = [t for t, _ in self.image_times]
        for k, t_fused in d['kf_fused'].items():
            i = bisect.bisect_right(times, t_fused) - 1
            newest = self.image_times[i][1] if i >= 0 else 0
            s = int(k)
            if s not in self.kf_fused or self.kf_fused[s][0] > t_fused:
                self.kf_fused[s] = (t_fused, newest)
        self.child_figures = {'cpu_s': d['cpu_s'], 'peak_rss_mb': d['peak_rss_mb']}
        return True

    # --- results ---------------------------------------------------------------------------------

    def breakdown(self, run_wall_s: float) -> dict:
        return {k: t.as_dict(run_wall_s) for k, t in sorted(self.timers.items()) if t.calls}

    def latency(self) -> dict:
        import numpy as np
        wall, flight, kfs_between = [], [], []
        index = {s: i for i, s in enumerate(self.kf_order)}
        by_time = sorted(self.kf_published.values())
        for s, t_pub in self.kf_published.items():
            if s not in self.kf_fused:
                continue
            t_fused, newest_ns = self.kf_fused[s]
            wall.append(t_fused - t_pub)
            flight.append((newest_ns - s) * 1e-9)
            kfs_between.append(int(np.searchsorted(by_time, t_fused)) - index[s] - 1)

        def stats(v):
            if not v:
                return None
            return {'median': round(float(np.median(v)), 2), 'p95': round(float(np.percentile(v, 95)), 2),
                    'max': round(float(np.max(v)), 2)}
        return {'keyframes_published': len(self.kf_published), 'keyframes_in_a_fused_cloud': len(wall),
                'wall_s': stats(wall), 'flight_s': stats(flight), 'keyframes_published_meanwhile': stats(kfs_between)}


def malloc_stats() -> dict:
    """glibc's mallinfo2 in MB: heap_mb (main + thread arenas, sbrk/mmap'd heaps), in_use_mb (allocated
    blocks there plus mmap'd blocks), free_mb (free space malloc holds: fragmentation when it grows),
    mmap_mb (large blocks malloc mmaps, e.g. numpy buffers over 128 kB or M_MMAP_THRESHOLD). Empty
    without glibc >= 2.33."""
    import ctypes
    import ctypes.util

    class _Mallinfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ('arena', 'ordblks', 'smblks', 'hblks', 'hblkhd', 'usmblks',
                                                    'fsmblks', 'uordblks', 'fordblks', 'keepcost')]
    try:
        libc = ctypes.CDLL(ctypes.util.find_library('c'))
        fn = libc.mallinfo2
    except (OSError, AttributeError, TypeError):
        return {}
    fn.restype = _Mallinfo2
    m = fn()
    mb = 1 / 2**20
    return {'heap_mb': round(m.arena * mb, 1), 'in_use_mb': round((m.uordblks + m.hblkhd) * mb, 1),
            'free_mb': round(m.fordblks * mb, 1), 'mmap_mb': round(m.hblkhd * mb, 1)}


def rss_parts() -> dict:
    """This process's RSS split as the kernel counts it (anonymous, file-backed, shared memory such as
    DDS transport segments), in MB, and its thread count."""
    out = {}
    with open('/proc/self/status') as f:
        for line in f:
            k, _, v = line.partition(':')
            if k in ('RssAnon', 'RssFile', 'RssShmem'):
                out[k[3:].lower() + '_mb'] = round(int(v.split()[0]) / 1024, 1)
            elif k == 'Threads':
                out['threads'] = int(v)
    return out


def growth_sites(s0, s1, n: int) -> list:
    """The n allocation sites (tracemalloc tracebacks, project frames first) that grew most from
    snapshot s0 to s1: [{'mb', 'count_diff', 'frames'}]."""
    out = []
    for d in s1.compare_to(s0, 'traceback')[:n]:
        frames = [f'{Path(f.filename).name}:{f.lineno}' for f in d.traceback
                  if 'photogram_ros' in f.filename or '/bench/' in f.filename or 'rclpy' in f.filename]
        out.append({'mb': round(d.size_diff / 1e6, 2), 'count_diff': d.count_diff,
                    'frames': frames[-4:] or [f'{Path(f.filename).name}:{f.lineno}' for f in d.traceback][-2:]})
    return out


def malloc_info_xml(path: str) -> bool:
    """Write glibc's malloc_info XML (every arena's free chunks by size class) to `path`."""
    import ctypes
    import ctypes.util
    try:
        libc = ctypes.CDLL(ctypes.util.find_library('c'))
        libc.fopen.restype = ctypes.c_void_p
        libc.fopen.argtypes = (ctypes.c_char_p, ctypes.c_char_p)
        libc.malloc_info.argtypes = (ctypes.c_int, ctypes.c_void_p)
        libc.fclose.argtypes = (ctypes.c_void_p,)
    except (OSError, AttributeError, TypeError):
        return False
    f = libc.fopen(path.encode(), b'w')
    if not f:
        return False
    libc.malloc_info(0, f)
    libc.fclose(f)
    return True


def big_blocks(snap, n: int, min_bytes: int = 64 * 1024) -> list:
    """The live allocations of at least min_bytes in a snapshot, grouped by site (the project frames
    of their traceback), the n largest groups: [{'mb', 'blocks', 'frames'}]. Long-lived large blocks
    between short-lived ones are what fragments malloc's heap."""
    groups: dict = {}
    for tr in snap.traces:
        if tr.size < min_bytes:
            continue
        frames = tuple(f'{Path(f.filename).name}:{f.lineno}' for f in tr.traceback
                       if 'photogram_ros' in f.filename or '/bench/' in f.filename or 'rclpy' in f.filename)[-4:]
        frames = frames or tuple(f'{Path(f.filename).name}:{f.lineno}' for f in tr.traceback)[-2:]
        g = groups.setdefault(frames, [0, 0])
        g[0] += tr.size
        g[1] += 1
    top = sorted(groups.items(), key=lambda kv: -kv[1][0])[:n]
    return [{'mb': round(b / 1e6, 2), 'blocks': c, 'frames': list(f)} for f, (b, c) in top]


def memory_holdings(probe: Probe) -> dict:
    """What the nodes of `probe`'s graph keep in memory now (read from another thread: sizes only)."""
    g = probe.graph
    if g is None:
        return {}
    n = g.nodes
    out = {}
    at = getattr(n.get('bundle'), 'at', None)
    if at is not None:
        out['bundle_keyframes'] = len(at.kfs)
        out['bundle_points'] = len(at.points)
        if hasattr(at, 'memory_stats'):   # what of it is still in the Python heap (the rest: disk, compact arrays)
            st = at.memory_stats()
            out['bundle_keyframes_in_memory'] = st['keyframes_in_memory']
            out['bundle_points_in_memory'] = st['points_in_memory']
            out['bundle_spilled_mb'] = st['spilled_mb']
    if 'stereo' in n:
        out['stereo_keyframes'] = len(n['stereo']._kf)
    if 'map' in n:
        f = n['map'].fusion
        out['map_tiles_in_memory'] = len(f.tiles)
        out['map_fusion_mb'] = round(f.memory_bytes / 1e6, 1)
    if 'tracker' in n:
        out['tracker_frames_queued'] = len(n['tracker']._frames)
    # Work queued between the nodes (a consumer falling behind holds its inputs in memory).
    if 'bundle' in n:
        out['bundle_keyframes_waiting'] = n['bundle'].waiting_keyframes()
    if 'stereo' in n:
        st = n['stereo']
        out['stereo_keyframes_unpaired'] = sum(1 for k in list(st._kf.values()) if not k.paired)
        out['stereo_dropped_unpaired'] = st.diag.counts().get('keyframes_dropped_unpaired', 0)
        if 'map' in n:
            c, m = st.diag.counts(), n['map'].diag.counts()
            out['clouds_in_flight'] = c.get('pairs_done', 0) - m.get('clouds', 0) - m.get('clouds_dropped', 0)
            out['map_images_behind_stereo'] = c.get('images', 0) - m.get('keyframes_saved', 0)
    if 'tracker' in n:
        from photogram_ros.nodes import replay_session
        if hasattr(replay_session, 'downstream_lag'):   # the whole graph's counters, the child's included
            out['downstream_lag'] = replay_session.downstream_lag(g.counts())
    return out


class RssSampler(threading.Thread):
    """VmRSS / VmHWM of this process every `period_s`, with the flight time the tracker had reached."""

    def __init__(self, probe: Probe | None = None, period_s: float = 2.0):
        super().__init__(daemon=True, name='rss-sampler')
        self.probe, self.period_s = probe, period_s
        self.samples = []   # (wall_s, flight_s or None, rss_mb, hwm_mb, extra)
        self._stop_evt = threading.Event()
        self.t0 = time.monotonic()
        self.extra = None   # callable -> dict of figures to keep with each sample

    @staticmethod
    def read() -> tuple[float, float]:
        rss = hwm = 0.0
        with open('/proc/self/status') as f:
            for line in f:
                if line.startswith('VmRSS:'):
                    rss = int(line.split()[1]) / 1024
                elif line.startswith('VmHWM:'):
                    hwm = int(line.split()[1]) / 1024
        return rss, hwm

    def sample(self) -> None:
        rss, hwm = self.read()
        flight = None
        if self.probe is not None and self.probe.first_image_ns:
            flight = (self.probe.newest_image_ns - self.probe.first_image_ns) * 1e-9
        extra = {}
        if self.extra is not None:
            try:
                extra = self.extra()
            except Exception as exc:   # a node being destroyed must not end the sampling
                extra = {'error': repr(exc)}
        self.samples.append((time.monotonic() - self.t0, flight, rss, hwm, extra))

    def run(self) -> None:
        while not self._stop_evt.wait(self.period_s):
            self.sample()

    def stop(self) -> None:
        self._stop_evt.set()
        self.join(timeout=5)
        self.sample()

    @property
    def peak_mb(self) -> float:
        return max([s[3] for s in self.samples] + [self.read()[1]])


def simulate_cached(cfg, label: str, log=print) -> tuple[Path, float, bool]:
    """The simulated bag for `cfg`, rendered once and kept under /tmp (rendering is the slow part and
    is not what these benchmarks measure). Returns (bag folder, render seconds, came from cache)."""
    from photogram_ros.sim.scenario import simulate
    key = hashlib.sha1(json.dumps(asdict(cfg), sort_keys=True, default=str).encode()).hexdigest()[:12]
    bag = CACHE / f'{label}_{key}'
    if (bag / 'ground_truth.json').exists():
        return bag, 0.0, True
    CACHE.mkdir(parents=True, exist_ok=True)
    tmp = CACHE / f'.{label}_{key}_partial'
    shutil.rmtree(tmp, ignore_errors=True)
    t0 = time.perf_counter()
    last = [0.0]

    def progress(k, n):
        if time.perf_counter() - last[0] > 15:
            last[0] = time.perf_counter()
            log(f'simulating {label}: frame {k}/{n}')
    simulate(cfg, tmp, progress=progress)
    tmp.rename(bag)
    return bag, time.perf_counter() - t0, False
