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
minute) after `--settle` minutes, and what the nodes hold at each checkpoint (bundle keyframes and
tie points, and how many of them are still in memory rather than frozen/spilled; stereo keyframes,
map tiles) to tell which one grows. `--tracemalloc N` adds the N Python allocation sites that grew
most after the settle time (slower replay: use it to find a leak, not for the reference figures). Baseline in the same run: the
process's RSS just before the graph starts, so growth is reported as a ratio to it.

    .venv/bin/python bench/memory_soak.py               # ~6 min of flight, about 10 minutes here
    .venv/bin/python bench/memory_soak.py --minutes 30  # the issue's 30-minute flight (about 1.5 h here)
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
from replay_probe import Probe, RssSampler  # noqa: E402

CHECKPOINTS_MIN = (1, 2, 5, 10, 15, 20, 25, 30, 45, 60)
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
    """What the nodes keep in memory now (read from another thread: sizes only)."""
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
    return out


def emit_growth_sites(first, last, n: int) -> None:
    """The allocation sites (project frames of the traceback) that grew most between two snapshots."""
    (s0, f0), (s1, f1) = first, last
    minutes = max(((f1 or 0) - (f0 or 0)) / 60, 1e-6)
    emit({'bench': 'memory_soak_tracemalloc', 'from_flight_min': round((f0 or 0) / 60, 2),
          'to_flight_min': round((f1 or 0) / 60, 2),
          'traced_growth_mb_per_flight_min': round(sum(d.size_diff for d in s1.compare_to(s0, 'filename')) / 1e6 / minutes, 2)})
    for d in s1.compare_to(s0, 'traceback')[:n]:
        frames = [f'{Path(f.filename).name}:{f.lineno}' for f in d.traceback
                  if 'photogram_ros' in f.filename or '/bench/' in f.filename or 'rclpy' in f.filename]
        emit({'bench': 'memory_soak_tracemalloc_site', 'mb_per_flight_min': round(d.size_diff / 1e6 / minutes, 2),
              'count_diff': d.count_diff, 'frames': frames[-4:] or [f'{Path(f.filename).name}:{f.lineno}' for f in d.traceback][-2:]})


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
                    'end of the bag (slows the replay: its RSS figures are not the reference ones)')
    a = ap.parse_args()

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
            if a.tracemalloc and 'settle' in snaps:
                snaps['end'] = (tracemalloc.take_snapshot(), sampler.samples[-1][1])
    PlayerNode.play = marked_play

    rclpy.init()
    snaps = {}
    if a.tracemalloc:
        import tracemalloc
        tracemalloc.start(8)
    baseline_rss, _ = RssSampler.read()
    sampler = RssSampler(probe, a.period)
    sampler.extra = lambda: holdings(probe)
    sampler.start()
    out = Path(tempfile.mkdtemp(prefix='memory_soak_'))
    last_log = [0.0]

    def progress_extra():
        h = holdings(probe)
        s = sampler.samples[-1] if sampler.samples else None
        if a.tracemalloc and 'settle' not in snaps and s is not None and (s[1] or 0) >= a.settle * 60:
            snaps['settle'] = (tracemalloc.take_snapshot(), s[1])
        if time.monotonic() - last_log[0] > 30 and sampler.samples:
            last_log[0] = time.monotonic()
            s = sampler.samples[-1]
            log(f'[soak] wall {s[0]:6.0f} s, flight {(s[1] or 0) / 60:5.2f} min, RSS {s[2]:.0f} MB, '
                f'peak {s[3]:.0f} MB, {h}')
        return h
    sampler.extra = progress_extra
    try:
        res = run_replay(ReplayOptions(bag=str(bag), out=str(out), params_file=a.params, progress=False,
                                       drain_timeout_s=1800.0))
    finally:
        sampler.stop()
        rclpy.try_shutdown()
        probe.uninstall()
        PlayerNode.play = play
    run = res['run']
    samples = sampler.samples
    play_end_wall = marks.get('play_end', time.monotonic()) - sampler.t0

    for m in CHECKPOINTS_MIN:
        hit = next((s for s in samples if s[1] is not None and s[1] >= m * 60), None)
        if hit is None:
            break
        emit({'bench': 'memory_soak', 'flight_min': m, 'wall_s': round(hit[0], 1), 'rss_mb': round(hit[2], 1),
              'peak_rss_mb': round(hit[3], 1), 'rss_over_start': round(hit[2] / baseline_rss, 2), **hit[4]})
    end_play = min(samples, key=lambda s: abs(s[0] - play_end_wall))
    final = samples[-1]
    for label, s in (('end_of_bag', end_play), ('after_final_adjustment', final)):
        emit({'bench': 'memory_soak', 'at': label, 'flight_min': round((s[1] or 0) / 60, 2), 'wall_s': round(s[0], 1),
              'rss_mb': round(s[2], 1), 'peak_rss_mb': round(s[3], 1), **s[4]})
    slope = slope_mb_per_min([s for s in samples if s[0] <= play_end_wall], a.settle)
    after = [s for s in samples if s[1] is not None and s[1] / 60 >= a.settle and s[0] <= play_end_wall]
    emit({'bench': 'memory_soak_summary', 'flight_min': round(run['bag_s'] / 60, 2), 'wall_s': round(run['wall_s'], 1),
          'real_time_factor': round(run['real_time_factor'], 3), 'frames': run['frames'],
          'keyframes': len(probe.kf_published), 'rss_before_graph_mb': round(baseline_rss, 1),
          'peak_rss_mb': round(sampler.peak_mb, 1), 'peak_over_start': round(sampler.peak_mb / baseline_rss, 2),
          'rss_slope_mb_per_flight_min_after_settle': None if slope is None else round(slope, 2),
          'settle_min': a.settle,
          'peak_growth_after_settle_mb': round(after[-1][3] - after[0][3], 1) if len(after) > 1 else None,
          'projected_growth_30min_mb': None if slope is None else round(slope * 30, 0),
          'flat': None if slope is None else slope < FLAT_MB_PER_MIN, 'flat_threshold_mb_per_min': FLAT_MB_PER_MIN,
          'samples': len(samples), 'load_avg_after': os.getloadavg()})
    if 'end' in snaps:
        emit_growth_sites(snaps['settle'], snaps['end'], a.tracemalloc)
    # The raw curve, every ~30 s of flight, for plotting.
    curve, last = [], -1e9
    for w, f, rss, hwm, _ in samples:
        if f is not None and f - last >= 30:
            curve.append([round(f / 60, 2), round(rss), round(hwm)])
            last = f
    emit({'bench': 'memory_soak_curve', 'columns': ['flight_min', 'rss_mb', 'peak_rss_mb'], 'rows': curve})
    return 0


if __name__ == '__main__':
    sys.exit(main())
