"""`photogram-ros run` as a user starts it on a live-paced 20 MP camera: one process against two (`--processes`).

The flight: seneca_part's 41 real near-infrared photos upscaled to 20 MP (5164 x 3873) and re-timed one photo a
second (bench/inflight_20mp.py --flight seneca builds them once into /tmp/photogram_bench_cache). `run` is started
as a subprocess with a parameter file that sets only what a user must (camera_node: the folder, played at its EXIF
timing, rate 1; map_node: the map folder): every other parameter is the nodes' default, the tracker's queue of 2
frames included, as after `photogram-ros run --params mine.yaml`. Each --processes value is run back to back in
the same bench (the machine is shared: the ratio between them is the figure, not the seconds).

Per run (JSON lines through bench/machine.py's ResultWriter, --out): keyframes taken and oriented (report.json),
frames the tracker dropped and why (its counters), the flight's wall time from `photogram_ros running` to the
camera's last photo (`camera_end_s`), the backlog at the camera's end (`drain_s`: from the camera's last photo to
the end-of-flight steps starting, the time the graph needed to take what it had been given: a lag at the end of
the flight), the end-of-flight steps, the peak RSS of the whole process tree (sampled every 0.25 s with psutil,
`peak_rss_tree_mb`), and the run's exit status. Products are made from the in-flight map (--live-map).

    ROS_DOMAIN_ID=171 .venv/bin/python bench/run_processes.py --processes 1,2 --out bench/results/run_processes_<c>.jsonl
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import ResultWriter  # noqa: E402

CACHE = Path('/tmp/photogram_bench_cache')
FOLDER = CACHE / 'inflight_20mp_seneca_1s_41'


def ensure_folder() -> Path:
    if not FOLDER.is_dir() or len(list(FOLDER.glob('*.jpg'))) < 41:
        subprocess.run([sys.executable, str(ROOT / 'bench' / 'inflight_20mp.py'), '--flight', 'seneca',
                        '--periods', '1', '--photos', '41', '--build-only'], cwd=ROOT, check=True)
    return FOLDER


def tree_rss_mb(pid: int) -> float:
    import psutil
    try:
        p = psutil.Process(pid)
        procs = [p] + p.children(recursive=True)
    except psutil.Error:
        return 0.0
    total = 0
    for q in procs:
        try:
            total += q.memory_info().rss
        except psutil.Error:
            pass
    return total / 2**20


def run_once(folder: Path, processes: int, work: Path, timeout_s: float) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    params = work / 'params.yaml'
    params.write_text(f'camera_node:\n  ros__parameters:\n    source: {folder}\n    rate: 1.0\n'
                      f'map_node:\n  ros__parameters:\n    map_dir: {work / "map"}\n')
    cmd = [sys.executable, '-m', 'photogram_ros.cli', 'run', '--params', str(params), '--nodes',
           'camera,tracker,bundle,stereo,map', '--processes', str(processes), '--live-map', '--out',
           str(work / 'products')]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    peak = [0.0]
    done = threading.Event()

    def sample():
        while not done.wait(0.25):
            peak[0] = max(peak[0], tree_rss_mb(proc.pid))
    threading.Thread(target=sample, daemon=True).start()
    marks, lines = {}, []
    try:
        for line in proc.stdout:
            now = time.monotonic() - t0
            lines.append(line.rstrip())
            for key, pattern in (('running', r'^photogram_ros running'), ('camera_end', r'^end of the camera source: '
                                 'waiting'), ('ending', r'ending the flight'), ('steps_done', r'^end of flight: steps '
                                                                                             r'done')):
                if key not in marks and re.search(pattern, line):
                    marks[key] = now
            if now > timeout_s:
                proc.kill()
        rc = proc.wait(timeout=60)
    finally:
        done.set()
        if proc.poll() is None:
            proc.kill()
    (work / 'run.log').write_text('\n'.join(lines) + '\n')
    report = {}
    rj = work / 'products' / 'report.json'
    if rj.exists():
        report = json.loads(rj.read_text())
    counts = (report.get('run') or {}).get('counts', {})
    tracker = counts.get('tracker', {})
    start = marks.get('running', 0.0)
    row = {'flight': 'seneca_20mp_1s', 'photos': len(list(folder.glob('*.jpg'))), 'processes': processes,
           'exit_status': rc, 'keyframes_taken': report.get('keyframes_taken'),
           'keyframes_oriented': report.get('keyframes_oriented'),
           'tracker_frames_received': tracker.get('frames_received'), 'tracker_frames_dropped':
           sum(v for k, v in tracker.items() if isinstance(v, (int, float)) and 'drop' in k), 'tracker_counts': {k: v for k, v in tracker.items()
                                                                if isinstance(v, (int, float)) and 'drop' in k},
           'camera_end_s': round(marks['camera_end'] - start, 1) if 'camera_end' in marks else None,
           'drain_s': round(marks['ending'] - marks['camera_end'], 1) if {'ending', 'camera_end'} <= set(marks)
           else None,
           'end_of_flight_s': round(marks['steps_done'] - marks['ending'], 1) if {'steps_done', 'ending'} <= set(marks)
           else None,
           'wall_s': round(time.monotonic() - t0, 1), 'peak_rss_tree_mb': round(peak[0], 1),
           'verdict': (report.get('mapping') or {}).get('mapped'), 'log': str(work / 'run.log')}
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--processes', default='1,2', help='comma list of --processes values, run in this order')
    ap.add_argument('--repeat', type=int, default=1)
    ap.add_argument('--out', default='', help='append the JSON lines to this file')
    ap.add_argument('--keep', default='', help='keep the runs\' folders here (default: a temporary folder)')
    ap.add_argument('--timeout-s', type=float, default=1800.0)
    a = ap.parse_args(argv)
    folder = ensure_folder()
    base = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix='run_processes_'))
    os.environ.setdefault('ROS_DOMAIN_ID', '171')
    rows = []
    with ResultWriter.for_bench(a.out or None, 'run_processes', ['photogram_ros', 'config']) as w:
        for k in range(a.repeat):
            for n in (int(v) for v in a.processes.split(',')):
                row = run_once(folder, n, base / f'p{n}_{k}', a.timeout_s)
                rows.append(w.write(row))
                print(json.dumps(row), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
