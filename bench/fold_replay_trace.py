"""`photogram-ros replay` in this process with the adjustment stage traced: after every keyframe the stage takes
(stages/adjustment.AdjustmentStage.process), its step's status, whether it was the newest of its batch, and for
every oriented keyframe of a georeferenced block its distance from its fix (m) and tilt from nadir (deg); the
same after the final adjustment. One JSON line per step in TRACE (a diagnosis aid, not a measurement).

    PYTHONPATH=$PWD .venv/bin/python bench/fold_replay_trace.py TRACE.jsonl replay FOLDER --out OUT --quiet [...]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT))


def main() -> int:
    from fold_seneca_half import keyframe_state

    import photogram_ros.stages.adjustment as sa
    trace = open(sys.argv[1], 'w')
    t0 = time.monotonic()
    process, full = sa.AdjustmentStage.process, sa.AdjustmentStage.full_adjustment

    def write(stage, what: str, **kw):
        at = stage.at
        state = keyframe_state(at)
        trace.write(json.dumps({'t_s': round(time.monotonic() - t0, 2), 'what': what, **kw,
                                'n_oriented': sum(s['oriented'] for s in state),
                                'georeferenced': bool(at.georeferenced), 'pending': stage.waiting_keyframes(),
                                'state': [s for s in state if s['oriented']]}) + '\n')
        trace.flush()

    def traced_process(self, rec, publish=True):
        process(self, rec, publish)
        kid = next((kf.kid for kf in self.at.kfs if kf.stamp_ns == rec.stamp_ns), None)
        f = rec.fix
        write(self, 'keyframe', kid=kid, stamp_ns=rec.stamp_ns, publish=publish,
              fix=None if f is None else [f.lat_deg, f.lon_deg, f.h_m, float(f.cov_enu_m2[0, 0]), float(f.cov_enu_m2[2, 2])],
              n_obs=len(rec.track_ids), ids=sorted(int(i) for i in rec.track_ids if i >= 0))

    def traced_full(self):
        out = full(self)
        write(self, 'full_adjustment', outcome=str(out))
        return out

    import photogram_ros.core.incremental as inc
    add = inc.IncrementalAT.add_keyframe
    ats: dict[int, int] = {}

    def traced_add(self, rec, *args, **kw):
        rep = add(self, rec, *args, **kw)
        state = keyframe_state(self)
        for s, kf in zip(state, self.kfs):
            if kf.map_T_cam is not None:
                s['axis'] = [round(float(v), 3) for v in kf.map_T_cam[:3, 2]]
                s['centre'] = [round(float(v), 1) for v in kf.map_T_cam[:3, 3]]
        trace.write(json.dumps({'t_s': round(time.monotonic() - t0, 2), 'what': 'add_keyframe',
                                'adjuster': ats.setdefault(id(self), len(ats)), 'kid': len(self.kfs) - 1,
                                'status': rep.status, 'registered': rep.registered,
                                'georeferenced': bool(self.georeferenced), 'provisional': bool(self.block.provisional),
                                'state': [s for s in state if s['oriented']]}) + '\n')
        trace.flush()
        return rep
    inc.IncrementalAT.add_keyframe = traced_add
    import photogram_ros.core.at_register as ar

    def hook(name):
        orig = getattr(ar.Registration, name)

        def call(self, kf, *args, **kw):
            rep = orig(self, kf, *args, **kw)
            T = kf.map_T_cam
            trace.write(json.dumps({'what': name, 'block': id(self.block) % 10000, 'kid': kf.kid, 'status': rep.status,
                                    'axis': None if T is None else [round(float(v), 3) for v in T[:3, 2]],
                                    'centre': None if T is None else [round(float(v), 2) for v in T[:3, 3]]}) + '\n')
            return rep
        setattr(ar.Registration, name, call)
    for name in ('resect', 'relative', 'two_view'):
        hook(name)
    import pickle
    rp = ar.relative_pose
    pairs = []

    def saved_relative_pose(xn1, xn2, *args, **kw):
        res = rp(xn1, xn2, *args, **kw)
        pairs.append((xn1, xn2, args, kw, res.status, res.cam2_T_cam1))
        with open(sys.argv[1] + '.pairs.pkl', 'wb') as f:
            pickle.dump(pairs, f)
        trace.write(json.dumps({'what': 'relative_pose', 'pair': len(pairs) - 1, 'n': len(xn1),
                                'status': res.status, 'inliers': int(res.inliers.sum())}) + '\n')
        return res
    ar.relative_pose = saved_relative_pose
    sa.AdjustmentStage.process = traced_process
    sa.AdjustmentStage.full_adjustment = traced_full
    from photogram_ros.cli import main as cli_main
    return cli_main(sys.argv[2:])


if __name__ == '__main__':
    sys.exit(main())
