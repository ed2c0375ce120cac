"""Measuring hooks for the replay benchmarks (e2e_realtime.py, memory_soak.py); not a benchmark itself.

Node methods are wrapped with timers from outside, so the nodes carry no benchmark code and the
figures come from the very run being measured. Each wrapped call records wall time and the calling
thread's CPU time: with the GIL and other engineers' jobs on 2 cores, wall time inside a method
includes waiting, CPU time does not.
"""

from __future__ import annotations

import hashlib
import json
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
            f'    atexit.register(_probe.dump_child, os.environ[{Probe.CHILD_ENV!r}])\n')
        return folder

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
