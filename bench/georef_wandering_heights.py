"""What the off-GNSS full adjustment (core/incremental.py off_gnss_sigma) does on a flight whose geotag heights wander.

tests/test_poor_geotags.py's flight: the simulator's tiny preset (27 keyframes over 27 x 48 m, no GCP), its fixes
moved by a consumer camera's errors (heights a random walk 40 m peak to peak, a horizontal bias of 15 m that wanders
8 m, 2.5 m white noise; stated 5 m H / 2 m V: `consumer_errors`). For each off_gnss_sigma it feeds the keyframes to
IncrementalAT, then runs the final adjustment, and records:
- each off-GNSS full adjustment: the keyframe it came at, the window's figures at the test (`off_gnss_figures`) and
  the block's mean optical axis from the vertical after it (deg);
- the off-GNSS test's yardstick at the end of the flight (`off_gnss_noise_hv`) and the block's tilt then;
- after the final adjustment: its levelling (`gnss_noise['level']`: the heights' slope, the tilt kept, the heights'
  scatter it read), the mean optical axis against the truth (deg), the cameras' vertical RMS against the truth (m).

    .venv/bin/python bench/georef_wandering_heights.py [--sigmas 0,2.5]

Rows: bench/results/georef_wandering_heights_<commit>.jsonl, one per off_gnss_sigma.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT / 'tests'))
MODULES = ['photogram_ros/core']


def _tilt_deg(at) -> float:
    """The block's mean optical axis from the vertical (deg)."""
    a = np.mean([at.kfs[k].map_T_cam[:3, 2] for k in at.registered], axis=0)
    return round(float(np.degrees(np.arccos(-a[2] / np.linalg.norm(a)))), 2)


def fly(sigma: float) -> dict:
    from test_poor_geotags import _figures, _geotagged, consumer_errors

    from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions
    from photogram_ros.sim.observations import simulate_keyframes
    from photogram_ros.sim.scenario import build_world, preset

    cfg = preset('tiny', n_gcp=0, n_check=0)
    sk = simulate_keyframes(cfg, gnss_mode='rtk_fixed', world=build_world(cfg, np.random.default_rng(cfg.seed)))
    err = consumer_errors(len(sk.records))
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m), off_gnss_sigma=sigma),
                       origin=sk.origin)
    t0 = time.perf_counter()
    adjustments = []
    for i, rec in enumerate(_geotagged(sk, err)):
        n = at.off_gnss_adjustments
        at.add_keyframe(rec)
        if at.off_gnss_adjustments > n:
            fig = at.off_gnss_figures()
            adjustments.append({'keyframe': i, 'newest_sigmas': fig.get('newest_sigmas'),
                                'mean_sigmas': fig.get('mean_sigmas'), 'tilt_after_deg': _tilt_deg(at)})
    end = {'yardstick_hv': [round(float(f), 2) for f in at.off_gnss_noise_hv], 'tilt_deg': _tilt_deg(at)}
    at.full_adjustment()
    ang, h, v, allowed = _figures(at, sk, err)
    level = {k: round(float(x), 3) for k, x in at.gnss_noise.get('level', {}).items()}
    return {'off_gnss_sigma': sigma, 'keyframes': len(sk.records), 'oriented': len(at.registered),
            'off_gnss_adjustments': adjustments, 'flight_end': end,
            'final': {'level': level, 'axis_vs_truth_deg': round(ang, 3), 'cameras_v_rms_m': round(v, 3),
                      'cameras_h_rms_m': round(h, 3), 'h_the_geotags_allow_m': round(allowed, 3),
                      'scale_hv': [round(float(at.gnss_noise.get(k, float('nan'))), 3) for k in ('scale_h', 'scale_v')],
                      'yardstick_hv': [round(float(f), 2) for f in at.off_gnss_noise_hv]},
            'wall_s': round(time.perf_counter() - t0, 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--sigmas', default='0,2.5', help='off_gnss_sigma values, comma separated')
    a = ap.parse_args()
    from machine import ResultWriter, tree_state
    w = ResultWriter(ROOT / 'bench' / 'results' / f'georef_wandering_heights_{tree_state()["commit"][:7]}.jsonl',
                     'georef_wandering_heights', MODULES)
    for s in a.sigmas.split(','):
        row = fly(float(s))
        w.write(row)
        print(row, flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
