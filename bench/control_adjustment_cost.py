"""What the control adjustment (IncrementalOptions.control_adjustment) costs in flight: the simulator's flights as
keyframes through the adjustment stage with GCPs, once with it and once without, in the same run. Per flight: the
keyframes, the control adjustments made, the seconds of the whole run (every keyframe's adjustment as in flight,
then the final adjustment), the ratio with / without, and the live check points' median once 3 GCPs are used
(H / V, m). One line a flight, through bench/machine.py's ResultWriter (commit, clean-tree flag, cores, load) into
--out (default /tmp/control_adjustment_cost.jsonl), and on stdout.

    .venv/bin/python bench/control_adjustment_cost.py [--presets sample survey] [--out FILE.jsonl]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'tests'))
sys.path.insert(0, str(ROOT))

from helpers.control import targets_file  # noqa: E402
from helpers.stage_flight import fly_stage  # noqa: E402

from bench.machine import ResultWriter  # noqa: E402
from photogram_ros.sim.observations import simulate_keyframes  # noqa: E402
from photogram_ros.sim.scenario import build_world, preset  # noqa: E402


def measure(name: str, n_gcp: int, n_check: int) -> dict:
    cfg = preset(name, n_gcp=n_gcp, n_check=n_check)
    world = build_world(cfg, np.random.default_rng(cfg.seed))
    sk = simulate_keyframes(cfg, world=world, attitude_sigma_deg=None)
    out = {'preset': name, 'keyframes': len(sk.records), 'gcps': n_gcp, 'check_points': n_check}
    with tempfile.TemporaryDirectory() as tmp:
        control = targets_file(Path(tmp) / 'targets.txt', sk.origin, world[2])
        for mode in (False, True):
            t0 = time.perf_counter()
            stage, live = fly_stage(sk, world[2], control, control_adjustment=mode)
            total = time.perf_counter() - t0
            after = [q for n, q in live if n >= 3 and q['check_rmse']['count']]
            med = (np.median([[q['check_rmse']['horizontal_m'], q['check_rmse']['vertical_m']] for q in after], axis=0)
                   if after else [float('nan')] * 2)
            out['with' if mode else 'without'] = {
                'seconds': round(total, 2), 'control_adjustments': sum(h.block_adjusted for h in stage.at.history),
                'live_check_median_m': [round(float(v), 4) for v in med]}
    out['time_ratio'] = round(out['with']['seconds'] / out['without']['seconds'], 2)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--presets', nargs='+', default=['sample', 'survey'])
    ap.add_argument('--out', help='the result file (JSON lines; default /tmp/control_adjustment_cost.jsonl)')
    a = ap.parse_args()
    w = ResultWriter.for_bench(a.out, 'control_adjustment_cost', ['photogram_ros', 'config'])
    for p in a.presets:
        w.write(measure(p, 5 if p == 'sample' else 8, 4))
    return 0


if __name__ == '__main__':
    sys.exit(main())
