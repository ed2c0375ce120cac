"""The ground station beside a live replay, measured: `photogram-ros ground-station --web` and `replay --rate 1`
of the sample flight with its targets file, the page's status.json polled every 5 s.

    ROS_DOMAIN_ID=N .venv/bin/python bench/ground_flight.py --out bench/results/ground_flight_COMMIT.jsonl

One line (bench/machine.py's ResultWriter): the page's final check points (RMSE H, V, count) and GCP residuals
against the final report's, their differences, the verdicts polled, and the largest horizontal check-point
RMSE the page showed in flight from the final georeference on. tests/test_ground_flight.py drives the
same Station and replay and gates its figures at 1.5x this file.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import ResultWriter  # noqa: E402

BAG = ROOT / 'bags' / 'sample_flight'
MODULES = ['photogram_ros']


class Station:
    """The ground-station command with its page; `polls` holds status.json every `period_s`."""

    def __init__(self, out: Path, *extra, period_s: float = 5.0):
        self.proc = subprocess.Popen([sys.executable, '-m', 'photogram_ros.cli', 'ground-station', '--out', str(out),
                                      '--web', '127.0.0.1:0', '--drones', '/', '--save-period', '2', *extra],
                                     cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines = []
        self.url = None
        while self.url is None:
            line = self.proc.stdout.readline()
            if not line:
                raise AssertionError(f'station ended: {self.proc.stderr.read()[-2000:]}')
            self.lines.append(line)
            m = re.search(r'map page on (http://\S+/)', line)
            self.url = m.group(1) if m else None
        threading.Thread(target=lambda: self.lines.extend(self.proc.stdout), daemon=True).start()
        self.polls = []
        self._stop = threading.Event()
        self.period_s = period_s
        self.thread = threading.Thread(target=self._poll, daemon=True)
        self.thread.start()

    def status(self) -> dict:
        with urllib.request.urlopen(self.url + 'status.json', timeout=10) as r:
            return json.loads(r.read())

    def _poll(self):
        while not self._stop.wait(self.period_s):
            try:
                self.polls.append((time.monotonic(), self.status()))
            except OSError:
                pass

    def stop(self) -> tuple[int, str]:
        self._stop.set()
        self.thread.join(30)
        self.proc.send_signal(signal.SIGINT)
        err = self.proc.communicate(timeout=60)[1]
        return self.proc.returncode, err


def replay(bag: Path, out: Path) -> subprocess.CompletedProcess:
    # On the station's domain: a replay takes a domain of its own unless told.
    return subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(bag), '--out', str(out), '--quiet',
                           '--rate', '1', '--gcp', str(bag / 'targets.txt'), '--domain', os.environ['ROS_DOMAIN_ID'],
                           '--truth', str(bag)],
                          cwd=ROOT, capture_output=True, text=True, timeout=1200)


def page_figures(final: dict, report: dict, polls: list) -> dict:
    """The page's final accuracy against the report's, and what the page showed in flight."""
    a = final['drones']['default']['accuracy']
    rep, gcp = report['check_points']['rmse'], report['gcp_residuals']['rmse']
    live = [s['drones'].get('default', {}) for _, s in polls]
    live = [(d.get('accuracy') or {}) for d in live]
    live_h = [x['check_rmse_h_m'] for x in live if x.get('georeference') == 'final' and x.get('check_count')]
    verdicts = [(s['drones'].get('default', {}).get('go_no_go') or {}).get('verdict') for _, s in polls]
    return {'page_check_h_m': a['check_rmse_h_m'], 'page_check_v_m': a['check_rmse_v_m'],
            'page_check_n': a['check_count'], 'report_check_h_m': rep['horizontal_m'], 'report_check_v_m': rep['z_m'],
            'report_check_n': rep['count'],
            'check_diff_h_m': abs(a['check_rmse_h_m'] - rep['horizontal_m']),
            'check_diff_v_m': abs(a['check_rmse_v_m'] - rep['z_m']),
            'page_gcp_h_m': a['gcp_rmse']['horizontal_m'], 'page_gcp_v_m': a['gcp_rmse']['vertical_m'],
            'gcp_diff_h_m': abs(a['gcp_rmse']['horizontal_m'] - gcp['horizontal_m']),
            'gcp_diff_v_m': abs(a['gcp_rmse']['vertical_m'] - gcp['z_m']),
            'polls': len(polls), 'live_final_polls': len(live_h), 'live_check_h_max_m': max(live_h) if live_h else None,
            'nogo_polls': verdicts.count('NO-GO'),
            'final_verdict': (final['drones']['default'].get('go_no_go') or {}).get('verdict')}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--out', default='/tmp/ground_flight.jsonl', help='result file (JSON lines)')
    a = ap.parse_args(argv)
    os.environ.setdefault('ROS_DOMAIN_ID', '0')
    writer = ResultWriter(a.out, 'ground_flight', MODULES)
    tmp = Path(tempfile.mkdtemp(prefix='ground_flight_'))
    st = Station(tmp / 'gs')
    try:
        res = replay(BAG, tmp / 'out')
        time.sleep(6)          # the final adjustment's figures reach the station
        final = st.status()
    finally:
        rc, err = st.stop()
    report = json.loads((tmp / 'out' / 'report.json').read_text())
    row = {'flight': 'sample_flight --rate 1 --gcp targets.txt', 'replay_rc': res.returncode, 'station_rc': rc,
           **page_figures(final, report, st.polls)}
    print(json.dumps(writer.write(row)), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
