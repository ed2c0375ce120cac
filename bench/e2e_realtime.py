"""End-to-end real-time factor of the whole mapper on a simulated survey (640x480, 5 fps, 1 Hz GPS).

The survey is simulated once into /tmp/photogram_bench_cache (rendering is slow and not measured),
then replayed through the full graph (run_replay, config/replay.yaml: mavlink, tracker, bundle,
stereo, map in one process) with timers wrapped around each node's per-message work. JSON lines (bench/machine.py's
ResultWriter: commit, clean-tree flag, cores, load; a line's `kind` says what it holds) to --out and stdout:
the real-time factor against the 2x target, the time per node as fractions of the replay's
wall time (wall inside the method, and the thread's CPU time, which excludes waiting for the GIL),
the keyframe-to-cloud latency (tracker publishes keyframe k -> map fuses the first pair cloud that
contains k), and, as the baseline measured in the same run, the same frames through the bare core
Tracker (no ROS): what share of the pipeline's cost tracking is.

Configurations (`--configs`, each replayed in turn, the first is the baseline of the ratios):
`1` = every node in one process (the GIL holds it near one core); `2` = bundle, stereo and map in a
child process (photogram-ros replay's default). The child's timers come from a Probe installed
there through a generated sitecustomize.py and are merged into the figures.

    .venv/bin/python bench/e2e_realtime.py [--lines 4 --line-length 150] [--short] [--configs 1,2]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT))
os.environ.setdefault('ROS_DOMAIN_ID', '170')

from machine import ResultWriter, machine_info  # noqa: E402
from replay_probe import Probe, RssSampler, simulate_cached  # noqa: E402

TARGET_RTF = 2.0


WRITER: ResultWriter | None = None     # main() sets it: every line goes through bench/machine.py's ResultWriter


def emit(d: dict) -> None:
    """One result line (its `bench` as `kind`: e2e_realtime, e2e_latency, ...), to --out and stdout."""
    d = dict(d)
    kind = d.pop('bench', None)
    if WRITER is None:
        print(json.dumps({'kind': kind, **d}), flush=True)
    else:
        WRITER.write({'kind': kind, **d} if kind else d)


def log(s: str) -> None:
    print(s, file=sys.stderr, flush=True)


def cpu_s() -> float:
    """This process and its ended children (the graph's child process is waited for at shutdown)."""
    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                  resource.getrusage(resource.RUSAGE_CHILDREN)))


def per_node(bd: dict) -> dict:
    """The key per-message method of each node (plus the map's housekeeping), summed."""
    groups = {'mavlink': ['mavlink_packet'], 'tracker': ['tracker_frame'],
              'bundle': ['bundle_keyframe', 'bundle_full_adjustment'], 'stereo': ['stereo_pair'],
              'map': ['map_cloud', 'map_save_keyframe_image', 'map_save_pose', 'map_flush', 'map_stream']}
    out = {}
    for node, keys in groups.items():
        rows = [bd[k] for k in keys if k in bd]
        out[node] = {'calls': sum(r['calls'] for r in rows[:1]),
                     'wall_fraction': round(sum(r['wall_fraction'] for r in rows), 3),
                     'cpu_fraction': round(sum(r['cpu_fraction'] for r in rows), 3),
                     'wall_s': round(sum(r['wall_s'] for r in rows), 1),
                     'cpu_s': round(sum(r['cpu_s'] for r in rows), 1)}
    return out


def bare_tracker(bag: Path, tracker_params) -> dict:
    """Baseline: the same frames and fixes through photogram_ros.core.tracker.Tracker, no ROS."""
    from photogram_ros import msgs
    from photogram_ros.core.gnss_fix import GnssFix
    from photogram_ros.core.tracker import Tracker
    from photogram_ros.io.bag import BagReader, deserialize
    camera, items = None, []   # (arrival_ns, kind, payload)
    t0 = time.perf_counter()
    with BagReader(bag) as r:
        wanted = [t for t in ('/camera/image_raw/compressed', '/camera/image_raw', '/camera/camera_info', '/gps/fix')
                  if t in r.topics()]
        for m in r.messages(wanted):
            msg = deserialize(m.msgtype, m.data)
            if m.topic.endswith('camera_info'):
                camera = camera or msgs.camera_from_info(msg)
            elif m.topic == '/gps/fix':
                items.append(('fix', GnssFix.from_dict(msgs.fix_from_navsatfix(msg))))
            else:
                items.append(('image', msg))
    read_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    decoded = [(k, (msgs.image_from_msg(p), msgs.ns_from_time(p.header.stamp)) if k == 'image' else p)
               for k, p in items]
    decode_s = time.perf_counter() - t0
    tr = Tracker(camera, tracker_params)
    n_kf = 0
    t0, c0 = time.perf_counter(), time.thread_time()
    for kind, p in decoded:
        if kind == 'fix':
            tr.add_fix(p)
        else:
            n_kf += len(tr.process(*p))
    n_kf += len(tr.flush())
    return {'frames': sum(1 for k, _ in decoded if k == 'image'), 'keyframes': n_kf,
            'track_s': time.perf_counter() - t0, 'track_cpu_s': time.thread_time() - c0,
            'decode_s': decode_s, 'read_s': read_s}


def run_config(a, bag, extra, cfg_name: str, child_roles: tuple) -> dict:
    """One replay of the bag in one configuration; emits its figures."""
    import rclpy
    from photogram_ros.nodes.graph import Graph
    from photogram_ros.nodes.player_node import PlayerNode
    from photogram_ros.nodes.replay_session import ReplayOptions, run_replay

    probe = Probe().install()
    marks = {}
    play, finish = PlayerNode.play, Graph.finish_flight

    def timed_play(self, *x, **k):
        try:
            return play(self, *x, **k)
        finally:
            marks['play_end'] = time.monotonic()

    def timed_finish(self, *x, **k):
        marks['finish_start'] = time.monotonic()
        return finish(self, *x, **k)
    PlayerNode.play, Graph.finish_flight = timed_play, timed_finish

    stop = threading.Event()

    def progress():
        while not stop.wait(20):
            g = probe.graph
            if g is None:
                continue
            c = g.counts()
            log(f'[e2e] flight {(probe.newest_image_ns - probe.first_image_ns) * 1e-9:6.1f} s, keyframes '
                f'{len(probe.kf_published)}, pairs {c.get("stereo", {}).get("pairs_done", 0)}, clouds fused '
                f'{c.get("map", {}).get("clouds", 0)}')
    threading.Thread(target=progress, daemon=True).start()

    out = Path(a.keep) / f'config_{cfg_name}' if a.keep else Path(tempfile.mkdtemp(prefix='e2e_replay_'))
    child_out = out / 'child_probe.json'
    if child_roles:
        site = Probe.child_sitecustomize(out / 'probe_site', ROOT / 'bench')
        os.environ['PYTHONPATH'] = os.pathsep.join([str(site)] + [v for v in [os.environ.get('PYTHONPATH')] if v])
        os.environ[Probe.CHILD_ENV] = str(child_out)
    rclpy.init()
    sampler = RssSampler(probe, period_s=2.0)
    sampler.start()
    if a.profile:
        import yappi
        yappi.set_clock_type('cpu')
        yappi.start()
    c0, t0 = cpu_s(), time.monotonic()
    try:
        res = run_replay(ReplayOptions(bag=str(bag), out=str(out / 'replay'), params_file=a.params, progress=False,
                                       extra=extra, child_roles=child_roles))
    finally:
        t_end = time.monotonic()
        stop.set()
        sampler.stop()
        rclpy.try_shutdown()
        probe.uninstall()
        PlayerNode.play, Graph.finish_flight = play, finish
        os.environ.pop(Probe.CHILD_ENV, None)
    if a.profile:
        yappi.stop()
        stats = yappi.get_func_stats()
        stats.sort('tsub')
        emit({'bench': 'e2e_profile', 'config': cfg_name, 'clock': 'cpu (yappi inflates Python-heavy code)',
              'top_own_cpu_s': [[round(f.tsub, 2), round(f.ttot, 2), f.ncall, f'{Path(f.module).name}:{f.name}']
                                for f in list(stats)[:25]]})
        yappi.clear_stats()
    merged = probe.merge_child(str(child_out)) if child_roles else False
    run_cpu = cpu_s() - c0
    run = res['run']
    wall = run['wall_s']
    diag = res['diagnostics']
    tracker_node = probe.graph.nodes['tracker']
    tag = {'config': cfg_name, 'child_roles': list(child_roles)}
    n_kf = len(probe.kf_published)
    emit({'bench': 'e2e_realtime', **tag, 'child_probe_merged': merged, 'frames': run['frames'], 'keyframes': n_kf,
          'bag_s': round(run['bag_s'], 1),
          'wall_s': round(wall, 1), 'real_time_factor': round(run['real_time_factor'], 3),
          'target_real_time_factor': TARGET_RTF, 'meets_target': run['real_time_factor'] >= TARGET_RTF,
          'play_s': round(marks.get('play_end', t_end) - t0, 1),
          'drain_and_finish_s': round(t_end - marks.get('play_end', t_end), 1),
          'finish_flight_s': round(t_end - marks.get('finish_start', t_end), 1),
          'process_cpu_s': round(run_cpu, 1), 'cpu_cores_busy': round(run_cpu / (t_end - t0), 2),
          'peak_rss_mb': round(sampler.peak_mb, 1), 'child_peak_rss_mb': probe.child_figures.get('peak_rss_mb'),
          'load_avg_after': os.getloadavg()})
    bd = probe.breakdown(wall)
    emit({'bench': 'e2e_per_node', **tag, 'fraction_of_wall': 'cpu = thread CPU time / replay wall; wall = time inside '
          'the methods / replay wall (overlapping threads can sum past 1)', 'nodes': per_node(bd)})
    emit({'bench': 'e2e_breakdown', **tag, 'methods': bd})
    lat = probe.latency()
    emit({'bench': 'e2e_latency', **tag, 'definition': 'tracker publishes keyframe -> map has fused the first pair cloud '
          'containing it; flight_s = flight time the camera had reached by then', **lat})

    def pick(node, *keys):
        v = diag.get(node, diag.get('/' + node, {})).get('values', {})
        return {k: v.get(k) for k in keys if k in v}
    emit({'bench': 'e2e_node_diagnostics', **tag,
          'tracker_node': pick('tracker_node', 'frames_received', 'frames_tracked', 'drops', 'keyframes', 'process_ms',
                               'fps', 'breaks', 'keyframes_without_fix'),
          'bundle_node': pick('bundle_node', 'keyframes_received', 'keyframes_oriented', 'keyframes_not_oriented',
                              'keyframes_without_fix', 'solve_time_s', 'full_adjustment_s', 'points', 'window_size'),
          'stereo_node': pick('stereo_node', 'images', 'poses', 'keyframes', 'pairs_done', 'ms_per_pair', 'sgbm_ms',
                              'points_per_pair', 'keyframes_dropped'),
          'map_node': pick('map_node', 'clouds', 'points_fused', 'fuse_points_per_s', 'memory_mb', 'keyframes_saved'),
          'problems': {n: d['problems'][:5] for n, d in diag.items() if d['problems']}})

    from photogram_ros.core.tracker import TrackerParams
    tp = TrackerParams(**{k: getattr(tracker_node.params, k) for k in TrackerParams.__dataclass_fields__})
    return {'config': cfg_name, 'res': res, 'probe': probe, 'tracker_params': tp,
            'rtf': round(run['real_time_factor'], 3), 'cores': round(run_cpu / (t_end - t0), 2),
            'lat_med': (lat['wall_s'] or {}).get('median'), 'fused': lat['keyframes_in_a_fused_cloud']}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--lines', type=int, default=None, help='survey lines (preset survey: 4)')
    ap.add_argument('--line-length', type=float, default=None, help='line length, m (preset survey: 150)')
    ap.add_argument('--fps', type=float, default=5.0)
    ap.add_argument('--gps-rate', type=float, default=1.0)
    ap.add_argument('--short', action='store_true', help='2 lines of 100 m (a quick check)')
    ap.add_argument('--params', default=str(ROOT / 'config' / 'replay.yaml'))
    ap.add_argument('--set', action='append', default=[], metavar='ROLE.PARAM=VALUE',
                    help='override a node parameter over the params file, e.g. tracker.fix_wait_s=1.5 '
                         '(ROLE: mavlink, tracker, bundle, stereo, map)')
    ap.add_argument('--bag', default='', help='replay this bag instead of simulating the survey')
    ap.add_argument('--keep', default='', help='keep the replay outputs in this folder')
    ap.add_argument('--configs', default='1,2', help='replay configurations in turn, the first is the baseline: '
                    '1 = one process, 2 = bundle+stereo+map in a child process, '
                    'or a +-list of child roles (e.g. stereo+map)')
    ap.add_argument('--no-bare-tracker', action='store_true', help='skip the bare-tracker baseline')
    ap.add_argument('--profile', action='store_true', help='CPU profile of this process\'s threads with yappi '
                    '(bench/requirements-peers.txt): the top functions by own time, as one more JSON line')
    ap.add_argument('--out', default=None, help='the result file (JSON lines; default /tmp/e2e_realtime.jsonl)')
    a = ap.parse_args()
    global WRITER
    WRITER = ResultWriter.for_bench(a.out, 'e2e_realtime', ['photogram_ros', 'config'])

    from photogram_ros.sim.scenario import preset
    over = {'fps': a.fps, 'gps_rate_hz': a.gps_rate}
    if a.short:
        over.update(n_lines=2, line_length_m=100.0)
    if a.lines:
        over['n_lines'] = a.lines
    if a.line_length:
        over['line_length_m'] = a.line_length
    cfg = preset('survey', **over)
    extra = {}
    for item in a.set:
        key, _, value = item.partition('=')
        role, _, name = key.partition('.')
        extra.setdefault(role, {})[name] = json.loads(value) if value[:1] in '-0123456789[{tf' else value
    emit({'machine': machine_info(), 'load_avg_before': os.getloadavg()})
    if a.bag:
        bag, sim_s, cached = Path(a.bag), 0.0, True
    else:
        bag, sim_s, cached = simulate_cached(cfg, 'e2e_survey', log)
    emit({'bench': 'e2e_sim', 'bag': str(bag), 'render_s': round(sim_s, 1), 'from_cache': cached,
          'size': f'{cfg.width_px}x{cfg.height_px}', 'fps': cfg.fps, 'gps_rate_hz': cfg.gps_rate_hz,
          'n_lines': cfg.n_lines, 'line_length_m': cfg.line_length_m, 'params': a.params, 'overrides': extra})

    configs = [c.strip() for c in a.configs.split(',') if c.strip()]
    results = []
    for cfg_name in configs:
        child = () if cfg_name == '1' else ('bundle', 'stereo', 'map') if cfg_name == '2' else tuple(cfg_name.split('+'))
        results.append(run_config(a, bag, extra, cfg_name, child))
    base = results[0]
    for r in results[1:]:
        emit({'bench': 'e2e_compare', 'baseline': base['config'], 'config': r['config'],
              'real_time_factor': [base['rtf'], r['rtf']], 'rtf_ratio': round(r['rtf'] / base['rtf'], 2),
              'latency_median_wall_s': [base['lat_med'], r['lat_med']],
              'keyframes_in_fused_clouds': [base['fused'], r['fused']],
              'cpu_cores_busy': [base['cores'], r['cores']]})
    if a.no_bare_tracker:
        return 0
    res, probe = results[-1]['res'], results[-1]['probe']
    run = res['run']
    wall = run['wall_s']
    tracker_params = results[-1]['tracker_params']
    base = bare_tracker(bag, tracker_params)
    node_tracker = probe.timers['tracker_frame']
    emit({'bench': 'e2e_baseline_bare_tracker', 'frames': base['frames'], 'keyframes': base['keyframes'],
          'track_s': round(base['track_s'], 1), 'track_cpu_s': round(base['track_cpu_s'], 1),
          'decode_s': round(base['decode_s'], 1),
          'bare_tracker_real_time_factor': round(run['bag_s'] / (base['track_s'] + base['decode_s']), 2),
          'config': results[-1]['config'], 'pipeline_wall_over_bare_tracker': round(wall / (base['track_s'] + base['decode_s']), 2),
          'tracking_share_of_pipeline_wall': round((base['track_s'] + base['decode_s']) / wall, 3),
          'tracker_node_over_bare_tracker': round(node_tracker.wall_s / (base['track_s'] + base['decode_s']), 2)})
    return 0


if __name__ == '__main__':
    sys.exit(main())
