"""`run` with a camera that never ends, stopped by SIGTERM (issue 48): how long it takes to exit, and its
memory after the signal as a ratio to its in-flight peak, measured in the same run.

A copy of the toledo survey (42 photos, 2400x1800) is played by camera_node in a loop (rate 0, as fast as
the tracker takes them), SIGTERM after `--stop-after-s` of flight; the RSS of the run and its child process (bundle, stereo, map) is sampled from /proc
every 0.2 s: its peak in flight, in the end-of-flight steps (until "end of flight: steps done") and while
the products are made; with the run log's lines that time the end-of-flight steps and the products
(end_of_flight_lines) and what a stopped flight's budget left out (the report's run). Writes one JSON line (bench/machine.py's ResultWriter: the commit, whether the tree was
clean, cores, load, the modules the run ran) to --out (default /tmp/faults_stop.jsonl; bench/run_all.py copies it
to bench/results/faults_stop_<commit7>.jsonl).

    ROS_DOMAIN_ID=N .venv/bin/python bench/faults_stop.py [--stop-after-s 60] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / 'bench'), str(ROOT / 'tests'), str(ROOT)]
os.environ.setdefault('ROS_DOMAIN_ID', '152')

from machine import ResultWriter, machine_info  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--stop-after-s', type=float, default=60.0)
    ap.add_argument('--out', default=None, help='the result file (default /tmp/faults_stop.jsonl)')
    a = ap.parse_args()
    from test_faults_stop import looping_run
    w = ResultWriter.for_bench(a.out, 'faults_stop', ['photogram_ros', 'config'])
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix='faults_stop_') as tmp:
        tmp = Path(tmp)
        shutil.copytree(ROOT.parent / 'shared' / 'data' / 'photos' / 'toledo' / 'images', tmp / 'photos')
        rc, out, took_s, rss, products = looping_run(tmp, tmp / 'photos', stop_after_s=a.stop_after_s, bound_s=1800.0)
        report = json.loads((products / 'report.json').read_text()) if (products / 'report.json').exists() else {}
    row = {'data': 'toledo looping (42 photos)',
           'stop_after_s': a.stop_after_s, 'exit_status': rc, 'signal_to_exit_s': round(took_s, 1),
           'rss_in_flight_peak_mb': round(rss['before']), 'rss_end_of_flight_peak_mb': round(rss['after']),
           'rss_products_peak_mb': round(rss['products']),
           'end_of_flight_over_in_flight': round(rss['after'] / max(rss['before'], 1.0), 3),
           'products_over_in_flight': round(rss['products'] / max(rss['before'], 1.0), 3),
           'end_of_flight_lines': end_of_flight_lines(out),
           'stop_budget_s': report.get('run', {}).get('stop_budget_s'),
           'end_of_flight_skipped': report.get('run', {}).get('end_of_flight_skipped'),
           'products_from': report.get('run', {}).get('products_from'),
           'frames': report.get('run', {}).get('frames'), 'keyframes_taken': report.get('keyframes_taken'),
           'keyframes_oriented': report.get('keyframes_oriented'), 'machine': machine_info(),
           'load_avg_before': [round(x, 2) for x in load_before],
           'load_avg_after': [round(x, 2) for x in os.getloadavg()]}
    w.write(row)
    return 0 if rc in (0, 4) else 1


def end_of_flight_lines(out: str) -> list[str]:
    """The run's lines that time the end of flight (each step's start, the adjuster's own step times, the steps'
    end, what the budget left out, the products' steps), without the periodic "still working" ones."""
    keep = re.compile(r'^(end of flight: \d+ s: (?!waiting)|end of flight: steps done|end of flight within|'
                      r'export: .*(steps in|in \d)|\[INFO\].*\[bundle_node\]: end of flight|products in )')
    return [line.strip()[:300] for line in out.splitlines() if keep.search(line.strip())]


def append_result(bench: str, commit: str, row: dict, out: str = '') -> None:
    """Print `row` and append it as a JSON line to `out`, else bench/results/<bench>_<commit>.jsonl
    (bench/faults_odd_photo.py, bench/faults_strays.py)."""
    print(json.dumps(row), flush=True)
    dst = Path(out) if out else ROOT / 'bench' / 'results' / f'{bench}_{commit}.jsonl'
    with open(dst, 'a') as f:
        f.write(json.dumps(row) + '\n')
    print(f'-> {dst}', file=sys.stderr)


if __name__ == '__main__':
    sys.exit(main())
