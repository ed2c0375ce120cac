"""The sample flight end to end, as scripts/replay-sample.sh runs it, measured from the files `replay` writes.

Runs (one after the other, each in a fresh folder under --work):
- `rtk`: `photogram-ros replay bags/sample_flight --truth bags/sample_flight` (RTK fixes, no GCPs);
- `gcp`: the same with its targets file (`--gcp bags/sample_flight/targets.txt`: RTK + 5 GCPs, the rest check
  points).
The simulator's truth only grades the outputs (the report's figures against truth); nothing of it enters the
mapping. Per run, one JSON line (bench/machine.py's ResultWriter: commit, clean-tree flag, cores, load) with
report.json's figures: check points and GCP residuals (RMSE H / V, count), keyframes taken and oriented, keyframe
camera centres against truth, the DSM against the true DEM (all cells, those measured by stereo, away from walls),
the DTM away from buildings, DSM completeness, overlap; and run.json's frames, flight seconds, wall seconds and
real-time factor, and the command's exit and last line.

    ROS_DOMAIN_ID=N .venv/bin/python bench/sample_flight.py [--runs rtk,gcp] [--work DIR] [--out F]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import ResultWriter  # noqa: E402

BAG = ROOT / 'bags' / 'sample_flight'
RUNS = {'rtk': [], 'gcp': ['--gcp', str(BAG / 'targets.txt')]}
FIGURES = ('check_points', 'gcp_residuals', 'trajectory_vs_truth', 'dsm_vs_truth', 'dsm_vs_truth_measured',
           'dsm_vs_truth_filled', 'dsm_vs_truth_away_from_walls', 'dtm_vs_truth_away_from_buildings',
           'dsm_completeness', 'dsm_measured_completeness', 'dsm_cell_m', 'overlap', 'keyframes_taken',
           'keyframes_oriented', 'keyframes', 'keyframes_not_oriented_by_reason')
RUN_KEYS = ('frames', 'bag_s', 'wall_s', 'real_time_factor', 'map_points')


def run_one(name: str, work: Path) -> dict:
    out = work / name
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, '-m', 'photogram_ros.cli', 'replay', str(BAG), '--out', str(out), '--truth', str(BAG),
           '--quiet', *RUNS[name]]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    t0 = time.monotonic()
    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    lines = r.stdout.strip().splitlines()       # the command's own summary (the nodes log on stderr)
    (work / f'{name}.log').write_text(r.stdout + r.stderr)
    row = {'run': name, 'command': ' '.join(['photogram-ros replay bags/sample_flight --truth bags/sample_flight']
                                            + [a.replace(str(ROOT) + '/', '') for a in RUNS[name]]),
           'exit': r.returncode,
           'command_wall_s': round(time.monotonic() - t0, 1), 'last_line': lines[-1] if lines else ''}
    row.update(measure(out))
    return row


def measure(out: Path) -> dict:
    """report.json's and run.json's figures of a replay's output folder."""
    row = {}
    report = out / 'report.json'
    if report.exists():
        figures = json.loads(report.read_text())
        row.update({k: figures[k] for k in FIGURES if k in figures})
    run = out / 'run.json'
    if run.exists():
        r_ = json.loads(run.read_text())
        row['replay'] = {k: r_.get(k) for k in RUN_KEYS}
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--runs', default=','.join(RUNS), help='runs, comma separated (rtk, gcp)')
    ap.add_argument('--work', default='', help='keep the replays\' outputs here (default: a temporary folder)')
    ap.add_argument('--out', default=None, help='the result file (JSON lines; default /tmp/sample_flight.jsonl)')
    a = ap.parse_args()
    runs = [r for r in a.runs.split(',') if r]
    bad = [r for r in runs if r not in RUNS]
    if bad:
        ap.error(f'unknown runs {bad}: {list(RUNS)}')
    if not os.environ.get('ROS_DOMAIN_ID'):
        ap.error('set ROS_DOMAIN_ID (replay starts ROS nodes)')
    w = ResultWriter.for_bench(a.out, 'sample_flight', ['photogram_ros', 'config'])
    tmp = None if a.work else tempfile.TemporaryDirectory()
    work = Path(a.work or tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    failed = 0
    for name in runs:
        row = w.write(run_one(name, work))
        failed += row['exit'] != 0
    if tmp is not None:
        tmp.cleanup()
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
