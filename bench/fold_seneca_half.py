"""Keyframe by keyframe, where the in-flight adjuster loses or folds seneca_part's every other photo (issue #43).

The tracker (config/replay.yaml's tracker keys) then the adjustment stage (config/replay.yaml's bundle keys,
EXIF fixes at 5 m / 2 m as the camera node gives them), without ROS, each keyframe adjusted as it arrives (no
batches). After every keyframe: its step's status, and for every oriented keyframe of a georeferenced block its
camera centre's distance from its GNSS fix (m) and its tilt from nadir (deg). The first keyframe whose
registration puts a camera >= FAR_M from its fix or tilts it >= TILT_DEG is where the fold starts.

    PYTHONPATH=$PWD .venv/bin/python bench/fold_seneca_half.py [--survey seneca] [--all-photos] \
        [--out bench/results/fold_seneca_half_<commit>.jsonl]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / 'shared' / 'data' / 'photos'
SURVEYS = {'seneca': DATA / 'seneca_part' / 'images', 'brighton': DATA / 'brighton_beach' / 'images',
           'toledo': DATA / 'toledo' / 'images'}
MODULES = ['photogram_ros/core', 'photogram_ros/stages/adjustment.py', 'config/replay.yaml']
FAR_M = 15.0
TILT_DEG = 25.0


def keyframe_state(at) -> list[dict]:
    out = []
    for kf in at.kfs:
        row = {'kid': kf.kid, 'oriented': kf.map_T_cam is not None}
        if kf.map_T_cam is not None and at.georeferenced and kf.fix_enu is not None:
            c = kf.map_T_cam[:3, 3]
            row['from_fix_m'] = round(float(np.linalg.norm(c - np.asarray(kf.fix_enu).ravel())), 1)
            row['tilt_deg'] = round(float(np.degrees(np.arccos(np.clip(-kf.map_T_cam[2, 2], -1, 1)))), 1)
        out.append(row)
    return out


class Clock:
    """The stage's wall clock, simulated: `pace_s` a photo (the replay's tracker pace), so that the keyframes
    waiting for an attitude (a lever arm is set, none comes) go to the adjuster in the batch a replay makes."""

    def __init__(self):
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now

    def __getattr__(self, name):
        import time
        return getattr(time, name)


def run(folder: Path, every: int, pace_s: float, fix_late: bool = False) -> dict:
    import photogram_ros.stages.adjustment as stage_module
    clock = Clock()
    stage_module.time = clock
    from photogram_ros.core.tracker import EncodedImage, Tracker, TrackerParams
    from photogram_ros.io.image_source import FolderSource, read_exif_gps
    from photogram_ros.params import from_dict, load_params_file
    from photogram_ros.nodes.replay_session import EXIF_LENS_BUNDLE
    from photogram_ros.stages.adjustment import AdjustmentParams, AdjustmentStage
    params = load_params_file(str(ROOT / 'config' / 'replay.yaml'))
    tp = {k: v for k, v in params.get('tracker_node', {}).items() if k in TrackerParams.__dataclass_fields__}
    bp = {k: v for k, v in params.get('bundle_node', {}).items() if k in AdjustmentParams.__dataclass_fields__}
    # What `replay` of a photo folder sets on top (nodes/replay_session.py): EXIF lens, no lever arm.
    bp.update(EXIF_LENS_BUNDLE, lever_arm_body_frd_m=[0.0, 0.0, 0.0])
    src = FolderSource(folder)
    camera = src.exif_intrinsics().camera
    tr = Tracker(camera, TrackerParams(**tp))
    stage = AdjustmentStage(from_dict(AdjustmentParams, bp))
    stage.set_camera(camera)
    steps, first_bad, reports, inputs = [], None, [], []
    add = stage.at.add_keyframe

    def add_keyframe(rec, *args, **kw):
        rep = add(rec, *args, **kw)
        reports.append(rep)
        f = rec.fix
        inputs.append({'stamp_ns': rec.stamp_ns, 'ids': sorted(int(i) for i in rec.track_ids if i >= 0),
                       'fix': None if f is None else [f.lat_deg, f.lon_deg, f.h_m, float(f.cov_enu_m2[0, 0]),
                                                      float(f.cov_enu_m2[2, 2])]})
        return rep
    stage.at.add_keyframe = add_keyframe
    entries = list(src.entries)[::every]

    def adjust(new):
        nonlocal first_bad
        for k in new:
            f = k.fix
            if f is not None:
                stage.add_fix(k.stamp_ns, f.lat_deg, f.lon_deg, f.h_m, f.cov_enu_m2, f.status, 2)
            stage.add_keyframe(k.stamp_ns, k.observations['track_id'],
                               np.column_stack([k.observations['u'], k.observations['v']]))
            stage.drain()
            at = stage.at
            kid = next((kf.kid for kf in at.kfs if kf.stamp_ns == k.stamp_ns), None)
            if kid is None:
                print('waiting', k.stamp_ns, flush=True)
                continue
            rep_status = reports[-1].status if reports else None
            state = keyframe_state(at)
            bad = [s['kid'] for s in state if s.get('from_fix_m', 0) >= FAR_M or s.get('tilt_deg', 0) >= TILT_DEG]
            if bad and first_bad is None:
                first_bad = {'after_keyframe': kid, 'keyframes': bad}
            steps.append({'kid': kid, 'frame': k.frame_index, 'oriented_now': state[kid]['oriented'],
                          'n_oriented': sum(s['oriented'] for s in state), 'georeferenced': bool(at.georeferenced),
                          'status': rep_status, 'bad': bad,
                          'state': [s for s in state if s['oriented']]})
            print(kid, k.frame_index, steps[-1]['oriented_now'], steps[-1]['n_oriented'], bad,
                  [(s['kid'], s.get('from_fix_m'), s.get('tilt_deg')) for s in state if s['oriented']][-4:],
                  flush=True)

    for path, stamp in entries:
        clock.now += pace_s
        gps = read_exif_gps(path)
        if gps and not fix_late:
            tr.add_fix(gps.gnss_fix(stamp, 5.0, 2.0))
        new = tr.process(EncodedImage(np.fromfile(str(path), np.uint8)), stamp)
        if gps and fix_late:
            tr.add_fix(gps.gnss_fix(stamp, 5.0, 2.0))
        adjust(new)
    adjust(tr.flush())
    out = stage.finish()
    at = stage.at
    final = keyframe_state(at)
    ts = tr.stats
    print('camera', camera)
    for t, text in [(pr[0], pr[-1]) for pr in stage.diag.problems]:
        print('problem', str(text)[:300])
    print('verdict', stage.diag.values.get('final_verdict_summary'))
    return {'tracker': {'breaks': ts.breaks, 'bridged': ts.bridged, 'keyframes': ts.keyframes,
                        'chain_pairs': ts.chain_pairs, 'chain_verified': ts.chain_verified},
            'photos': len(entries), 'keyframes': len(at.kfs), 'oriented_in_flight': steps[-1]['n_oriented'] if steps else 0,
            'oriented_final': sum(s['oriented'] for s in final), 'first_bad': first_bad,
            'final_bad': [s['kid'] for s in final if s.get('from_fix_m', 0) >= FAR_M or s.get('tilt_deg', 0) >= TILT_DEG],
            'final': final, 'not_oriented': {str(s['kid']): None for s in final if not s['oriented']},
            'outcome': str(out)[:2000], 'steps': steps, 'inputs': inputs}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--survey', default='seneca', choices=sorted(SURVEYS))
    ap.add_argument('--all-photos', action='store_true', help='every photo instead of every other one')
    ap.add_argument('--pace-s', type=float, default=1.0, help='simulated wall time a photo, s')
    ap.add_argument('--fix-late', action='store_true', help="a photo's fix reaches the tracker after the photo")
    ap.add_argument('--out', default='/tmp/fold_seneca_half.jsonl')
    a = ap.parse_args()
    from machine import ResultWriter
    w = ResultWriter(a.out, 'fold_seneca_half', MODULES, fresh=False, echo=False)
    row = run(SURVEYS[a.survey], 1 if a.all_photos else 2, a.pace_s, a.fix_late)
    w.write({'survey': a.survey, 'every': 1 if a.all_photos else 2, 'pace_s': a.pace_s, 'fix_late': a.fix_late, **row})
    print({k: v for k, v in row.items() if k not in ('steps', 'final', 'inputs')})
    return 0


if __name__ == '__main__':
    sys.exit(main())
