"""Cost of ArUco target detection (`detect_targets`) per frame, against the whole-image full-resolution
search it replaced (the baseline, timed in the same run on the same frames), and its cost beside the tracker.

Frame sets: the sample flight's frames (640x480, searched whole: the baseline's path); the same frames
upscaled 4x (2560x1920, markers 96-120 px); real 1080p video frames (phantom3_village, no markers) and the
same with markers painted in (18-100 px); real 4000x2250 photos (brighton_beach, no markers) and a 12 MP
(4000x3000) frame with markers painted in (36-200 px). Per set: median and p90 ms of both, the ratio,
the detections of both and the largest centre difference. Then the tracker on the sample flight (its own
time per keyframe) and `detect_keyframe_targets` on its keyframes, as the tracker node runs it.
One JSON line per set (bench/machine.py's ResultWriter: commit, clean-tree flag, cores, load) to --out and stdout.

    .venv/bin/python bench/target_detection.py [--bag bags/sample_flight] [--repeat 3] [--out F]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT / 'tests'))

from test_target_detection_fast import full_resolution_detection, paint_markers  # noqa: E402
from tracker_fps import load_frames  # noqa: E402

from bench.machine import ResultWriter  # noqa: E402
from photogram_ros.core.control import detect_keyframe_targets  # noqa: E402
from photogram_ros.core.evaluation import detect_targets  # noqa: E402
from photogram_ros.core.tracker import Tracker  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'


def timed(fn, img, repeat: int):
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn(img)
        best = min(best, time.perf_counter() - t0)
    return out, best * 1e3


def compare_set(name: str, frames: list, repeat: int) -> dict:
    new_ms, old_ms, n_new, n_old, same_ids, diff = [], [], 0, 0, 0, 0.0
    for img in frames:
        full, t_old = timed(full_resolution_detection, img, repeat)
        fast, t_new = timed(detect_targets, img, repeat)
        old_ms.append(t_old)
        new_ms.append(t_new)
        n_old += len(full)
        n_new += len(fast)
        same_ids += sorted(d.marker_id for d in fast) == sorted(d.marker_id for d in full)
        by_id = {d.marker_id: d.center_uv for d in full}
        diff = max([diff] + [float(np.linalg.norm(d.center_uv - by_id[d.marker_id]))
                             for d in fast if d.marker_id in by_id])
    h, w = frames[0].shape[:2]
    return {'bench': 'target_detection', 'set': name, 'image': f'{w}x{h}', 'frames': len(frames),
            'new_ms_median': float(np.median(new_ms)), 'new_ms_p90': float(np.percentile(new_ms, 90)),
            'baseline_ms_median': float(np.median(old_ms)), 'baseline_ms_p90': float(np.percentile(old_ms, 90)),
            'ratio_median': float(np.median(old_ms) / np.median(new_ms)),
            'ratio_total': float(np.sum(old_ms) / np.sum(new_ms)),
            'detections_new': n_new, 'detections_baseline': n_old, 'frames_same_ids': same_ids,
            'max_centre_diff_px': diff, 'load_avg': os.getloadavg()[0]}


def frame_sets(bag_frames: list) -> list[tuple[str, list]]:
    rng = np.random.default_rng(1)
    with_markers = [img for img in bag_frames if full_resolution_detection(img)]
    sets = [('sample_bag', bag_frames),
            ('sample_bag_x4', [cv2.resize(img, (2560, 1920), interpolation=cv2.INTER_CUBIC)
                               for img in with_markers[::3]])]
    video = sorted((DATA / 'video' / 'phantom3_village' / 'rgb').glob('*.jpg'))[::10]
    if video:
        imgs = [cv2.imread(str(p)) for p in video]
        sets += [('phantom3_video', imgs),
                 ('phantom3_video_markers', [paint_markers(img, (18, 20, 24, 30, 40, 60, 100), rng)[0]
                                             for img in imgs[:5]])]
    photos = sorted((DATA / 'photos' / 'brighton_beach' / 'images').glob('*.JPG'))[::3]
    if photos:
        imgs = [cv2.imread(str(p)) for p in photos]
        sets += [('brighton_photos', imgs),
                 ('12mp_markers', [paint_markers(cv2.resize(img, (4000, 3000), interpolation=cv2.INTER_AREA),
                                                 (36, 44, 60, 80, 120, 200), rng)[0] for img in imgs[:3]])]
    return sets


def tracker_overhead(camera, frames: list, repeat: int) -> dict:
    tr = Tracker(camera)
    t0 = time.perf_counter()
    kfs = []
    for stamp, img in frames:
        kfs += tr.process(img, stamp)
    kfs += tr.flush()
    track_s = time.perf_counter() - t0
    times, found = [], 0
    for _ in range(repeat):
        for kf in kfs:
            t0 = time.perf_counter()
            found += len(detect_keyframe_targets(kf.image, camera))
            times.append(time.perf_counter() - t0)
    ms = np.array(times) * 1e3
    return {'bench': 'target_detection', 'set': 'tracker_keyframes', 'image': f'{camera.width}x{camera.height}',
            'keyframes': len(kfs), 'frames': len(frames),
            'detections_per_keyframe': found / repeat / max(len(kfs), 1),
            'detection_ms_median': float(np.median(ms)), 'detection_ms_p90': float(np.percentile(ms, 90)),
            'baseline_tracker_ms_per_frame': track_s / len(frames) * 1e3,
            'baseline_tracker_ms_per_keyframe': track_s / max(len(kfs), 1) * 1e3,
            'overhead_vs_tracker': float(np.median(ms)) * len(kfs) / (track_s * 1e3),
            'load_avg': os.getloadavg()[0]}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument('--bag', default=str(ROOT / 'bags' / 'sample_flight'))
    ap.add_argument('--repeat', type=int, default=3, help='runs per frame; the fastest counts')
    ap.add_argument('--out', default=None, help='the result file (JSON lines; default /tmp/target_detection.jsonl)')
    a = ap.parse_args()
    w = ResultWriter.for_bench(a.out, 'target_detection', ['photogram_ros/core/evaluation.py',
                                                           'photogram_ros/core/control.py'])
    cv2.setNumThreads(1)   # one core, as the tracker node's worker thread
    camera, frames = load_frames(Path(a.bag), 10**6)
    for name, imgs in frame_sets([img for _, img in frames]):
        w.write(compare_set(name, imgs, a.repeat))
    w.write(tracker_overhead(camera, frames, a.repeat))
    return 0


if __name__ == '__main__':
    sys.exit(main())
