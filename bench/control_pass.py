"""`triangulate PHOTOS --gcp`: the adjustment with the vetted control started from the GNSS-only block
(TriangulateOptions.control_from 'gnss_block', the default) against the block built again photo by photo with the
GCPs ('photos', the baseline), measured in the same run on the same photos.

Data: the simulated GCP surveys of bench/photo_triangulation_scale.py (made here or reused from --sims: fN/photos,
RTK geotags, 5 GCPs and 4 check points in gcp_list.txt). Per survey and mode one JSON line: wall and CPU time of the
whole triangulate, of reading + matching and of the aerial triangulation, photos oriented, check-point RMSE, the
focal length after the self-calibration, the machine's load before and after; the modes alternate, and with
--repeat the fastest run of each is kept. Then per survey a comparison line: the speedup of the aerial
triangulation and of the whole command, and the check-point RMSE of each mode.

    .venv/bin/python bench/control_pass.py [--photos 40 100] [--sims DIR] [--repeat 1]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import machine_info  # noqa: E402
from bench.photo_triangulation_scale import LEVER_ARM_CAM_M, _cpu_s, _load, simulated_photos  # noqa: E402
from photogram_ros.io.aerial_triangulation import TriangulateOptions, triangulate  # noqa: E402

MODES = ('photos', 'gnss_block')


def run_once(photos: Path, control_from: str) -> dict:
    row = {'control_from': control_from, 'data': str(photos), 'load_before': _load()}
    t0, cc0 = time.perf_counter(), _cpu_s()
    with tempfile.TemporaryDirectory() as out:
        res = triangulate(photos, out, TriangulateOptions(gcp=str(photos / 'gcp_list.txt'),
                                                          lever_arm_cam_m=LEVER_ARM_CAM_M,
                                                          control_from=control_from),
                          log=lambda text: print(f'# {text}', file=sys.stderr, flush=True))
    rep = res.report
    ck = rep['check']['rmse']
    sc = rep.get('self_calibration') or {}
    row.update(wall_s=round(time.perf_counter() - t0, 2), cpu_s=round(_cpu_s() - cc0, 2),
               matching_s=rep['timing_s']['reading_and_matching'], at_s=rep['timing_s']['aerial_triangulation'],
               photos=res.inputs, oriented=res.registered, tie_points=res.tie_points, check_n=ck.get('n', 0),
               check_h_m=ck.get('horizontal_m'), check_v_m=ck.get('vertical_m'),
               gcp_rmse=rep['gcp']['rmse'], reprojection_rms_px=rep['reprojection_rms_px'],
               fx_px=(sc.get('fx') or {}).get('after'), verdict=res.verdict.get('status'), load_after=_load())
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--photos', type=int, nargs='+', default=[40, 100], help='survey sizes (about; photos)')
    ap.add_argument('--sims', help='folder for the simulated surveys (kept and reused; default: a temporary one)')
    ap.add_argument('--repeat', type=int, default=1, help='runs per survey and mode (the fastest kept)')
    a = ap.parse_args()
    print(json.dumps({'bench': 'control_pass', 'machine': machine_info()}), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        where = Path(a.sims) if a.sims else Path(tmp)
        where.mkdir(parents=True, exist_ok=True)
        for n in a.photos:
            photos = simulated_photos(n, where)
            best: dict = {}
            for _ in range(a.repeat):
                for mode in MODES:
                    row = run_once(photos, mode)
                    print(json.dumps({'bench': 'control_pass', 'run': row}), flush=True)
                    if mode not in best or row['wall_s'] < best[mode]['wall_s']:
                        best[mode] = row
            base, new = best['photos'], best['gnss_block']
            print(json.dumps({'bench': 'control_pass', 'compare': 'gnss_block / photos', 'photos': base['photos'],
                              'at_speedup': round(base['at_s'] / new['at_s'], 3),
                              'speedup': round(base['wall_s'] / new['wall_s'], 3),
                              'oriented': [base['oriented'], new['oriented']],
                              'check_h_cm': [round(100 * r['check_h_m'], 2) for r in (base, new)],
                              'check_v_cm': [round(100 * r['check_v_m'], 2) for r in (base, new)],
                              'loads': [base['load_before'], new['load_before']]}), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
