"""Cost of the tracker node's ArUco target detection per keyframe, against the tracker's own time.

The sample flight's frames go through the core tracker (timed: the baseline, per frame and per
keyframe); then `detect_keyframe_targets` runs on every keyframe it emitted (timed), as the tracker
node does with `detect_targets` on. Prints one JSON line.

    .venv/bin/python bench/target_detection.py [--bag bags/sample_flight] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'bench'))

from tracker_fps import load_frames  # noqa: E402

from photogram_ros.core.control import detect_keyframe_targets  # noqa: E402
from photogram_ros.core.tracker import Tracker  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument('--bag', default=str(ROOT / 'bags' / 'sample_flight'))
    ap.add_argument('--repeat', type=int, default=3)
    a = ap.parse_args()
    cv2.setNumThreads(1)   # one core, as the tracker node's worker thread
    camera, frames = load_frames(Path(a.bag), 10**6)
    tr = Tracker(camera)
    t0 = time.perf_counter()
    kfs = []
    for stamp, img in frames:
        kfs += tr.process(img, stamp)
    kfs += tr.flush()
    track_s = time.perf_counter() - t0
    times, found = [], 0
    for _ in range(a.repeat):
        for kf in kfs:
            t0 = time.perf_counter()
            found += len(detect_keyframe_targets(kf.image, camera))
            times.append(time.perf_counter() - t0)
    ms = np.array(times) * 1e3
    print(json.dumps({
        'bench': 'target_detection', 'image': f'{camera.width}x{camera.height}', 'keyframes': len(kfs),
        'frames': len(frames), 'detections_per_keyframe': found / a.repeat / max(len(kfs), 1),
        'detection_ms_median': float(np.median(ms)), 'detection_ms_p90': float(np.percentile(ms, 90)),
        'baseline_tracker_ms_per_frame': track_s / len(frames) * 1e3,
        'baseline_tracker_ms_per_keyframe': track_s / max(len(kfs), 1) * 1e3,
        'overhead_vs_tracker': float(np.median(ms)) * len(kfs) / (track_s * 1e3),
        'load_avg': os.getloadavg()[0]}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
