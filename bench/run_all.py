"""Run every bench that feeds a rendered figure (bench/render_figures.py), most important first, each writing its
result file to bench/results/<name>_<commit>.jsonl.

    .venv/bin/python bench/run_all.py --list                 # each bench, its command and expected minutes
    .venv/bin/python bench/run_all.py --groups               # the named groups, their benches and minutes
    ROS_DOMAIN_ID=N .venv/bin/python bench/run_all.py [--only a,b] [--skip c] [--budget-min 45] [--dry-run]
    ROS_DOMAIN_ID=N .venv/bin/python bench/run_all.py --only long_short   # a named group (GROUPS below)

From a clean clone beside ../shared (the benches read ../shared/data):

    git clone /work/main /work/X && cd /work/X && ln -s /work/main/.venv .venv
    ROS_DOMAIN_ID=N .venv/bin/python bench/run_all.py --budget-min 45

Each bench runs in its own work folder (/tmp/run_all_<commit>/<name>, or --work) with its output sent to
<work>/<name>.log; the result lines it wrote are copied to bench/results/<name>_<commit7>.jsonl (also after a
failure, when it wrote some: the summary says so). A failing bench does not stop the others. `--budget-min`: no
new bench starts once that many minutes have passed since the start (a started bench runs to its end, bounded
by its own timeout). The run's own record (one line a bench: exit, wall minutes, result file) goes to
bench/results/run_all_<commit7>.jsonl; `--list` takes each bench's expected minutes from the newest such record
that ran it, else from the estimate below (minutes on this 2-core machine at a load of 2-4, from earlier result
files' wall times). Commit the new result files, then `.venv/bin/python bench/render_figures.py`.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import ResultWriter, tree_state  # noqa: E402

RESULTS = ROOT / 'bench' / 'results'
DATA = ROOT.parent / 'shared' / 'data'
PY = str(ROOT / '.venv' / 'bin' / 'python')


@dataclass(frozen=True)
class Bench:
    """One bench: `name` (its result file's prefix), `argv` (after the interpreter; {out} the result file it
    writes, {work} its work folder, {data} ../shared/data), `produced` (a glob under {work} of the file it writes
    when it does not take {out}), `minutes` (expected on this machine), `feeds` (the figures)."""
    name: str
    argv: tuple
    minutes: float
    feeds: str
    produced: str = ''
    ros: bool = False
    timeout_min: float = 0.0         # 0: 3x the expected minutes, at least 10
    needs: tuple = field(default_factory=tuple)   # paths (with {data}) that must exist

    def command(self, out: str, work: str) -> list[str]:
        return [PY] + [a.format(out=out, work=work, data=str(DATA)) for a in self.argv]


STEREO_SCENES = tuple(f'{{data}}/stereo/{s}' for s in ('tsukuba', 'venus', 'cones', 'teddy'))

# Most important first: the real sets (README headline, real-surveys, agreement and verdict tables), the 20 MP
# stage budget and the simulated 20 MP flight, then the component benches, then the long simulated ones.
BENCHES: tuple[Bench, ...] = (
    Bench('real_surveys', ('bench/real_surveys.py', '--out', '{work}'), 16,
          'README headline real rows; real-surveys, real-agreement, real-verdicts (brighton, toledo, seneca, phantom3)',
          produced='real_surveys.jsonl', ros=True, needs=('{data}/photos/toledo',)),
    Bench('real_surveys_variants', ('bench/real_surveys.py', '--only', 'none', '--variants', '--noisy', 'brighton,toledo',
                                    '--out', '{work}'), 15,
          'real-surveys: every other photo, four geotags moved, two sites, geotags scattered 17 m',
          produced='real_surveys.jsonl', ros=True, needs=('{data}/photos/toledo',)),
    Bench('stage_budget', ('bench/stage_budget.py', '--out', '{out}'), 16, 'stage-budget (20 MP, toledo upscaled)',
          needs=('{data}/photos/toledo',)),
    Bench('inflight_20mp', ('bench/inflight_20mp.py', '--flight', 'sim', '--photos', '317', '--periods', '1,0.7',
                            '--export-dsm',
                            '--set', 'stereo.cpu_share=0.5', '--set', 'stereo.worker_nice=10', '--set',
                            'stereo.cv_threads=1', '--set', 'map.cv_threads=1', '--set', 'map.ortho_cpu_share=0.15',
                            '--set', 'tracker.cv_threads=2', '--out', '{out}'), 24,
          'inflight-20mp (the simulated 317-photo survey at one photo per 1 s and per 0.7 s, each exported with '
          '--densify: the 0.7 s DSM against the 1 s one), speed "20 MP photos in flight" (add ~40 min the first '
          'time: the rendered flight is cached in /tmp/photogram_bench_cache)', ros=True),
    Bench('sample_flight', ('bench/sample_flight.py', '--work', '{work}', '--out', '{out}'), 6,
          'simulated: the sample flight end to end, its DSM, with its targets file; speed: replay of the sample bag; '
          'README sample flight row', ros=True),
    Bench('stereo_middlebury', ('bench/stereo_middlebury.py', *STEREO_SCENES, '--out', '{out}'), 1,
          'components: stereo on Middlebury; README stereo row', needs=('{data}/stereo/venus',)),
    Bench('bundle_bal', ('bench/bundle_bal.py', '{data}/bal/problem-49-7776-pre.txt', '--peers', '--out', '{out}'), 8,
          'components: BAL against SciPy (and Ceres when pycolmap is installed); README BAL row',
          needs=('{data}/bal/problem-49-7776-pre.txt',)),
    Bench('mavlink_parse', ('bench/mavlink_parse.py', '--out', '{out}'), 1, 'components: MAVLink parsing'),
    Bench('stereo_speed', ('bench/stereo_speed.py', '--out', '{out}'), 3, 'components: stereo speed'),
    Bench('fusion_throughput', ('bench/fusion_throughput.py', '--out', '{out}'), 2, 'components: map fusion'),
    Bench('tracker_fps', ('bench/tracker_fps.py', '--out', '{out}'), 3, 'components: tracker accuracy and frame rate'),
    Bench('window_latency', ('bench/window_latency.py', '--out', '{out}'), 2, 'speed: sliding-window update'),
    Bench('target_detection', ('bench/target_detection.py', '--out', '{out}'), 2, 'control: target detection'),
    Bench('replay_throughput', ('bench/replay_throughput.py', '--out', '{out}'), 1,
          'speed: bag player; the simulator\'s rendering'),
    Bench('inflight_chain', ('bench/inflight_chain.py', '--out', '{work}', '--results', '{work}'), 56,
          'inflight-chain (every real set, every and every other photo); README seneca in-flight rows',
          produced='inflight_chain_*.jsonl', ros=True, needs=('{data}/photos/seneca_part',)),
    Bench('block_verdicts', ('bench/block_verdicts.py', '--out', '{work}', '--result', '{out}'), 50,
          'real-verdicts (brighton and toledo variants, tipped and folded blocks); held-out heights rows', ros=True,
          needs=('{data}/photos/toledo',)),
    Bench('held_out_proxies', ('bench/held_out_proxies.py', '--out', '{work}'), 25,
          'held-out: consumer-camera geotags; README held-out row', produced='held_out_proxies.jsonl', ros=True,
          needs=('{data}/photos/toledo',)),
    Bench('e2e_realtime', ('bench/e2e_realtime.py', '--out', '{out}'), 12,
          'speed: real time (5 fps 640x480 survey through replay); README real time row', ros=True),
    Bench('ground_stream', ('bench/ground_stream.py', '--out', '{out}'), 4, 'ground: tile stream and its cost',
          ros=True),
    Bench('ground_flight', ('bench/ground_flight.py', '--out', '{out}'), 6,
          'ground: the sample flight beside the ground station; README ground station row', ros=True),
    Bench('control_adjustment_cost', ('bench/control_adjustment_cost.py', '--out', '{out}'), 5,
          'simulated: control adjustment in flight'),
    Bench('ppk_survey', ('bench/ppk_survey.py', '--out', '{out}'), 6, 'simulated: PPK photo survey; README PPK row'),
    Bench('ppk_formats', ('bench/ppk_formats.py', '--layouts', '--out', '{out}'), 12,
          'simulated: geotag event delay and DJI RTK XMP photos (docs/commands.md geotag figures)'),
    Bench('photo_triangulation', ('bench/photo_triangulation.py', '--out', '{out}'), 12,
          'real-more: photo-survey speed against a bare OpenCV baseline', needs=('{data}/photos/brighton_beach',)),
    Bench('photo_triangulation_matching', ('bench/photo_triangulation_scale.py', '--photos', '100', '--matching-only',
                                           '--counts', '1', '2', '--out', '{out}'), 8,
          'real-more: Dask matching (2 workers against 1)'),
    Bench('split_merge_paths', ('bench/split_merge_paths.py', '--photos', '100', '--split-photos', '60',
                                '--out', '{out}'), 12, 'real-more: 104 simulated photos, one block and split-merge'),
    Bench('split_merge_small', ('bench/split_merge_small.py', '--out', '{out}'), 8,
          'real-more: the 40-photo survey of the slow split-merge test (its gates, tests/test_triangulate_dask_split.py)'),
    Bench('photo_triangulation_scale', ('bench/photo_triangulation_scale.py', '--photos', '600', '--modes', 'split',
                                        'single', '--counts', '1', '2', '--split-photos', '320', '--single-max', '700',
                                        '--out', '{out}'), 130,
          'real-more: 635 simulated photos (split-merge on 1 and 2 workers, one block); README 635-photo row',
          timeout_min=360),
    Bench('gnss_tilt', ('bench/gnss_tilt.py', '--out', '{out}'), 10,
          'docs/parameters.md: why gnss_tilt defaults to never (6 simulated sample flights with 5 GCPs, one leaning; '
          'not rendered)'),
    Bench('run_processes', ('bench/run_processes.py', '--out', '{out}'), 6,
          'inflight-20mp: `run` as a user starts it (run\'s defaults) on seneca_part at 20 MP, one photo a second, '
          'one process against two (not rendered)', ros=True, needs=('{data}/photos/seneca_part',)),
    Bench('georef_inflight', ('bench/georef_inflight.py',), 12,
          'docs/parameters.md pass_min_keyframes: in-flight poses against the final and triangulate\'s on every real '
          'photo set, old code (a clean checkout at /tmp/georef_base) against new (writes bench/results itself; not '
          'rendered)', needs=('{data}/photos/seneca_part', '/tmp/georef_base')),
    Bench('faults_stop', ('bench/faults_stop.py', '--out', '{out}'), 6,
          'docs/faults.md: `run` with a camera that never ends, stopped by SIGTERM (exit time, RSS; not rendered)',
          ros=True, needs=('{data}/photos/toledo',)),
    Bench('faults_odd_photo', ('bench/faults_odd_photo.py', '--survey', 'seneca', '--scale', '0.9', '--out', '{out}'), 6,
          'docs/faults.md: replay of a survey whose first photo has another size, against the plain survey '
          '(not rendered)', ros=True, needs=('{data}/photos/seneca_part',)),
    Bench('faults_strays', ('bench/faults_strays.py', '--survey', 'toledo', '--out', '{out}'), 6,
          'docs/faults.md: triangulate with a panorama, a thumbnail and a duplicate among the photos (not rendered)',
          needs=('{data}/photos/toledo',)),
)
BY_NAME = {b.name: b for b in BENCHES}

# Named groups for --only / --skip (a name here stands for its benches, in this order). The long benches are
# those whose figures can only stay fresh when a run of them is cheap to start: `long_short` (each under ~15 min)
# first, then `long` (the hour-long ones).
GROUPS: dict[str, tuple[str, ...]] = {
    'real': ('real_surveys', 'real_surveys_variants', 'inflight_chain', 'block_verdicts', 'held_out_proxies'),
    'components': ('stereo_middlebury', 'bundle_bal', 'mavlink_parse', 'stereo_speed', 'fusion_throughput',
                   'tracker_fps', 'window_latency', 'target_detection', 'replay_throughput'),
    'simulated': ('inflight_20mp', 'sample_flight', 'control_adjustment_cost', 'ppk_survey', 'ground_stream',
                  'ground_flight', 'e2e_realtime', 'split_merge_paths', 'photo_triangulation_matching',
                  'photo_triangulation_scale'),
    'long_short': ('bundle_bal', 'control_adjustment_cost', 'ppk_survey', 'ground_stream', 'ground_flight',
                   'e2e_realtime', 'photo_triangulation', 'photo_triangulation_matching', 'split_merge_paths'),
    'long': ('block_verdicts', 'held_out_proxies', 'inflight_chain', 'photo_triangulation_scale'),
    'faults': ('faults_stop', 'faults_odd_photo', 'faults_strays'),
    'adjustment': ('gnss_tilt',),
}


def short_commit() -> str:
    return tree_state()['commit'][:7]


def recorded_minutes() -> dict[str, float]:
    """Each bench's wall minutes in the newest run_all record that ran it (file modification order)."""
    out: dict[str, float] = {}
    for path in sorted(RESULTS.glob('run_all_*.jsonl'), key=lambda p: p.stat().st_mtime):
        for line in path.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            if row.get('name') in BY_NAME and isinstance(row.get('wall_min'), (int, float)) and row.get('exit') == 0:
                out[row['name']] = row['wall_min']
    return out


def expected(b: Bench, recorded: dict) -> tuple[float, str]:
    return (recorded[b.name], 'recorded') if b.name in recorded else (b.minutes, 'estimate')


def _names(text: str) -> list[str]:
    """Comma-separated bench and group names -> bench names (a group's in its order, each once)."""
    out: list[str] = []
    for n in (x.strip() for x in text.split(',')):
        for m in GROUPS.get(n, (n,) if n else ()):
            if m not in out:
                out.append(m)
    return out


def select(only: str, skip: str) -> list[Bench]:
    names = _names(only) if only else [b.name for b in BENCHES]
    dropped = set(_names(skip))
    unknown = [n for n in names + sorted(dropped) if n not in BY_NAME]
    if unknown:
        raise SystemExit(f'unknown bench(es) {unknown}; known: {", ".join(BY_NAME)}; groups: {", ".join(GROUPS)}')
    return [BY_NAME[n] for n in names if n not in dropped]


def groups_text(recorded: dict) -> str:
    lines = []
    for g, names in GROUPS.items():
        mins = [expected(BY_NAME[n], recorded) for n in names]
        lines.append(f'{g:12} {sum(m for m, _ in mins):5.0f} min  ' + ', '.join(
            f'{n} {m:.0f}{"" if how == "recorded" else "~"}' for n, (m, how) in zip(names, mins)))
    lines.append('(minutes: from the newest run_all record that ran the bench; ~ an estimate)')
    return '\n'.join(lines)


def run_one(b: Bench, work_root: Path, commit7: str, domain: str) -> dict:
    work = work_root / b.name
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    tmp_out = work / f'{b.name}.jsonl'
    dst = RESULTS / f'{b.name}_{commit7}.jsonl'
    missing = [p.format(data=str(DATA)) for p in b.needs if not Path(p.format(data=str(DATA))).exists()]
    if missing:
        return {'exit': None, 'wall_min': 0.0, 'result_file': None, 'why': f'missing {", ".join(missing)}'}
    cmd = b.command(str(tmp_out), str(work))
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    if b.ros:
        env['ROS_DOMAIN_ID'] = domain
    timeout_s = 60 * (b.timeout_min or max(10.0, 3 * b.minutes))
    log = work / f'{b.name}.log'
    t0 = time.monotonic()
    with open(log, 'w') as fh:
        fh.write(' '.join(cmd) + '\n')
        fh.flush()
        try:
            proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
            code = proc.wait(timeout=timeout_s)
            why = '' if code == 0 else f'exit {code}'
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 15)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, 9)
                proc.wait()
            code, why = -1, f'timed out after {timeout_s / 60:.0f} min'
    wall_min = round((time.monotonic() - t0) / 60, 2)
    found = sorted(glob.glob(str(work / b.produced))) if b.produced else ([str(tmp_out)] if tmp_out.exists() else [])
    found = [p for p in found if Path(p).stat().st_size > 0]
    result = None
    if found:
        with open(dst, 'w') as out:
            for p in found:
                out.write(Path(p).read_text())
        result = dst.relative_to(ROOT).as_posix()
    elif code == 0:
        code, why = 1, 'exited 0 but wrote no result line'
    tail = log.read_text().strip().splitlines()[-1:] if why else []
    return {'exit': code, 'wall_min': wall_min, 'result_file': result,
            'why': why + (f' ({tail[0][:200]})' if tail else ''), 'log': str(log)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--list', action='store_true', help='list the benches, their commands and expected minutes')
    ap.add_argument('--only', default='', help='these benches or groups (comma separated), in this order')
    ap.add_argument('--skip', default='', help='not these benches or groups (comma separated)')
    ap.add_argument('--groups', action='store_true', help='list the named groups, their benches and minutes')
    ap.add_argument('--budget-min', type=float, default=0.0, help='start no bench once this many minutes have passed')
    ap.add_argument('--work', default='', help='work folder (default /tmp/run_all_<commit7>)')
    ap.add_argument('--domain', default=os.environ.get('ROS_DOMAIN_ID', ''),
                    help='ROS_DOMAIN_ID for the benches that start ROS nodes (default: the environment\'s)')
    ap.add_argument('--dry-run', action='store_true', help='print what would run')
    a = ap.parse_args(argv)
    if a.groups:
        print(groups_text(recorded_minutes()))
        return 0
    benches = select(a.only, a.skip)
    commit7 = short_commit()
    work_root = Path(a.work or f'/tmp/run_all_{commit7}')
    if a.list or a.dry_run:
        rec = recorded_minutes()
        total = 0.0
        for b in benches:
            m, how = expected(b, rec)
            total += m
            work = work_root / b.name
            cmd = ' '.join(b.command(str(work / f'{b.name}.jsonl'), str(work)))
            print(f'{b.name:28} {m:6.1f} min ({how}; cumulative {total:.0f})  {"[ROS] " if b.ros else ""}{b.feeds}\n'
                  f'{"":28} {cmd}\n{"":28} -> bench/results/{b.name}_{commit7}.jsonl')
        print(f'{len(benches)} benches, {total:.0f} min expected')
        return 0
    if not DATA.is_dir():
        print(f'run_all: {DATA} is missing: clone beside ../shared (the benches read ../shared/data)', file=sys.stderr)
        return 2
    if any(b.ros for b in benches) and not a.domain:
        print('run_all: set ROS_DOMAIN_ID (or --domain) for the benches that start ROS nodes', file=sys.stderr)
        return 2
    state = tree_state()
    if not state['clean']:
        print(f'run_all: WARN: uncommitted changes to the code ({", ".join(state["dirty"][:5])}): the result lines '
              'will say clean false', file=sys.stderr)
    record = ResultWriter(RESULTS / f'run_all_{commit7}.jsonl', 'run_all', ['photogram_ros', 'config'], fresh=False)
    t0 = time.monotonic()
    summary = []
    for b in benches:
        spent = (time.monotonic() - t0) / 60
        if a.budget_min and spent >= a.budget_min:
            summary.append((b, {'exit': None, 'wall_min': 0.0, 'result_file': None,
                                'why': f'not started: {spent:.0f} min spent of a {a.budget_min:.0f} min budget'}))
            continue
        print(f'run_all: {b.name} (expected {b.minutes:.0f} min, {spent:.0f} min spent) ...', flush=True)
        # Named for the commit the bench starts at (the one its lines record), should HEAD move during the run.
        r = run_one(b, work_root, short_commit(), a.domain)
        print(f'run_all: {b.name}: {"ok" if r["exit"] == 0 else "FAILED " + r["why"]} in {r["wall_min"]:.1f} min'
              + (f' -> {r["result_file"]}' if r['result_file'] else ''), flush=True)
        if r['exit'] is not None:
            record.write({'name': b.name, **r})
        summary.append((b, r))
    print('\nrun_all summary:')
    failed = 0
    for b, r in summary:
        status = 'ok' if r['exit'] == 0 else ('SKIPPED' if r['exit'] is None else 'FAILED')
        failed += status == 'FAILED'
        print(f'  {status:8} {b.name:26} {r["wall_min"]:6.1f} min  {r["result_file"] or ""}'
              + (f'  {r["why"]}' if r['why'] else ''))
    print(f'{sum(r["exit"] == 0 for _, r in summary)} ok, {failed} failed, '
          f'{sum(r["exit"] is None for _, r in summary)} skipped in {(time.monotonic() - t0) / 60:.0f} min; '
          'commit bench/results, then run bench/render_figures.py')
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
