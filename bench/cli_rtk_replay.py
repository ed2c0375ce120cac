"""DJI RTK photos replayed with and without their XMP sigmas (issue #45): what camera_node's per-photo weighting gives.

`simulate --rtk-photos` (preset tiny, 11 photos of one line; EXIF GPS = the RTK camera centre, XMP RtkFlag and
RtkStdLon/Lat/Hgt) is replayed twice: (a) as written, camera_node publishing each photo's fix with its XMP sigmas
and the flag's NavSatStatus (io/image_source.dji_rtk_accuracy, the reading triangulate uses); (b) the same photos
with the XMP packet cut out, so the same EXIF positions go in with the EXIF sigmas (5 m horizontal, 2 m vertical).
Case `float_1m` does it again with every third photo FLOAT (flag 34, 0.5 / 0.8 m stated) and 1 m off. No GCP is
used: every target is a check point. Per row: the check points' RMSE, the cameras against the simulator's truth,
the cloud's height bias against the truth, the replay's health, and the ratio of (a) to (b).

    .venv/bin/python bench/cli_rtk_replay.py [--cases clean,float_1m] [--domain 33]
        [--out bench/results/cli_rtk_replay_<commit>.jsonl]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'bench'))
from machine import ResultWriter  # noqa: E402

CASES = {'clean': {}, 'float_1m': {'rtk_float_every': 3, 'rtk_float_offset_m': 1.0}}
XMP_HEAD = b'http://ns.adobe.com/xap/1.0/'


def strip_xmp(folder: Path) -> int:
    """Cut the XMP APP1 segment out of each JPEG of `folder`; returns how many photos had one."""
    n = 0
    for p in sorted(folder.glob('*.JPG')):
        d = p.read_bytes()
        k = 2
        while k + 4 <= len(d) and d[k] == 0xFF and d[k + 1] in range(0xE0, 0xF0):
            size = int.from_bytes(d[k + 2:k + 4], 'big')
            if d[k + 1] == 0xE1 and d[k + 4:k + 4 + len(XMP_HEAD)] == XMP_HEAD:
                p.write_bytes(d[:k] + d[k + 2 + size:])
                n += 1
                break
            k += 2 + size
    return n


def replay(folder: Path, sim: Path, out: Path, domain: int) -> dict:
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join([str(ROOT), os.environ.get('PYTHONPATH', '')]).rstrip(os.pathsep),
           'ROS_DOMAIN_ID': str(domain)}
    cmd = [sys.executable, '-c', 'import sys; from photogram_ros.cli import main; sys.exit(main(sys.argv[1:]))',
           'replay', str(folder), '--out', str(out), '--truth', str(sim), '--domain', str(domain), '--quiet',
           '--overwrite']
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)
    rep = json.loads((out / 'report.json').read_text()) if (out / 'report.json').exists() else {}
    ck = rep.get('check_points', {}).get('rmse', {})
    tr = rep.get('trajectory_vs_truth', {})
    cloud = rep.get('cloud_vs_truth', {})
    health = rep.get('health', [])
    return {'exit_code': run.returncode, 'check_n': ck.get('count'), 'check_h_m': ck.get('horizontal_m'),
            'check_v_m': ck.get('z_m'), 'cameras_vs_truth_h_m': tr.get('rmse_horizontal_m'),
            'cameras_vs_truth_v_m': tr.get('rmse_vertical_m'), 'cameras_vs_truth_n': tr.get('count'),
            'cloud_bias_m': cloud.get('bias_m'), 'keyframes_oriented': rep.get('keyframes_oriented'),
            'health': {h.get('node'): h.get('worst_level') for h in health} if isinstance(health, list) else health,
            'block_check': next((r[:160] for h in health if isinstance(health, list) for r in h.get('reasons', [])
                                 if 'block check' in r), None),
            'stderr_tail': run.stderr[-300:] if run.returncode else ''}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--cases', default='clean,float_1m')
    ap.add_argument('--domain', type=int, default=33)
    ap.add_argument('--out', default=None)
    a = ap.parse_args(argv)
    commit = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    out = Path(a.out or ROOT / 'bench' / 'results' / f'cli_rtk_replay_{commit}.jsonl')
    from photogram_ros.sim.scenario import preset, simulate
    with ResultWriter(out, 'cli_rtk_replay', modules=['photogram_ros', 'config'], echo=True) as w, \
            tempfile.TemporaryDirectory(prefix='cli_rtk_replay_') as tmp:
        for case in a.cases.split(','):
            sim = Path(tmp) / case
            simulate(preset('tiny', fps=1.0, rtk_photos=True, **CASES[case]), sim)
            bare = sim / 'rtk_without_xmp'
            shutil.copytree(sim / 'rtk', bare)
            stripped = strip_xmp(bare)
            rows = {}
            for weights, folder in (('xmp', sim / 'rtk'), ('exif_sigmas', bare)):
                rows[weights] = replay(folder, sim, Path(tmp) / f'{case}_{weights}', a.domain)
            for weights, row in rows.items():
                base = rows['exif_sigmas']
                ratio = {k: (row[k] / base[k] if row.get(k) is not None and base.get(k) else None)
                         for k in ('check_h_m', 'check_v_m', 'cameras_vs_truth_h_m', 'cameras_vs_truth_v_m')}
                w.write({'case': case, 'preset': 'tiny', 'weights': weights, 'photos': len(list(bare.glob('*.JPG'))),
                         'photos_with_xmp_cut': stripped, **row, 'ratio_to_exif_sigmas': ratio})
    return 0


if __name__ == '__main__':
    sys.exit(main())
