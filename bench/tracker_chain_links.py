"""The tracker alone (no ROS, no adjuster) over seneca_part's 41 photos with config/replay.yaml's tracker
parameters, once per switch set: what the chain's early stop (chain_enough_verified, chain_stop_after_failures)
and KLT's rest (klt_rest_after_losses) change in the links the adjuster gets.

Per set (JSON lines, --out appends): chain pairs tried and verified, CPU s per frame (time.process_time), and
against the first set (all off): the keyframe pairs whose shared track ids (>= LINK_MIN) changed, and the track
ids the strip that folded in the replay with all three on (keyframes 29-34 and 36, bench/results/
real_surveys_6e10adb.jsonl) shares with the rest of the block, per keyframe of the rest. The sets are built
without TrackerParams.check, which refuses KLT's rest with the early stop: this bench shows why.

    PYTHONPATH=$PWD .venv/bin/python bench/tracker_chain_links.py [--out bench/results/tracker_chain_links_<commit>.jsonl]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT))
PHOTOS = ROOT.parent / 'shared' / 'data' / 'photos' / 'seneca_part' / 'images'
REPLAY_TRACKER = {'keyframe_overlap': 0.8, 'features_fallback': True}   # config/replay.yaml's tracker_node keys
OFF = {'chain_enough_verified': 0, 'chain_stop_after_failures': 0, 'klt_rest_after_losses': 0}
SETS = {'off': {}, 'chain_stop': {'chain_enough_verified': 4, 'chain_stop_after_failures': 3},
        'klt_rest': {'klt_rest_after_losses': 3},
        'both': {'chain_enough_verified': 4, 'chain_stop_after_failures': 3, 'klt_rest_after_losses': 3}}
FOLDED_STRIP = (29, 30, 31, 32, 33, 34, 36)   # keyframe indices (= photo indices: every photo is a keyframe)
LINK_MIN = 15
MODULES = ['photogram_ros/core', 'photogram_ros/io/image_source.py']


def run(over: dict) -> tuple[dict, list[set]]:
    from photogram_ros.core.tracker import EncodedImage, Tracker, TrackerParams
    from photogram_ros.io.image_source import FolderSource, read_exif_gps
    src = FolderSource(PHOTOS)
    tr = Tracker(src.exif_intrinsics().camera, TrackerParams(**{**REPLAY_TRACKER, **OFF, **over}))
    kfs, cpu = [], 0.0
    for path, stamp in src.entries:
        gps = read_exif_gps(path)
        if gps:
            tr.add_fix(gps.gnss_fix(stamp, 3.0, 5.0))
        data = np.fromfile(str(path), np.uint8)
        t0 = time.process_time()
        kfs += tr.process(EncodedImage(data), stamp)
        cpu += time.process_time() - t0
    kfs += tr.flush()
    s = tr.stats
    return ({'frames': s.frames, 'keyframes': s.keyframes, 'breaks': s.breaks, 'bridged': s.bridged,
             'chain_pairs': s.chain_pairs, 'chain_verified': s.chain_verified,
             'cpu_s_per_frame': round(cpu / max(s.frames, 1), 3)},
            [set(k.observations['track_id'].tolist()) for k in kfs])


def links(ids: list[set]) -> dict:
    return {(b, a): len(ids[a] & ids[b]) for a in range(len(ids)) for b in range(a) if len(ids[a] & ids[b]) >= LINK_MIN}


def strip_ties(ids: list[set]) -> dict:
    inside = set().union(*[ids[i] for i in FOLDED_STRIP if i < len(ids)])
    rest = [j for j in range(len(ids)) if j not in FOLDED_STRIP]
    per = {j: len(inside & ids[j]) for j in rest if len(inside & ids[j]) >= LINK_MIN}
    return {'tracks_shared_with_rest': len(inside & set().union(*[ids[j] for j in rest])),
            'per_keyframe': {str(j): n for j, n in per.items()}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--out', default='')
    ap.add_argument('--sets', default=','.join(SETS))
    a = ap.parse_args()
    from machine import ResultWriter
    w = ResultWriter(a.out or '/tmp/tracker_chain_links.jsonl', 'tracker_chain_links', MODULES, fresh=False,
                     echo=True)
    base = None
    for name in a.sets.split(','):
        stats, ids = run(SETS[name])
        row = {'photos': 'seneca_part', 'set': name, 'tracker_set': SETS[name], **stats,
               'folded_strip': strip_ties(ids)}
        if base is None:
            base = links(ids)
        else:
            now = links(ids)
            row['links_changed_vs_off'] = {f'{i}-{j}': [base.get((i, j), 0), now.get((i, j), 0)]
                                           for (i, j) in sorted(set(base) | set(now))
                                           if abs(base.get((i, j), 0) - now.get((i, j), 0)) >= 5}
        w.write(row)
    return 0


if __name__ == '__main__':
    sys.exit(main())
