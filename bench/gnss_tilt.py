"""The tilt of the fixes' heights (IncrementalOptions.estimate_gnss_tilt) against the GNSS bias alone, on the
simulator's sample flight with 5 GCPs and 4 check points (3 N-S strips 34.5 m apart, 40 m high, RTK fixes whose
error wanders with a 60 s time constant), for several simulated flights (seeds) and once with a lean of
`--lean` m/m eastwards added to the fixes' heights.

Per run and mode of `gnss_tilt` (never: the bias alone; always: the bias and the tilt; auto: the tilt kept when an
F-test on the GCPs' height residuals says it pays): the check points' RMSE (H, V) after the final adjustment, the
camera centres' mean offset from the truth (E, N, U), the cameras' mean rotation against the truth about E and N
(mrad), and whether the tilt was estimated. One JSON line per run on stdout, or appended to --out through
bench/machine.py's ResultWriter (commit, clean-tree flag, cores, load, the modules it ran); a table on stderr.

    .venv/bin/python bench/gnss_tilt.py [--seeds 1 2 3 4 5 6] [--lean 0.01] [--out FILE.jsonl]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from attitude_mode import block_against_truth, fly, targets_file  # noqa: E402
from machine import ResultWriter  # noqa: E402

from photogram_ros.sim.observations import simulate_keyframes  # noqa: E402
from photogram_ros.sim.scenario import build_world, preset  # noqa: E402


MODES = ('never', 'always', 'auto')


def leaned(sk, lean: float):
    """sk with lean (m/m) x (east - the fixes' mean east) added to every fix's height."""
    east = np.array([sk.origin.geodetic_to_enu(r.fix.lat_deg, r.fix.lon_deg, r.fix.h_m)[0] for r in sk.records])
    records = [dataclasses.replace(r, fix=dataclasses.replace(r.fix, h_m=r.fix.h_m + lean * (e - east.mean())))
               for r, e in zip(sk.records, east)]
    return dataclasses.replace(sk, records=records)


def run(seed: int, lean: float) -> dict:
    cfg = dataclasses.replace(preset('sample', n_gcp=5, n_check=4), seed=seed)
    world = build_world(cfg, np.random.default_rng(cfg.seed))
    sk = simulate_keyframes(cfg, world=world, attitude_sigma_deg=None)
    if lean:
        sk = leaned(sk, lean)
    out = {'seed': seed, 'lean_added_m_per_m': lean}
    with tempfile.TemporaryDirectory() as tmp:
        control = str(targets_file(Path(tmp) / 'targets.txt', sk.origin, world[2]))
        for mode in MODES:
            stage, _ = fly(sk, world[2], control, gnss_tilt=mode)
            q = stage.quality()['check_rmse']
            b = block_against_truth(sk, stage.at)
            out[mode] = {'check_h_m': round(q['horizontal_m'], 4), 'check_v_m': round(q['vertical_m'], 4),
                         'camera_offset_m_enu': b['centre_offset_m_enu'],
                         'rotation_mrad_en': b['rotation_mrad_enu'][:2],
                         'tilt_estimated': bool(stage.at.gnss_tilt_estimated), 'tilt_test': stage.at.gnss_tilt_test,
                         'slope_mm_per_m': (np.asarray(stage.at.gnss_slope) * 1e3).round(2).tolist()}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seeds', type=int, nargs='+', default=[1, 2, 3, 4, 5, 6])
    ap.add_argument('--lean', type=float, default=0.01, help='m/m added to the fixes of one more run (first seed)')
    ap.add_argument('--out', help='append the JSON lines to this file')
    a = ap.parse_args()
    rows = [run(s, 0.0) for s in a.seeds] + ([run(a.seeds[0], a.lean)] if a.lean else [])
    sys.stderr.write('| seed | lean added (mm/m) | ' + ' | '.join(f'check H / V, tilt {m} (cm)' for m in MODES) + ' | '
                     + ' | '.join(f'cameras E / N / U, tilt {m} (cm)' for m in MODES) + ' | auto: F (its 90 % quantile), kept |\n|'
                     + '---|' * (3 + 2 * len(MODES)) + '\n')
    for r in rows:
        cells = [f"{r[m]['check_h_m'] * 100:.2f} / {r[m]['check_v_m'] * 100:.2f}" for m in MODES]
        cams = [' / '.join(f'{v * 100:.1f}' for v in r[m]['camera_offset_m_enu']) for m in MODES]
        t = r['auto']['tilt_test']
        test = f"{t['f']:.1f} ({t['f_crit']:.1f}), {'yes' if t['kept'] else 'no'}" if t else 'not made'
        sys.stderr.write(f"| {r['seed']} | {r['lean_added_m_per_m'] * 1e3:g} | {' | '.join(cells)} | {' | '.join(cams)} | "
                         f'{test} |\n')
    if a.out:
        w = ResultWriter(a.out, 'gnss_tilt', ['photogram_ros', 'config'], fresh=False)
        for r in rows:
            w.write(r)
    else:
        sys.stdout.write(''.join(json.dumps(r) + '\n' for r in rows))
    return 0


if __name__ == '__main__':
    sys.exit(main())
