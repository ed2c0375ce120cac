"""One odd photo never sinks a flight (issue 48): `replay` of a real survey whose first photo has another size,
against `replay` of the unmodified survey, in the same run.

The survey (brighton: 18 photos of 4000x2250, DJI FC300S; toledo: 42 of 2400x1800, DJI FC350; or seneca: 41 of
1600x1200) is copied; a copy of its first photo resized (by default to 81 % of its size: 3240x1823 for brighton;
`--scale 0.9` is the held-out folder's 3240x2430 before 3600x2700; `--aspect` changes its height's share against
its width's, e.g. 0.9 for a 4:3 photo cut towards 3:2), its EXIF kept (the same time, a name that sorts first) is
added. Both folders go through `photogram-ros replay`; the keyframes taken and
oriented of each are read from report.json. Writes one JSON line (with the commit, whether the tree was
clean, cores and load) to bench/results/faults_odd_photo_<commit>.jsonl.

    .venv/bin/python bench/faults_odd_photo.py [--survey brighton] [--scale 0.81] [--aspect 1.0]
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
sys.path[:0] = [str(ROOT / 'bench'), str(ROOT)]
os.environ.setdefault('ROS_DOMAIN_ID', '95')

SURVEYS = {'brighton': ('brighton_beach', '*.JPG'), 'toledo': ('toledo', '*.JPG'), 'seneca': ('seneca_part', '*.jpg')}
ODD_SCALE = 0.81   # the odd photo's size as a share of the survey's (default)


def survey_photos(survey: str) -> list[Path]:
    folder, pattern = SURVEYS[survey]
    return sorted((ROOT.parent / 'shared' / 'data' / 'photos' / folder / 'images').glob(pattern))


def odd_first_photo_copy(src: list[Path], dst: Path, scale: float = ODD_SCALE, aspect: float = 1.0
                         ) -> tuple[Path, tuple]:
    """`src` copied into `dst` with a copy of its first photo resized to `scale` of its width and `scale * aspect`
    of its height (EXIF kept; a name that sorts first): (the odd photo's path, its size)."""
    from PIL import Image
    dst.mkdir(parents=True)
    for p in src:
        shutil.copy2(p, dst / p.name)
    odd = dst / ('A_ODD_' + src[0].name)
    with Image.open(src[0]) as im:
        exif = im.info.get('exif', b'')
        size = (int(im.size[0] * scale), int(im.size[1] * scale * aspect))
        im.resize(size).save(odd, quality=90, exif=exif)
    return odd, size


def replay(photos: Path, out: Path, timeout_s: float = 1800.0) -> dict:
    """`photogram-ros replay` of `photos` into `out`: exit status, wall time, keyframes taken and oriented, the
    camera node's diagnostics (as report.json holds them) and the last line."""
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(photos), '--out', str(out),
                        '--quiet'], cwd=ROOT, capture_output=True, text=True, timeout=timeout_s,
                       env={**os.environ, 'PYTHONPATH': str(ROOT)})
    wall_s = time.monotonic() - t0
    rep = json.loads((out / 'report.json').read_text()) if (out / 'report.json').exists() else {}
    lines = [ln for ln in r.stdout.splitlines() if ln.strip()]
    return {'exit': r.returncode, 'wall_s': round(wall_s, 1), 'keyframes_taken': rep.get('keyframes_taken'),
            'keyframes_oriented': rep.get('keyframes_oriented'), 'frames': rep.get('run', {}).get('frames'),
            'camera_node': json.dumps(rep.get('nodes', {}).get('/camera_node', {})),
            'last_line': lines[-1] if lines else '', 'stderr_tail': r.stderr[-2000:]}


def measure(survey: str, tmp: Path, scale: float = ODD_SCALE, aspect: float = 1.0) -> dict:
    """Both replays of `survey` (unmodified, then with the odd first photo) under `tmp`."""
    src = survey_photos(survey)
    plain = tmp / 'plain'
    plain.mkdir()
    for p in src:
        shutil.copy2(p, plain / p.name)
    odd, size = odd_first_photo_copy(src, tmp / 'odd', scale, aspect)
    a = replay(plain, tmp / 'out_plain')
    b = replay(tmp / 'odd', tmp / 'out_odd')
    return {'survey': survey, 'photos': len(src), 'odd_photo': odd.name, 'odd_size': list(size),
            'plain': {k: v for k, v in a.items() if k not in ('camera_node', 'stderr_tail')},
            'odd': {k: v for k, v in b.items() if k not in ('camera_node', 'stderr_tail')},
            'odd_named_by_camera_node': odd.name in b['camera_node'],
            'oriented_odd_over_plain': (round(b['keyframes_oriented'] / a['keyframes_oriented'], 3)
                                        if a['keyframes_oriented'] and b['keyframes_oriented'] is not None else None),
            '_stderr': (a['stderr_tail'], b['stderr_tail'])}


def main() -> int:
    from faults_stop import append_result
    from machine import machine_info, tree_state
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--survey', choices=sorted(SURVEYS), default='brighton')
    ap.add_argument('--out', default='', help='the result file (default bench/results/<bench>_<commit>.jsonl)')
    ap.add_argument('--scale', type=float, default=ODD_SCALE, help='the odd photo\'s width as a share of the others\'')
    ap.add_argument('--aspect', type=float, default=1.0,
                    help='its height\'s share against its width\'s (1: the same aspect; 0.9: 4:3 towards 3:2)')
    a = ap.parse_args()
    if not (0.1 <= a.scale <= 2.0 and 0.5 <= a.aspect <= 2.0 and (a.scale, a.aspect) != (1.0, 1.0)):
        ap.error('--scale in [0.1, 2], --aspect in [0.5, 2], not both 1 (the photo would not be odd)')
    state = tree_state()
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix='faults_odd_') as tmp:
        row = measure(a.survey, Path(tmp), a.scale, a.aspect)
    row.pop('_stderr')
    row = {'bench': 'faults_odd_photo', **state, 'scale': a.scale, 'aspect': a.aspect, **row, 'machine': machine_info(),
           'load_avg_before': [round(x, 2) for x in load_before],
           'load_avg_after': [round(x, 2) for x in os.getloadavg()]}
    append_result('faults_odd_photo', state['commit'][:7], row, a.out)
    return 0 if row['odd']['exit'] == row['plain']['exit'] else 1


if __name__ == '__main__':
    sys.exit(main())
