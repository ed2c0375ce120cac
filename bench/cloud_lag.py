"""Where a keyframe's fused cloud waits: the exposure -> fused cloud lag of bench/inflight_20mp.py, per keyframe.

Reads the pose_history.json that `bench/inflight_20mp.py --keep DIR` writes per run (DIR/<config>/pose_history.json:
every pose each keyframe got on map/keyframe_pose with its time and provisional flag, the time its first pair
cloud was fused by the map, its exposure) and splits each keyframe's lag into
  pose:      exposure -> the first pose stereo may pair with (the first final one, or with --pairs-provisional the
             first of any status);
  partner:   that pose -> the pose of the next keyframe in flight order that stereo may pair with (the settle rule
             needs one newer posed keyframe; its along-line partner is its neighbour);
  stereo_map: the later of the two -> the first fused cloud (stereo's queue, the pair, the message, the map's fusion).
A keyframe counts as fused by the first fused pair it is in, as the newer or the older keyframe (bench/replay_probe.py):
one whose own pairs were shed (max_pair_lag_s) is fused when a later keyframe's pair with it is, the next strip's
across-line pair ~100 s later on the sim flight; `tail_rows` lists the tail's keyframes with their flight times.
and says which one sets the tail (the keyframes at or above the lag's p95). No ROS: it reads the files.

    .venv/bin/python bench/cloud_lag.py /tmp/keep/1s_baseline:final /tmp/keep/1s:provisional \
        --out bench/results/cloud_lag_<commit>.jsonl
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine import ResultWriter  # noqa: E402


def _stats(v) -> dict:
    v = np.asarray(v, float)
    if not v.size:
        return {'n': 0}
    return {'n': int(v.size), 'p50': round(float(np.percentile(v, 50)), 2), 'p95': round(float(np.percentile(v, 95)), 2),
            'max': round(float(v.max()), 2)}


def decompose(doc: dict, pairs_provisional: bool, last_minute_s: float = 60.0) -> dict:
    exposure = {int(s): t for s, t in doc['exposure'].items()}
    fused = {int(s): t for s, t in doc['fused'].items()}
    usable = {}
    for s, hist in doc['poses'].items():
        times = [t for t, provisional, _ in hist if pairs_provisional or not provisional]
        if times:
            usable[int(s)] = min(times)
    kfs = sorted(s for s in usable if s in exposure)
    rows = []
    for i, s in enumerate(kfs):
        if s not in fused:
            continue
        nxt = usable[kfs[i + 1]] if i + 1 < len(kfs) else usable[s]
        ready = max(usable[s], nxt)
        rows.append({'stamp': s, 'index': i, 't_flight_s': exposure[s] - min(exposure.values()),
                     'lag': fused[s] - exposure[s], 'pose': usable[s] - exposure[s],
                     'partner': ready - usable[s], 'stereo_map': fused[s] - ready,
                     'last_minute': exposure[s] >= doc['flight_end'] - 1.0 - last_minute_s})
    lag = np.array([r['lag'] for r in rows])
    p95 = float(np.percentile(lag, 95)) if lag.size else 0.0
    tail = [r for r in rows if r['lag'] >= p95]
    parts = ('pose', 'partner', 'stereo_map')
    out = {'keyframes_fused': len(rows), 'keyframes_posed': len(kfs),
           'lag_exposure_to_fused_cloud_s': _stats(lag),
           'lag_last_minute_s': _stats([r['lag'] for r in rows if r['last_minute']]),
           'parts_s': {k: _stats([r[k] for r in rows]) for k in parts},
           'tail_keyframes': len(tail), 'tail_parts_mean_s': {k: round(float(np.mean([r[k] for r in tail])), 2)
                                                               for k in parts} if tail else {},
           'tail_first_in_flight_order': sorted(kfs.index(r['stamp']) for r in tail),
           # The tail's keyframes (flight order, exposure time in the flight, lag and its parts, s), worst first.
           'tail_rows': [{k: (round(r[k], 1) if isinstance(r[k], float) else r[k])
                          for k in ('index', 't_flight_s', 'lag', 'pose', 'partner', 'stereo_map')}
                         for r in sorted(tail, key=lambda r: -r['lag'])],
           'keyframes_posed_not_fused': [kfs.index(s) for s in kfs if s not in fused]}
    if tail:
        out['tail_dominated_by'] = max(parts, key=lambda k: out['tail_parts_mean_s'][k])
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('runs', nargs='+', metavar='DIR:final|provisional',
                    help='a kept run folder (holding pose_history.json) and which poses stereo paired with')
    ap.add_argument('--label', action='append', default=[], help='a label per run (default: the folder name)')
    ap.add_argument('--out', default='', help='append the rows to this JSON lines file')
    a = ap.parse_args()
    # What it measures: the runs' graph (the stereo and map nodes set the lag's last parts).
    writer = (ResultWriter(a.out, 'cloud_lag', modules=['photogram_ros/nodes/stereo_node.py', 'photogram_ros/stages/map.py',
                                                        'photogram_ros/core/placements.py'], fresh=False)
              if a.out else None)
    for i, spec in enumerate(a.runs):
        folder, _, mode = spec.rpartition(':')
        doc = json.loads((Path(folder) / 'pose_history.json').read_text())
        row = {'run': a.label[i] if i < len(a.label) else Path(folder).name, 'paired_with': mode,
               **decompose(doc, mode == 'provisional')}
        print(json.dumps(row))
        if writer is not None:
            writer.write(row)
    return 0


if __name__ == '__main__':
    sys.exit(main())
