"""Same figures before and after a change that must not move them: `photogram-ros triangulate` of one photo set by
two checkouts (the base one given, this one), their report.json compared value by value (timings left out).

    PYTHONPATH=$PWD .venv/bin/python bench/same_figures.py --base /tmp/house-base \
        --photos ../shared/data/photos/brighton_beach/images [--extra "--split-photos 8"]

Writes one JSON line to bench/results/same_figures_<commit>.jsonl: the commit, whether the tree was clean, the
machine and its load, the headline figures of each side, and every value that differs (none for a refactor).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from machine import machine_info  # noqa: E402

# Wall-clock figures: they differ from run to run, whatever the code (in texts too: "sub-block 0: ..., 40 s; ...").
SKIP = {'timing_s', 'matching_s', 'features_s', 'wall_s', 'cpu_s', 's'}
SECONDS = re.compile(r'\b\d+(\.\d+)? s\b')


def differences(a, b, path: str = '') -> list[str]:
    """Every place where the two JSON values differ (keys in SKIP left out)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k in SKIP:
                continue
            if k not in a or k not in b:
                out.append(f'{path}/{k}: only in {"after" if k in b else "before"}')
            else:
                out += differences(a[k], b[k], f'{path}/{k}')
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f'{path}: {len(a)} items before, {len(b)} after']
        return [d for i, (u, v) in enumerate(zip(a, b)) for d in differences(u, v, f'{path}[{i}]')]
    if isinstance(a, str) and isinstance(b, str):
        a, b = SECONDS.sub('# s', a), SECONDS.sub('# s', b)
    return [] if a == b else [f'{path}: {a!r} before, {b!r} after']


def headline(rep: dict) -> dict:
    ck = rep.get('check', {}).get('rmse', {})
    return {'registered': rep.get('registered'), 'keyframes': rep.get('keyframes'), 'points': rep.get('points'),
            'reprojection_rms_px': rep.get('reprojection_rms_px'), 'gnss_rmse': rep.get('gnss', {}).get('rmse'),
            'check_rmse': ck, 'camera': rep.get('camera')}


def triangulate(checkout: Path, photos: Path, out: Path, extra: list) -> dict:
    env = dict(os.environ, PYTHONPATH=str(checkout))
    subprocess.run([str(checkout / '.venv' / 'bin' / 'photogram-ros'), 'triangulate', str(photos), '--out', str(out),
                    '--quiet', *extra], check=True, env=env, capture_output=True, text=True)
    return json.loads((out / 'report.json').read_text())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--base', required=True, help='the checkout before the change (with its .venv)')
    ap.add_argument('--photos', required=True, help='a folder of geotagged photos')
    ap.add_argument('--extra', default='', help='more triangulate arguments, e.g. "--split-photos 8" (split-merge)')
    a = ap.parse_args()
    extra = a.extra.split()
    commit = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    base_commit = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=a.base, capture_output=True,
                                 text=True).stdout.strip()
    clean = not subprocess.run(['git', 'status', '--porcelain'], cwd=ROOT, capture_output=True, text=True).stdout
    row = {'bench': 'same_figures', 'commit': commit, 'base_commit': base_commit, 'clean_tree': clean,
           'photos': str(a.photos), 'extra': extra, 'machine': machine_info(), 'load_avg_before': os.getloadavg(),
           'time_utc': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}
    with tempfile.TemporaryDirectory() as tmp:
        before = triangulate(Path(a.base).resolve(), Path(a.photos).resolve(), Path(tmp) / 'before', extra)
        after = triangulate(ROOT, Path(a.photos).resolve(), Path(tmp) / 'after', extra)
    diffs = differences(before, after)
    row.update({'before': headline(before), 'after': headline(after), 'differences': diffs,
                'identical': not diffs, 'load_avg_after': os.getloadavg()})
    out = HERE / 'results' / f'same_figures_{commit}.jsonl'
    with open(out, 'a') as f:
        f.write(json.dumps(row) + '\n')
    print(f'{"identical" if not diffs else f"{len(diffs)} differences"} ({a.photos} {a.extra}); wrote {out}')
    for d in diffs[:20]:
        print(' ', d)
    return 0 if not diffs else 1


if __name__ == '__main__':
    raise SystemExit(main())
