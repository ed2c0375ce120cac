"""A stray image never refuses a photo set (issue 48): `triangulate` of a real survey with a 100 MP panorama, a
thumbnail (neither with an EXIF focal length) and a photo downloaded twice among its photos, against `triangulate`
of the unmodified survey, in the same run.

The survey (toledo: 42 photos of 2400x1800, DJI FC350; or seneca: 41 of 1600x1200) is copied; beside its photos a
panorama (its fifth photo stretched to 14400x7000, saved without EXIF, as a stitching tool writes it), a 160x120
thumbnail of it (no EXIF) and a byte-identical copy of its eighth photo named '<name> (1).JPG'. Both folders go
through `photogram-ros triangulate`; per run the exit status, the cameras in poses.csv, whether each stray is named
on the console and in report.json, and whether any stray has a pose. Writes one JSON line (with the commit, whether
the tree was clean, cores and load) to bench/results/faults_strays_<commit>.jsonl.

    .venv/bin/python bench/faults_strays.py [--survey toledo]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / 'bench'), str(ROOT)]

SURVEYS = {'toledo': ('toledo', '*.JPG'), 'seneca': ('seneca_part', '*.jpg'), 'brighton': ('brighton_beach', '*.JPG')}


def strays_copy(src: list[Path], dst: Path) -> dict:
    """`src` copied into `dst` with a panorama, a thumbnail and a duplicate: {stray name: what it is}."""
    from PIL import Image
    Image.MAX_IMAGE_PIXELS = None    # the panorama is made here on purpose
    dst.mkdir(parents=True)
    for p in src:
        shutil.copy2(p, dst / p.name)
    with Image.open(src[4]) as im:
        im = im.convert('RGB')
        im.resize((14400, 7000)).save(dst / 'PANO_0001.JPG', quality=80)
        im.resize((160, 120)).save(dst / f'{src[4].stem}_thumb{src[4].suffix}')
    dup = dst / f'{src[7].stem} (1){src[7].suffix}'
    shutil.copy2(src[7], dup)
    return {'PANO_0001.JPG': 'panorama 14400x7000, no EXIF', f'{src[4].stem}_thumb{src[4].suffix}':
            'thumbnail 160x120, no EXIF', dup.name: f'identical copy of {src[7].name}'}


def triangulate(photos: Path, out: Path, timeout_s: float = 1800.0) -> dict:
    """`photogram-ros triangulate` of `photos` into `out`: exit status, wall time, the photo names in poses.csv,
    report.json's text and the console's."""
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'triangulate', str(photos), '--out', str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=timeout_s,
                       env={**os.environ, 'PYTHONPATH': str(ROOT)})
    wall_s = time.monotonic() - t0
    from real_surveys import read_poses
    names = list(read_poses(out / 'poses.csv')) if (out / 'poses.csv').exists() else []
    report = (out / 'report.json').read_text() if (out / 'report.json').exists() else ''
    lines = [ln for ln in r.stdout.splitlines() if ln.strip()]
    return {'exit': r.returncode, 'wall_s': round(wall_s, 1), 'oriented': len(names), 'names': names,
            'report': report, 'console': r.stdout + r.stderr, 'last_line': lines[-1] if lines else ''}


def measure(survey: str, tmp: Path) -> dict:
    folder, pattern = SURVEYS[survey]
    src = sorted((ROOT.parent / 'shared' / 'data' / 'photos' / folder / 'images').glob(pattern))
    plain = tmp / 'plain'
    plain.mkdir()
    for p in src:
        shutil.copy2(p, plain / p.name)
    strays = strays_copy(src, tmp / 'strays')
    a = triangulate(plain, tmp / 'out_plain')
    b = triangulate(tmp / 'strays', tmp / 'out_strays')
    return {'survey': survey, 'photos': len(src), 'strays': strays,
            'plain': {k: a[k] for k in ('exit', 'wall_s', 'oriented', 'last_line')},
            'with_strays': {k: b[k] for k in ('exit', 'wall_s', 'oriented', 'last_line')},
            'strays_named_on_console': {n: n in b['console'] for n in strays},
            'strays_named_in_report': {n: n in b['report'] for n in strays},
            'strays_with_a_pose': [n for n in strays if n in b['names']],
            'decompression_bomb_warning': 'DecompressionBomb' in b['console'],
            'oriented_strays_over_plain': round(b['oriented'] / a['oriented'], 3) if a['oriented'] else None}


def main() -> int:
    from faults_stop import append_result
    from machine import machine_info, tree_state
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--survey', choices=sorted(SURVEYS), default='toledo')
    ap.add_argument('--out', default='', help='the result file (default bench/results/<bench>_<commit>.jsonl)')
    a = ap.parse_args()
    state = tree_state()
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix='faults_strays_') as tmp:
        row = measure(a.survey, Path(tmp))
    row = {'bench': 'faults_strays', **state, **row, 'machine': machine_info(),
           'load_avg_before': [round(x, 2) for x in load_before],
           'load_avg_after': [round(x, 2) for x in os.getloadavg()]}
    append_result('faults_strays', state['commit'][:7], row, a.out)
    ok = (row['with_strays']['exit'] == row['plain']['exit'] and not row['strays_with_a_pose']
          and all(row['strays_named_in_report'].values()))
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
