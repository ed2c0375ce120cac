"""Memory of the replay process over a long simulated flight: is it flat after the first minutes?

A lawnmower survey of 150 m lines at 1 fps is simulated (once, in a child process, cached under
/tmp/photogram_bench_cache, so the simulator's terrain never counts in this process's memory) with
as many lines as `--minutes` of flight needs, new ground all the way up to `--max-lines` lines;
longer flights fly that block again (SimConfig.repeats: a return transit, then the same lines,
which still adds new keyframes, tracks and pair clouds every minute). It is then replayed at full
speed through the whole graph (run_replay, config/replay.yaml) while a thread samples VmRSS/VmHWM
from /proc/self/status every few seconds, with the flight time the camera has reached.

Prints JSON lines: RSS and peak at flight minutes 1, 2, 5, 10, 15, 20, 30 (those the flight
reaches), at the end of the bag and after the final adjustment; the RSS slope (MB per flight
minute) after `--settle` minutes and over the last 10, and what the nodes hold at each checkpoint
(bundle keyframes and tie points, and how many of them are still in memory rather than
frozen/spilled; stereo keyframes, map tiles) to tell which one grows, with glibc malloc's own
figures (heap, free space inside it, mmap'd blocks) to tell live memory from fragmentation. With
`--processes 2` (replay's default) the child process running bundle, stereo and map is sampled
too (a Probe installed there through a generated sitecustomize.py): its figures carry the prefix
`child_`, `total_rss_mb` is both processes; the summary also gives each process's CPU seconds and
how long the player waited for the nodes after the tracker (replay backpressure). `--tracemalloc N`
adds the N Python allocation sites that grew most after the settle time and the largest live
blocks (slower replay: use it to find a leak, not for the reference figures). Baseline in the same
run: the process's RSS just before the graph starts, so growth is reported as a ratio to it.

    .venv/bin/python bench/memory_soak.py               # ~6 min of flight, a few minutes here
    .venv/bin/python bench/memory_soak.py --minutes 8   # 16.6 min of flight (the block flown twice), ~10 min
    .venv/bin/python bench/memory_soak.py --minutes 30  # a 30-minute flight (34 min), ~30 min here
    .venv/bin/python bench/memory_soak.py --processes 1 --tracemalloc 30   # every node in one traced process
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT))
os.environ.setdefault('ROS_DOMAIN_ID', '171')

from machine import machine_info  # noqa: E402
from replay_probe import (Probe, RssSampler, big_blocks, growth_sites, malloc_stats,  # noqa: E402
                          memory_holdings, rss_parts)

CHECKPOINTS_MIN = (1, 2, 5, 10, 15, 20, 25, 30, 45, 60)
# Columns of the curves besides flight minute, RSS and peak: malloc's view, the traced Python
# heap (with --tracemalloc) and the work queued between the nodes.
CURVE = ('heap_mb', 'in_use_mb', 'free_mb', 'mmap_mb', 'traced_mb', 'clouds_in_flight',
         'bundle_keyframes_waiting', 'stereo_keyframes_unpaired', 'map_images_behind_stereo', 'downstream_lag')
FLAT_MB_PER_MIN = 1.0   # "flat": under 1 MB per flight minute, i.e. < 30 MB over a 30-minute flight


def emit(d: dict) -> None:
    print(json.dumps(d), flush=True)


def log(s: str) -> None:
    print(s, file=sys.stderr, flush=True)


def flight_config(minutes: float, fps: float, max_lines: int, line_length_m: float):
    """Lines (then repeats of the block) until the flight lasts at least `minutes`."""
    import numpy as np
    from photogram_ros.sim.flight import LawnmowerFlight, SurveyPlan
    from photogram_ros.sim.scenario import preset

    def duration(cfg):
        plan = SurveyPlan(cfg.altitude_m, cfg.line_length_m, cfg.line_spacing_m, cfg.n_lines, cfg.speed_mps,
                          cfg.turn_speed_mps, cfg.heading_deg, (0.0, 0.0), cfg.repeats)
        return LawnmowerFlight(plan, np.random.default_rng(0)).duration_s

    base = dict(fps=fps, gps_rate_hz=1.0, line_length_m=line_length_m, jpeg_quality=85)
    for n in range(1, max_lines + 1):
        cfg = preset('survey', n_lines=n, **base)
        if duration(cfg) >= minutes * 60:
            return cfg, duration(cfg)
    for r in range(2, 1000):
        cfg = preset('survey', n_lines=max_lines, repeats=r, **base)
        if duration(cfg) >= minutes * 60:
            return cfg, duration(cfg)
    raise SystemExit(f'--minutes {minutes} is too long for this pattern')


def simulate_in_child(cfg) -> tuple[Path, float, bool]:
    """Render in another process: the simulator's terrain and texture must not inflate this one's RSS."""
    from dataclasses import asdict
    code = ('import json, sys; sys.path.insert(0, "bench"); from replay_probe import simulate_cached; '
            'from photogram_ros.sim.scenario import SimConfig; '
            'c = SimConfig(**json.loads(sys.argv[1])); '
            'c.dist = tuple(c.dist); c.lever_arm_frd_m = tuple(c.lever_arm_frd_m); '
            'b, s, k = simulate_cached(c, "soak", lambda m: print(m, file=sys.stderr, flush=True)); '
            'print(json.dumps([str(b), s, k]))')
    out = subprocess.run([sys.executable, '-c', code, json.dumps(asdict(cfg))], cwd=ROOT, check=True,
                         stdout=subprocess.PIPE, text=True).stdout
    bag, s, cached = json.loads(out.strip().splitlines()[-1])
    return Path(bag), s, cached


def holdings(probe: Probe) -> dict:
    """What this process's nodes hold, its malloc figures and (when tracing) the traced Python heap."""
    out = {**memory_holdings(probe), **rss_parts(), **malloc_stats()}
    import tracemalloc
    if tracemalloc.is_tracing():
        out['traced_mb'] = round(tracemalloc.get_traced_memory()[0] / 2**20, 1)
    return out


def child_curve(path: Path, probe: Probe, t0: float) -> list:
    """The child's samples as (wall_s since t0, flight_s or None, rss, hwm, extra), like RssSampler's."""
    import bisect
    if not path.exists():
        return []
    times = [t for t, _ in probe.image_times]
    out = []
    for line in path.read_text().splitlines():
        try:
            d = json.loads(line)
        except ValueError:   # a line cut by the child's exit
            continue
        i = bisect.bisect_right(times, d['t']) - 1
        flight = (probe.image_times[i][1] - probe.first_image_ns) * 1e-9 if i >= 0 else None
        extra = {k: v for k, v in d.items() if k not in ('t', 'rss_mb', 'hwm_mb')}
        out.append((d['t'] - t0, flight, d['rss_mb'], d['hwm_mb'], extra))
    return out


def cpu_s() -> dict:
    """User + system CPU seconds of this process and of its ended, waited-for children."""
    import resource
    usage = {'self': resource.getrusage(resource.RUSAGE_SELF), 'children': resource.getrusage(resource.RUSAGE_CHILDREN)}
    return {k: r.ru_utime + r.ru_stime for k, r in usage.items()}


def diag_value(diagnostics: dict, node: str, key: str):
    """The last value of `key` that node `node` (e.g. 'stereo' for /stereo_node) put on /diagnostics."""
    for name, d in diagnostics.items():
        if name.strip('/').split('/')[-1] == f'{node}_node':
            return d['values'].get(key, 0)
    return None


def at_wall(samples, wall_s: float):
    """The sample nearest wall time `wall_s` (None without samples)."""
    return min(samples, key=lambda s: abs(s[0] - wall_s)) if samples else None


def emit_growth_sites(first, last, n: int) -> None:
    """The allocation sites (project frames of the traceback) that grew most between two snapshots."""
    (s0, f0), (s1, f1) = first, last
    minutes = max(((f1 or 0) - (f0 or 0)) / 60, 1e-6)
    emit({'bench': 'memory_soak_tracemalloc', 'process': 'main', 'from_flight_min': round((f0 or 0) / 60, 2),
          'to_flight_min': round((f1 or 0) / 60, 2),
          'traced_growth_mb_per_flight_min': round(sum(d.size_diff for d in s1.compare_to(s0, 'filename')) / 1e6 / minutes, 2)})
    for site in growth_sites(s0, s1, n):
        emit({'bench': 'memory_soak_tracemalloc_site', 'process': 'main',
              'mb_per_flight_min': round(site['mb'] / minutes, 2), 'count_diff': site['count_diff'],
              'frames': site['frames']})


def slope_mb_per_min(samples, after_min: float):
    import numpy as np
    pts = [(f / 60, rss) for _, f, rss, _, _ in samples if f is not None and f / 60 >= after_min]
    if len(pts) < 3:
        return None
    x, y = np.array(pts).T
    if np.ptp(x) < 0.5:
        return None
    return float(np.polyfit(x, y, 1)[0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--minutes', type=float, default=6.0, help='simulated flight length, minutes')
    ap.add_argument('--fps', type=float, default=1.0, help='camera rate (the issue\'s survey is 5 fps; 1 fps '
                    'renders 5x faster and gives nearly the same keyframes)')
    ap.add_argument('--max-lines', type=int, default=12, help='lines of new ground before the block repeats')
    ap.add_argument('--line-length', type=float, default=150.0)
    ap.add_argument('--settle', type=float, default=2.0, help='minutes excluded from the slope (start-up)')
    ap.add_argument('--period', type=float, default=3.0, help='RSS sampling period, s')
    ap.add_argument('--params', default=str(ROOT / 'config' / 'replay.yaml'))
    ap.add_argument('--tracemalloc', type=int, default=0, metavar='N',
                    help='also trace Python allocations: the N sites that grew most between --settle and the '
                    'end of the bag (slows the replay: its RSS figures are not the reference ones); with '
                    '--processes 2 in the child process (bundle, stereo, map) only')
    ap.add_argument('--processes', type=int, choices=(1, 2), default=2, help='as `photogram-ros replay '
                    '--processes`; the child process is sampled too (figures with the prefix child_)')
    a = ap.parse_args()
    child_roles = ('bundle', 'stereo', 'map') if a.processes == 2 else ()
    trace_here = a.tracemalloc if not child_roles else 0

    cfg, dur_s = flight_config(a.minutes, a.fps, a.max_lines, a.line_length)
    emit({'machine': machine_info(), 'load_avg_before': os.getloadavg()})
    bag, sim_s, cached = simulate_in_child(cfg)
    emit({'bench': 'memory_soak_sim', 'bag': str(bag), 'flight_min': round(dur_s / 60, 2), 'fps': cfg.fps,
          'n_lines': cfg.n_lines, 'repeats': cfg.repeats, 'line_length_m': cfg.line_length_m,
          'render_s': round(sim_s, 1), 'from_cache': cached})

    import rclpy
    from photogram_ros.nodes.player_node import PlayerNode
    from photogram_ros.nodes.replay_session import ReplayOptions, run_replay
    probe = Probe().install()
    marks = {}
    play = PlayerNode.play

    def marked_play(self, *x, **k):
        try:
            return play(self, *x, **k)
        finally:
            marks['play_end'] = time.monotonic()
            sampler.sample()
            marks['play_end_flight_s'] = sampler.samples[-1][1]
            if trace_here and 'settle' in snaps:
                snaps['end'] = (tracemalloc.take_snapshot(), sampler.samples[-1][1])
            if child_roles:
                Path(f'{child_samples}.end').touch()
    PlayerNode.play = marked_play

    from photogram_ros.nodes.process_memory import limit_malloc_arenas
    limit_malloc_arenas()   # as photogram-ros does before rclpy.init() (cli.main)
    rclpy.init()
    snaps = {}
    if trace_here:
        import tracemalloc
        tracemalloc.start(8)
    baseline_rss, _ = RssSampler.read()
    cpu0 = cpu_s()
    sampler = RssSampler(probe, a.period)
    sampler.extra = lambda: holdings(probe)
    sampler.start()
    out = Path(tempfile.mkdtemp(prefix='memory_soak_'))
    child_samples = out / 'child_samples.jsonl'
    if child_roles:
        site = Probe.child_sitecustomize(out / 'probe_site', ROOT / 'bench')
        os.environ['PYTHONPATH'] = os.pathsep.join([str(site)] + [v for v in [os.environ.get('PYTHONPATH')] if v])
        os.environ[Probe.CHILD_ENV] = str(out / 'child_probe.json')
        os.environ[Probe.CHILD_SAMPLES_ENV] = str(child_samples)
        if a.tracemalloc:
            os.environ[Probe.CHILD_TRACEMALLOC_ENV] = str(a.tracemalloc)
    last_log = [0.0]

    def child_rss() -> str:
        if not child_roles or not child_samples.exists():
            return ''
        with open(child_samples, 'rb') as f:   # the last complete line
            f.seek(max(0, os.path.getsize(child_samples) - 4096))
            lines = f.read().decode(errors='replace').splitlines()
        try:
            d = json.loads(lines[-1])
        except (ValueError, IndexError):
            return ''
        return f', child RSS {d["rss_mb"]:.0f} MB (heap {d.get("heap_mb")}, free {d.get("free_mb")})'

    def progress_extra():
        h = holdings(probe)
        s = sampler.samples[-1] if sampler.samples else None
        if 'settle' not in snaps and s is not None and (s[1] or 0) >= a.settle * 60:
            snaps['settle'] = (tracemalloc.take_snapshot() if trace_here else None, s[1])
            if child_roles:
                Path(f'{child_samples}.settle').touch()
        if time.monotonic() - last_log[0] > 30 and sampler.samples:
            last_log[0] = time.monotonic()
            s = sampler.samples[-1]
            log(f'[soak] wall {s[0]:6.0f} s, flight {(s[1] or 0) / 60:5.2f} min, RSS {s[2]:.0f} MB, '
                f'peak {s[3]:.0f} MB{child_rss()}, {h}')
        return h
    sampler.extra = progress_extra
    try:
        res = run_replay(ReplayOptions(bag=str(bag), out=str(out), params_file=a.params, progress=False,
                                       drain_timeout_s=1800.0, child_roles=child_roles))
    finally:
        sampler.stop()
        rclpy.try_shutdown()
        probe.uninstall()
        PlayerNode.play = play
        for k in (Probe.CHILD_ENV, Probe.CHILD_SAMPLES_ENV, Probe.CHILD_TRACEMALLOC_ENV):
            os.environ.pop(k, None)
    run = res['run']
    cpu = {k: round(v - cpu0[k], 1) for k, v in cpu_s().items()}
    samples = sampler.samples
    play_end_wall = marks.get('play_end', time.monotonic()) - sampler.t0
    child = child_curve(child_samples, probe, sampler.t0) if child_roles else []

    def with_child(s) -> dict:
        """The child's figures at the time of parent sample `s`, and both processes' sum."""
        c = at_wall(child, s[0])
        if c is None:
            return {}
        return {'child_rss_mb': round(c[2], 1), 'child_peak_rss_mb': round(c[3], 1),
                'total_rss_mb': round(s[2] + c[2], 1), **{f'child_{k}': v for k, v in c[4].items()}}

    for m in CHECKPOINTS_MIN:
        hit = next((s for s in samples if s[1] is not None and s[1] >= m * 60), None)
        if hit is None:
            break
        emit({'bench': 'memory_soak', 'flight_min': m, 'wall_s': round(hit[0], 1), 'rss_mb': round(hit[2], 1),
              'peak_rss_mb': round(hit[3], 1), 'rss_over_start': round(hit[2] / baseline_rss, 2), **hit[4],
              **with_child(hit)})
    end_play = min(samples, key=lambda s: abs(s[0] - play_end_wall))
    final = samples[-1]
    for label, s in (('end_of_bag', end_play), ('after_final_adjustment', final)):
        emit({'bench': 'memory_soak', 'at': label, 'flight_min': round((s[1] or 0) / 60, 2), 'wall_s': round(s[0], 1),
              'rss_mb': round(s[2], 1), 'peak_rss_mb': round(s[3], 1), **s[4], **with_child(s)})
    in_bag = [s for s in samples if s[0] <= play_end_wall]
    child_in_bag = [c for c in child if c[0] <= play_end_wall]
    slope = slope_mb_per_min(in_bag, a.settle)
    last10 = max(a.settle, run['bag_s'] / 60 - 10)

    def rounded(v):
        return None if v is None else round(v, 2)
    slopes = {'rss_slope_mb_per_flight_min_last_10_min': rounded(slope_mb_per_min(in_bag, last10))}
    if child_roles:
        total = [(s[0], s[1], s[2] + c[2], 0, {}) for s in in_bag for c in [at_wall(child_in_bag, s[0])] if c]
        slopes.update({
            'child_rss_slope_mb_per_flight_min_after_settle': rounded(slope_mb_per_min(child_in_bag, a.settle)),
            'child_rss_slope_mb_per_flight_min_last_10_min': rounded(slope_mb_per_min(child_in_bag, last10)),
            'total_rss_slope_mb_per_flight_min_after_settle': rounded(slope_mb_per_min(total, a.settle)),
            'total_rss_slope_mb_per_flight_min_last_10_min': rounded(slope_mb_per_min(total, last10)),
            'child_peak_rss_mb': round(max(c[3] for c in child), 1) if child else None})
    after = [s for s in samples if s[1] is not None and s[1] / 60 >= a.settle and s[0] <= play_end_wall]
    emit({'bench': 'memory_soak_summary', 'flight_min': round(run['bag_s'] / 60, 2), 'wall_s': round(run['wall_s'], 1),
          'real_time_factor': round(run['real_time_factor'], 3), 'frames': run['frames'],
          'keyframes': len(probe.kf_published), 'rss_before_graph_mb': round(baseline_rss, 1),
          'peak_rss_mb': round(sampler.peak_mb, 1), 'peak_over_start': round(sampler.peak_mb / baseline_rss, 2),
          'rss_slope_mb_per_flight_min_after_settle': None if slope is None else round(slope, 2),
          'settle_min': a.settle, 'processes': a.processes, **slopes,
          'peak_growth_after_settle_mb': round(after[-1][3] - after[0][3], 1) if len(after) > 1 else None,
          'projected_growth_30min_mb': None if slope is None else round(slope * 30, 0),
          'flat': None if slope is None else slope < FLAT_MB_PER_MIN, 'flat_threshold_mb_per_min': FLAT_MB_PER_MIN,
          'samples': len(samples), 'waited_for_downstream_s': run.get('waited_for_downstream_s'),
          # CPU of the replay, this process and the graph's child (ended by now): the same work costs
          # about the same CPU whatever else the machine runs, unlike the real-time factor
          'cpu_s': cpu['self'], 'child_cpu_s': cpu['children'],
          # lost work: keyframes stereo dropped before pairing them (their pose came too late: a backlog)
          **{f'{node}_{k}': diag_value(res['diagnostics'], node, k) for node, k in
             (('stereo', 'keyframes_dropped_unpaired'), ('stereo', 'pairs_done'), ('map', 'clouds'))},
          'load_avg_after': os.getloadavg()})
    if 'end' in snaps and snaps['settle'][0] is not None:
        emit_growth_sites(snaps['settle'], snaps['end'], a.tracemalloc)
        for g in big_blocks(snaps['end'][0], a.tracemalloc):
            emit({'bench': 'memory_soak_big_blocks', 'process': 'main', 'at': 'end_of_bag', **g})
    sites = Path(f'{child_samples}.sites.json')
    if sites.exists() and 'settle' in snaps:
        # The child snapshots within one sampling period of each mark: minutes are approximate.
        minutes = max(((marks.get('play_end_flight_s') or 0) - (snaps['settle'][1] or 0)) / 60, 1e-6)
        for site in json.loads(sites.read_text()):
            emit({'bench': 'memory_soak_tracemalloc_site', 'process': 'child',
                  'mb_per_flight_min': round(site['mb'] / minutes, 2), 'count_diff': site['count_diff'],
                  'frames': site['frames']})
    big = Path(f'{child_samples}.big_blocks.json')
    if big.exists():
        for g in json.loads(big.read_text()):
            emit({'bench': 'memory_soak_big_blocks', 'process': 'child', 'at': 'end_of_bag', **g})
    # The raw curves, every ~30 s of flight, for plotting.
    for name, rows in (('memory_soak_curve', samples), ('memory_soak_child_curve', child)):
        if rows:
            emit({'bench': name, 'columns': ['flight_min', 'rss_mb', 'peak_rss_mb', *CURVE], 'rows': _curve(rows)})
    return 0


def _curve(samples, every_s: float = 30.0) -> list:
    curve, last = [], -1e9
    for _w, f, rss, hwm, x in samples:
        if f is not None and f - last >= every_s:
            curve.append([round(f / 60, 2), round(rss), round(hwm)] + [x.get(k) for k in CURVE])
            last = f
    return curve


if __name__ == '__main__':
    sys.exit(main())
