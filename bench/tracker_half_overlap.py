"""`replay` of brighton_beach's, toledo's or seneca_part's every other photo (bench/real_surveys.half_overlap_block: half the forward overlap,
the tracker's weakest real block) once per parameter file, measured as bench/real_surveys.py measures a replay
(oriented, from GPS with and without a similarity, the block check's verdict).

    PYTHONPATH=$PWD .venv/bin/python bench/tracker_half_overlap.py --params on=config/replay.yaml,off=FILE \
        [--out bench/results/tracker_half_overlap_<commit>.jsonl] [--work /tmp/tracker_half]

Each FILE is a replay parameter file (a copy of config/replay.yaml with a change); its text is kept in the row.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT))
MODULES = ['photogram_ros', 'config/replay.yaml']
KEEP = ('survey', 'pipeline', 'exit', 'wall_s', 'photos', 'verdict', 'keyframes_taken', 'keyframes_oriented',
        'oriented', 'given', 'n', 'sim_h_m', 'sim_v_m', 'rigid_h_m', 'rigid_v_m', 'sim_outliers', 'tilt_max_deg',
        'reprojection_px', 'last_line', 'stderr_last')


def main() -> int:
    import real_surveys as rs
    from machine import ResultWriter
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--params', required=True, help='NAME=FILE,... replay parameter files, one replay each')
    ap.add_argument('--survey', default='brighton', choices=('brighton', 'toledo', 'seneca'))
    ap.add_argument('--out', default='/tmp/tracker_half_overlap.jsonl')
    ap.add_argument('--work', default='/tmp/tracker_half')
    a = ap.parse_args()
    work = Path(a.work)
    src = {'brighton': rs.BRIGHTON, 'toledo': rs.TOLEDO, 'seneca': rs.SENECA}[a.survey] / 'images'
    folder = work / 'blocks' / f'{a.survey}_half'
    ref = rs.half_overlap_block(src, folder)
    w = ResultWriter(a.out, 'tracker_half_overlap', MODULES, fresh=False, echo=True)
    for item in a.params.split(','):
        name, path = item.split('=', 1)
        rs.REPLAY_PARAMS = str(Path(path).resolve())
        (work / name).mkdir(parents=True, exist_ok=True)
        row = rs.run_photos(f'{a.survey}_half', 'replay', folder, work / name, None, reference=ref)
        w.write({'set': name, 'replay_params_file': path, 'replay_params': Path(path).read_text(),
                 'broken': f'every other photo of {a.survey} ({len(ref)}): half the forward overlap',
                 **{k: row.get(k) for k in KEEP}})
    return 0


if __name__ == '__main__':
    sys.exit(main())
