"""Stop means stop (issue 48): `run` with a camera that never ends (a looping photo folder, as a live camera
goes on producing after landing) stopped by SIGTERM: every source stops at once, the end of flight runs on
what was taken with progress lines, a second signal skips to the products of what exists, the end of
flight has a time bound, and a flight that mapped nothing exits 5 (docs/faults.md)."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from conftest import ROOT, shared_data
from helpers.processes import reaped

CLI = [sys.executable, '-m', 'photogram_ros.cli']


def _tree_pids(pid: int) -> list[int]:
    """`pid` and its descendants (from /proc: the run's child process holds bundle, stereo and map)."""
    children: dict[int, list[int]] = {}
    for stat in Path('/proc').glob('[0-9]*/stat'):
        try:
            fields = stat.read_text().rsplit(')', 1)[1].split()
            children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
        except (OSError, ValueError, IndexError):
            pass
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(children.get(p, []))
    return out


def _rss_mb(pid: int) -> float:
    """The RSS of `pid` and its descendants, MB."""
    total = 0.0
    for p in _tree_pids(pid):
        try:
            for line in Path(f'/proc/{p}/status').read_text().splitlines():
                if line.startswith('VmRSS:'):
                    total += int(line.split()[1]) / 1024.0
        except (OSError, ValueError):
            pass
    return total


def looping_run(tmp_path: Path, photos: Path, stop_after_s: float, signals=(signal.SIGTERM,),
                 gap_s: float = 5.0, extra: tuple = (), bound_s: float = 600.0):
    """`run` of a camera_node looping over `photos` (rate 0, as fast as the tracker takes them), the signals
    sent `stop_after_s` after it runs (then `gap_s` apart). Returns (exit status, output, seconds from the
    first signal to the exit, RSS peaks MB {'before': in flight, 'after': the end-of-flight steps, 'products': the
    products}, products folder)."""
    cfg = tmp_path / 'loop.yaml'
    cfg.write_text(f'camera_node:\n  ros__parameters:\n    source: {photos}\n    rate: 0.0\n    loop: true\n'
                   f'map_node:\n  ros__parameters:\n    map_dir: {tmp_path / "map"}\n')
    products = tmp_path / 'products'
    proc = subprocess.Popen(CLI + ['run', '--params', str(cfg), '--nodes', 'camera,tracker,bundle,stereo,map',
                                   '--out', str(products), *extra], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    running = threading.Event()
    rss = {'before': 0.0, 'after': 0.0, 'products': 0.0}
    phase = ['before']

    def read_output():
        for line in proc.stdout:
            lines.append(line)
            if 'photogram_ros running' in line:
                running.set()
            if 'end of flight: steps done' in line:
                phase[0] = 'products'
        running.set()

    def sample():
        while proc.poll() is None:
            rss[phase[0]] = max(rss[phase[0]], _rss_mb(proc.pid))
            time.sleep(0.2)

    threading.Thread(target=read_output, daemon=True).start()
    threading.Thread(target=sample, daemon=True).start()
    with reaped(proc):
        assert running.wait(300) and proc.poll() is None, ''.join(lines)[-3000:]
        time.sleep(stop_after_s)
        phase[0] = 'after'
        t_signal = time.monotonic()
        for k, sig in enumerate(signals):
            if k:
                time.sleep(gap_s)
            proc.send_signal(sig)
        proc.wait(timeout=bound_s)
        took_s = time.monotonic() - t_signal
    time.sleep(0.5)
    return proc.returncode, ''.join(lines), took_s, rss, products


def test_a_looping_camera_stopped_by_sigterm_stops_and_says_mapping_failed(tmp_path):
    """The fast variant: a looping folder of white photos (nothing to map). SIGTERM stops the camera at once,
    the end-of-flight steps say what they do, the report is written, and the exit status is 5 (MAPPING
    FAILED, as `replay`)."""
    from test_replay_unmappable import write_white_wall
    photos = write_white_wall(tmp_path / 'wall', n=4)
    rc, out, took_s, _, products = looping_run(tmp_path, photos, stop_after_s=8.0, bound_s=300.0)
    assert rc == 5, out[-3000:]
    assert 'SIGTERM: stopped camera after' in out, out[-3000:]
    assert 'end of flight: 0 s: final adjustment' in out or 'final adjustment (RSS' in out, out[-3000:]
    assert out.strip().splitlines()[-1].startswith('MAPPING FAILED: '), out[-3000:]
    assert (products / 'report.md').exists() and (products / 'report.json').exists()
    assert 'Traceback' not in out


def test_a_second_signal_skips_to_writing_what_exists(tmp_path):
    """SIGTERM, then SIGINT while the end of flight runs: the steps left are skipped, said, and the
    products of what exists are written (the report among them)."""
    from test_replay_unmappable import write_white_wall
    photos = write_white_wall(tmp_path / 'wall', n=4)
    rc, out, _, _, products = looping_run(tmp_path, photos, stop_after_s=8.0,
                                              signals=(signal.SIGTERM, signal.SIGINT), gap_s=0.3, bound_s=300.0)
    # Both signals may be pending when Python next runs a handler: it runs them in signal-number order, so
    # either may be the one said to come again.
    assert re.search(r'SIG(INT|TERM) again: skipping the end-of-flight steps left', out), out[-3000:]
    assert rc != 0 and (products / 'report.md').exists(), out[-3000:]
    assert 'Traceback' not in out


def end_of_flight_graph(release: threading.Event | None = None):
    """A stand-in graph for commands/run.finish_within_bounds: (graph, its nodes); with `release`, the tracker's
    end-of-flight step hangs until it is set (at most 30 s). Each node counts its calls."""
    from photogram_ros.nodes.graph import Graph

    class Node:
        def __init__(self, hang=False):
            self.hang, self.called = hang, 0

        def flush(self):
            self.called += 1
            if self.hang:
                release.wait(30)

        finish = finish_coverage = flush

    nodes = {'tracker': Node(hang=release is not None), 'bundle': Node(), 'stereo': Node(), 'map': Node()}
    graph = SimpleNamespace(spec=SimpleNamespace(roles=tuple(nodes)), child=None, nodes=nodes,
                            counts=lambda: {}, problems=lambda role: [], drain=lambda **kw: {})
    graph.finish_flight = lambda **kw: Graph.finish_flight(graph, **kw)
    return graph, nodes


def test_the_end_of_flight_is_cut_short_past_its_time_bound():
    """finish_within_bounds: a step that never ends is cut short past the bound; the steps left are skipped
    and the FlightEnd says so (not a final adjustment claimed)."""
    from photogram_ros.commands.run import finish_within_bounds

    release = threading.Event()
    said: list[str] = []
    graph, nodes = end_of_flight_graph(release)
    skip = threading.Event()
    t0 = time.monotonic()
    end = finish_within_bounds(graph, skip, timeout_s=1.0, max_rss_mb=0.0, say=said.append)
    release.set()
    assert time.monotonic() - t0 < 25.0   # the bound (1 s) and the running step's 10 s grace
    assert skip.is_set() and end.final_adjustment == 'failed', (end, said)
    assert any('--end-timeout-s' in s for s in said), said
    time.sleep(0.2)
    assert nodes['bundle'].called == 0 and nodes['stereo'].called == 0   # the steps left were skipped


def test_stop_sources_stops_the_camera_and_the_mavlink_link():
    """Graph.stop_sources calls each source's stop_input and names it; other nodes are left alone."""
    from photogram_ros.nodes.graph import Graph
    calls = []
    nodes = {r: SimpleNamespace(stop_input=lambda r=r: calls.append(r)) for r in ('camera', 'mavlink')}
    nodes['tracker'] = SimpleNamespace()
    graph = SimpleNamespace(child=None, nodes=nodes)
    assert Graph.stop_sources(graph) == ['camera', 'mavlink'] and calls == ['camera', 'mavlink']


@pytest.mark.slow
def test_a_looping_real_survey_stopped_after_60_s_ends_within_bounds(tmp_path):
    """The issue's case: a real survey folder (toledo, 42 photos) played in a loop, SIGTERM after 60 s:
    `run` exits within 2 minutes with products and a report, and its RSS in the end-of-flight steps and while
    making the products stays within its in-flight peak (before the fix: 2.1 -> 6.6 GB as it went on taking
    keyframes); the end of flight keeps to the stop budget (--stop-budget-s) and says what it left out."""
    src = shared_data('photos', 'toledo', 'images')
    photos = tmp_path / 'photos'
    shutil.copytree(src, photos)
    rc, out, took_s, rss, products = looping_run(tmp_path, photos, stop_after_s=60.0, bound_s=900.0)
    report = json.loads((products / 'report.json').read_text())
    print(f"toledo loop: SIGTERM -> exit {took_s:.0f} s, RSS peaks: in flight {rss['before']:.0f} MB, end-of-flight "
          f"steps {rss['after']:.0f} MB, products {rss['products']:.0f} MB, {report['run'].get('frames')} frames")
    assert rc in (0, 4), out[-3000:]
    assert 'SIGTERM: stopped camera after' in out, out[-3000:]
    # bench/results/faults_stop_8e6b4f7.jsonl (load 4-8 on 2 cores): SIGTERM to exit 66.0 s with 41 keyframes
    # taken (before the stop budget: 240.2 s with 73, faults_stop_8d7542e): the steps within --stop-budget-s 45
    # (51 s: the final adjustment of 41 keyframes 39.7 s), the products from the in-flight map in 12 s; RSS 0.874x
    # the in-flight peak in the end-of-flight steps, 0.424x making the products. The exit's gate: 1.5x the 66.0 s
    # (faults_stop_9ffc7e7.jsonl at load 3-5: 41.8 s, 45 keyframes, final adjustment 18.6 s).
    # RSS never above the in-flight peak, as the issue asks.
    assert took_s < 99.0, (took_s, out[-3000:])
    assert 'end of flight: a stopped flight: the steps share --stop-budget-s 45 s' in out, out[-3000:]
    if report['run'].get('end_of_flight_skipped'):   # what the budget left out is said, with the way to the rest
        assert 'export' in out and '--densify' in out.split('end of flight within --stop-budget-s')[1], out[-3000:]
    assert rss['after'] <= rss['before'], rss
    assert rss['products'] <= rss['before'], rss
    assert (products / 'report.md').exists() and (products / 'cloud.las').stat().st_size > 0


def test_a_stopped_flight_s_budget_is_handed_to_each_step_in_order():
    """Graph.finish_flight with budget_s: the tracker gets TRACKER_SHARE of it for its queue (the frames it has
    not taken then are dropped and said), the adjuster what is left but the stereo and map share, stereo what is
    left; without a budget no step gets an argument (the flight's own end: every step to its end)."""
    import collections

    from photogram_ros.nodes.graph import STEREO_AND_MAP_SHARE, TRACKER_SHARE, Graph

    class Node:
        def __init__(self):
            self.kwargs = []

        def flush(self, **kw):
            self.kwargs.append(kw)

        finish = finish_coverage = flush

    def graph_of():
        nodes = {'tracker': Node(), 'bundle': Node(), 'stereo': Node(), 'map': Node()}
        queue = nodes['tracker'].queue = collections.deque(range(7))   # 7 frames it has not taken

        def drop_queued(keep=0):
            n = max(len(queue) - keep, 0)
            for _ in range(n):
                queue.pop()
            return n
        nodes['tracker'].drop_queued = drop_queued
        return SimpleNamespace(spec=SimpleNamespace(roles=tuple(nodes)), child=None, nodes=nodes,
                               counts=lambda: {}, problems=lambda role: []), nodes

    graph, nodes = graph_of()
    said: list[str] = []
    settles: list[float] = []
    nodes['bundle'].end_budget = lambda budget_s: nodes['bundle'].kwargs.append({'end_budget': budget_s})
    end = Graph.finish_flight(graph, settle=lambda timeout_s=2.0: settles.append(timeout_s), say=said.append,
                              budget_s=40.0)
    # The adjuster's worker keeps to the budget from the stop on (before the tracker's step), then finish.
    assert nodes['bundle'].kwargs.pop(0)['end_budget'] == pytest.approx((1 - STEREO_AND_MAP_SHARE) * 40.0, abs=0.5)
    assert nodes['tracker'].kwargs[0]['max_wait_s'] == pytest.approx(TRACKER_SHARE * 40.0, abs=0.5)
    assert nodes['bundle'].kwargs[0]['budget_s'] == pytest.approx((1 - STEREO_AND_MAP_SHARE) * 40.0, abs=0.5)
    assert 0 < nodes['stereo'].kwargs[0]['budget_s'] <= 40.0 and nodes['map'].kwargs == [{}]
    assert not nodes['tracker'].queue and any('7 frames the tracker had not taken' in s for s in said), said
    assert any('7 frames' in s for s in end.skipped) and all(0 < t <= 4.0 for t in settles), (end, settles)
    graph, nodes = graph_of()
    end = Graph.finish_flight(graph, settle=lambda timeout_s=2.0: None)
    assert [n.kwargs for n in nodes.values()] == [[{}]] * 4 and len(nodes['tracker'].queue) == 7
    assert not end.skipped


def test_the_adjuster_leaves_out_what_does_not_fit_in_its_budget(monkeypatch):
    """AdjustmentStage.finish with a budget shorter than its final adjustment's estimate: the waiting keyframes
    are counted in keyframes_skipped_at_end and said, the final adjustment still runs; without a budget every
    waiting keyframe is taken."""
    import numpy as np

    from photogram_ros.stages.adjustment import AdjustmentOutcome, AdjustmentParams, AdjustmentStage

    def stage_with(n_waiting: int):
        stage = AdjustmentStage(AdjustmentParams())
        stage.at = SimpleNamespace(block=SimpleNamespace(n_oriented=100, keyframes=lambda: []),
                                   retry_unregistered=lambda: 0, origin=None)
        monkeypatch.setattr(stage, 'full_adjustment', lambda: AdjustmentOutcome('done', 'converged'))
        for k in range(n_waiting):
            stage._pending[k * 10**9] = (0.0, np.arange(3), np.zeros((3, 2)), {})
        return stage

    taken = []
    stage = stage_with(5)
    stage._full_s, stage._full_n = 30.0, 100   # the last full adjustment: 30 s for 100 keyframes
    out = stage.finish(lambda rec, publish=True: taken.append(rec.stamp_ns), budget_s=10.0)
    assert out.status == 'done' and taken == [], taken
    assert stage.diag.counts()['keyframes_skipped_at_end'] == 5
    assert any('5 keyframes waiting for the adjuster were left out' in p for _, p in stage.diag.problems)
    stage = stage_with(5)
    stage._full_s, stage._full_n = 30.0, 100
    assert stage.finish(lambda rec, publish=True: taken.append(rec.stamp_ns)).status == 'done'
    assert len(taken) == 5 and 'keyframes_skipped_at_end' not in stage.diag.counts()


@pytest.mark.parametrize('value', ['-1', '3601', 'nan'])
def test_a_stop_budget_out_of_its_range_is_refused_before_any_node_starts(value):
    """--stop-budget-s: 0 (no budget) to 3600 s; anything else is a configuration error (exit 2, one line)."""
    res = subprocess.run(CLI + ['run', '--nodes', 'tracker', '--stop-budget-s', value], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and '--stop-budget-s must be 0 (no budget) to 3600 s' in res.stderr, res.stderr[-2000:]
