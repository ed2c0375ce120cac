"""Split-merge against the single block on one simulated survey: where each final adjustment ends along the
focal length / GNSS height-bias trade-off, against the simulator's truth.

Both runs are `triangulate PHOTOS --gcp gcp_list.txt` (the photos' EXIF camera, the automatic self-calibration,
the GNSS bias estimated from the GCPs) on the same photos and matches, workers 1: the single block
(`--split-photos 0`) and split-merge above --split-photos. Per run one JSON line: check points (H / V RMSE, n),
the focal length found and its sigma (the report's, with the GNSS bias free beside it), the GNSS bias
estimated, the GNSS noise used and the geotags rejected, and the cameras against the simulator's true centres
(mean and RMS height error, horizontal RMS): a bias that is not the fixes' own shows as the cameras' mean height
error. The simulator's fixes are RTK (about 1 cm / 3 cm, no bias); its geotags lag along the track (about 0.2 m).
The lines go through bench/machine.py's ResultWriter (commit, clean-tree flag, cores, load) into --out (default
/tmp/split_merge_paths.jsonl), and on stdout.

    .venv/bin/python bench/split_merge_paths.py [--photos 100] [--sims DIR] [--split-photos 60] [--keep DIR]
        [--out FILE.jsonl]
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import ResultWriter  # noqa: E402
from bench.photo_triangulation_scale import LEVER_ARM_CAM_M, simulated_photos  # noqa: E402
from photogram_ros.core.geodesy import LocalFrame  # noqa: E402
from photogram_ros.core.split_merge import SplitMergeOptions  # noqa: E402
from photogram_ros.io.aerial_triangulation import TriangulateOptions  # noqa: E402
from photogram_ros.io.triangulate_action import triangulate  # noqa: E402


def cameras_against_truth(out: Path, truth: dict) -> dict:
    """poses.csv of a run against the simulator's true camera centres (photo IMG_NNNN is frame NNNN), m."""
    o = truth['origin']
    frame = LocalFrame(o['lat_deg'], o['lon_deg'], o['h_m'])
    true_c = {f['index']: np.array(f['map_T_cam'], float).reshape(4, 4)[:3, 3] for f in truth['frames']}
    with open(out / 'poses.csv') as f:
        rows = list(csv.DictReader(f))
    d = np.array([np.asarray(frame.geodetic_to_enu(float(r['lat_deg']), float(r['lon_deg']), float(r['h_m'])))
                  - true_c[int(Path(r['image']).stem.split('_')[-1])] for r in rows]).reshape(-1, 3)
    return {'n': len(d), 'mean_dz_m': float(d[:, 2].mean()), 'rms_dz_m': float(np.sqrt(np.mean(d[:, 2] ** 2))),
            'rms_dh_m': float(np.sqrt(np.mean(np.sum(d[:, :2] ** 2, axis=1))))}


def run(photos: Path, split: int, keep: Path | None) -> dict:
    sm = None if split == 0 else SplitMergeOptions(split_photos=split)
    with tempfile.TemporaryDirectory() as tmp:
        out = keep / f'split{split}' if keep is not None else Path(tmp)
        t0 = time.perf_counter()
        res = triangulate(photos, out, TriangulateOptions(gcp=str(photos / 'gcp_list.txt'),
                                                          lever_arm_cam_m=LEVER_ARM_CAM_M, workers=1, split=sm),
                          log=lambda text: print(f'# {text}', file=sys.stderr, flush=True), progress=False)
        rep = res.report
        sc = rep.get('self_calibration') or {}
        fx = sc.get('fx') or {}
        gn = rep.get('gnss_noise') or {}
        ck = rep['check']['rmse']
        row = {'split_photos': split, 'wall_s': round(time.perf_counter() - t0, 1), 'oriented': res.registered,
               'check_n': ck.get('n', 0), 'check_h_m': ck.get('horizontal_m'), 'check_v_m': ck.get('vertical_m'),
               'fx_px': fx.get('after'), 'fx_sigma_px': fx.get('sigma', fx.get('sigma_unreliable')),
               'focal': (sc.get('focal') or {}).get('reason'),
               'gnss_bias_enu_m': rep['gnss'].get('estimated_bias_enu_m'),
               'gnss_used_hv_m': [gn.get('used_h_m'), gn.get('used_v_m')],
               'gnss_rejected': len(gn.get('rejected', [])),
               'cameras': cameras_against_truth(out, json.loads((photos.parent / 'ground_truth.json').read_text()))}
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--photos', type=int, default=100, help='survey size (about; photos)')
    ap.add_argument('--sims', type=Path, default=Path(tempfile.gettempdir()) / 'scale_sims',
                    help='where the simulated surveys are made or found')
    ap.add_argument('--split-photos', type=int, default=60, help='split-merge above this many photos')
    ap.add_argument('--keep', type=Path, default=None, help='keep the runs\' outputs here (else temporary)')
    ap.add_argument('--out', default=None, help='the result file (JSON lines; default /tmp/split_merge_paths.jsonl)')
    a = ap.parse_args()
    w = ResultWriter.for_bench(a.out, 'split_merge_paths', ['photogram_ros', 'config'])
    photos = simulated_photos(a.photos, a.sims)
    truth = json.loads((photos.parent / 'ground_truth.json').read_text())
    err = np.array([f['error_enu_m'] for f in truth['fixes']])
    w.write({'survey': str(photos), 'fix_error_mean_enu_m': err.mean(0).tolist(),
             'fix_error_sd_enu_m': err.std(0).tolist()})
    for split in (0, a.split_photos):
        w.write({'run': run(photos, split, a.keep)})


if __name__ == '__main__':
    main()
