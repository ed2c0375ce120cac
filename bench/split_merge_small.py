"""Split-merge against the single block on the 41-photo survey of tests/test_triangulate_dask_split.py: the
figures that test gates, from one run of each.

The survey is the test's fixture (preset('survey', photos=True, fps=0.65, n_lines=2, line_length_m=140.0),
simulated afresh into a temporary folder); both runs are `triangulate` with its GCPs and the lever arm
(0, -0.05, -0.2) m as the test's: the single block (split None) and split-merge in sub-blocks of 30 photos'
cores (SplitMergeOptions(split_photos=30), in this process). Lines (JSON, through bench/machine.py's
ResultWriter: commit, clean-tree flag, cores, load) into --out (default
bench/results/split_merge_small_<commit7>.jsonl):

- `survey`: the simulated fixes' error (mean and SD, ENU m).
- `run` per mode: check points (H / V RMSE, n), the self-calibrated fx, the GNSS noise used and the geotags
  rejected, the GNSS bias, the cameras against the simulator's truth; for split-merge also every sub-block (photos,
  status, its camera's fx, its check points, its cameras against truth), the overlaps (shared cameras' RMS before
  and after the merge's similarities: `camera_rms_m` is what the test gates), the similarities' scales and shifts,
  the merged block's check points before the global adjustment, and the global adjustment (status, solves,
  iterations, wall time, camera moves: `centre_rms_m` is what the test gates).
- `ratio`: the split block's check RMSE over the single block's (H, V).

    .venv/bin/python bench/split_merge_small.py [--keep DIR] [--out FILE.jsonl]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import ResultWriter, tree_state  # noqa: E402
from bench.split_merge_paths import cameras_against_truth  # noqa: E402
from photogram_ros.core.split_merge import SplitMergeOptions  # noqa: E402
from photogram_ros.io.aerial_triangulation import TriangulateOptions  # noqa: E402
from photogram_ros.io.triangulate_action import triangulate  # noqa: E402
from photogram_ros.sim.scenario import preset, simulate  # noqa: E402

SPLIT = 30                      # as tests/test_triangulate_dask_split.py
LEVER = (0.0, -0.05, -0.2)


def _fx(rep: dict):
    return ((rep.get('self_calibration') or {}).get('fx') or {}).get('after')


def run(photos: Path, split: int | None, out: Path, truth: dict) -> dict:
    lines: list = []
    sm = None if split is None else SplitMergeOptions(split_photos=split)
    t0 = time.perf_counter()
    res = triangulate(photos, out, TriangulateOptions(gcp=str(photos / 'gcp_list.txt'), lever_arm_cam_m=LEVER,
                                                      split=sm),
                      log=lambda text: (lines.append(text), print(f'# {text}', file=sys.stderr, flush=True)),
                      progress=False)
    rep = res.report
    gn = rep.get('gnss_noise') or {}
    row = {'mode': 'single' if split is None else f'split{split}', 'wall_s': round(time.perf_counter() - t0, 1),
           'inputs': res.inputs, 'oriented': res.registered, 'verdict': res.verdict.get('status'),
           'check_rmse': rep['check']['rmse'], 'fx_px': _fx(rep),
           'gnss_used_hv_m': [gn.get('used_h_m'), gn.get('used_v_m')], 'gnss_rejected': gn.get('rejected', []),
           'gnss_bias_enu_m': rep['gnss'].get('estimated_bias_enu_m'),
           'cameras': cameras_against_truth(out, truth)}
    s = rep.get('split_merge')
    if s:
        g = s['global_adjustment']
        row['sub_blocks'] = [{'index': b['index'], 'photos': b['photos'], 'oriented': b['oriented'],
                              'status': b['status'], 'fx_px': (b.get('camera') or {}).get('fx'),
                              'check_rmse': b['check_rmse'],
                              'cameras': cameras_against_truth(out / 'sub_blocks' / f'{b["index"]:02d}', truth)}
                             for b in s['sub_blocks']]
        row['overlaps'] = s['overlaps']
        row['similarities'] = [None if x is None else {'scale': x['scale'], 't_m': x['t_m']}
                               for x in s['similarities']]
        row['merged_check_rmse'] = s['merged_check_rmse']
        row['global_adjustment'] = {k: g.get(k) for k in ('status', 'solves', 'iterations', 'wall_s', 'refine',
                                                          'refine_chosen_by', 'camera_moves')}
        row['sub_blocks_line'] = any('adjustment of the sub-blocks: 2/2 sub-blocks' in t for t in lines)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--keep', type=Path, default=None, help='keep the survey and the runs\' outputs here')
    ap.add_argument('--out', default=None, help='the result file (JSON lines; default '
                                                'bench/results/split_merge_small_<commit7>.jsonl)')
    a = ap.parse_args()
    out_file = a.out or ROOT / 'bench' / 'results' / f'split_merge_small_{tree_state()["commit"][:7]}.jsonl'
    w = ResultWriter(out_file, 'split_merge_small', ['photogram_ros', 'config'])
    with tempfile.TemporaryDirectory() as tmp:
        base = a.keep or Path(tmp)
        t0 = time.perf_counter()
        simulate(preset('survey', photos=True, fps=0.65, n_lines=2, line_length_m=140.0), base / 'flight')
        photos = base / 'flight' / 'photos'
        truth = json.loads((base / 'flight' / 'ground_truth.json').read_text())
        err = np.array([f['error_enu_m'] for f in truth['fixes']])
        w.write({'survey': {'photos': len(list(photos.glob('*.JPG'))), 'simulate_s': round(time.perf_counter() - t0, 1),
                            'fix_error_mean_enu_m': err.mean(0).tolist(), 'fix_error_sd_enu_m': err.std(0).tolist()}})
        rows = {}
        for split in (None, SPLIT):
            rows[split] = run(photos, split, base / ('single' if split is None else f'split{split}'), truth)
            w.write({'run': rows[split]})
        c1, c = rows[None]['check_rmse'], rows[SPLIT]['check_rmse']
        w.write({'ratio': {k: (c[k] / c1[k] if c1.get(k) else None) for k in ('horizontal_m', 'vertical_m')}})


if __name__ == '__main__':
    main()
