"""Photo-survey triangulation speed: photos/s for matching (features + pairs) and for the whole
`triangulate`, against the bare-OpenCV pipeline this project had before (the baseline, same run).

Data: the real DJI survey ../shared/data/photos/brighton_beach (18 photos, 4000x2250) and a simulated
survey of about 100 photos (640x480, made here with `simulate --photos`, about a minute; its camera is
the photos' EXIF one with the final self-calibration, as for a user's photos). The baseline
is full-frame matching: SIFT with 3000 features on the full photo, brute-force
2-NN with Lowe's ratio 0.8, an essential matrix by RANSAC (2 px) on each photo's 8 nearest neighbours;
it reports its verified pairs beside its time (on brighton it verified 5, the reason for the change).
The peer figures of the issue (pycolmap exhaustive on a 42-photo 2400x1800 set: 590 s; this project
with a hand-made calibration: 143 s) are for a set not stored here and are not re-measured.

    .venv/bin/python bench/photo_triangulation.py [--photos DIR ...] [--sim-photos 100] [--no-baseline]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import ResultWriter, machine_info  # noqa: E402
from photogram_ros.core.geodesy import LocalFrame  # noqa: E402
from photogram_ros.core.two_view import essential_ransac  # noqa: E402
from photogram_ros.io.aerial_triangulation import TriangulateOptions  # noqa: E402
from photogram_ros.io.triangulate_action import triangulate  # noqa: E402
from photogram_ros.io.image_source import IMAGE_SUFFIXES, exif_intrinsics, image_file_problem  # noqa: E402
from photogram_ros.io.photo_block import exif_position, read_photo_block  # noqa: E402

BRIGHTON = ROOT.parent / 'shared' / 'data' / 'photos' / 'brighton_beach' / 'images'


def baseline_matching(folder: Path) -> dict:
    """The pre-issue-13 pipeline with OpenCV alone: full-photo SIFT (3000), BF ratio test, essential RANSAC."""
    images = sorted(p for p in folder.iterdir()
                    if p.suffix.lower() in IMAGE_SUFFIXES and image_file_problem(p) is None)
    cam = exif_intrinsics(images[0]).camera
    t0 = time.perf_counter()
    sift = cv2.SIFT_create(nfeatures=3000)
    feats = []
    for p in images:
        k, d = sift.detectAndCompute(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), None)
        feats.append((np.array([x.pt for x in k]).reshape(-1, 2), d))
    t_feat = time.perf_counter() - t0
    geo = [exif_position(p) for p in images]
    origin = LocalFrame(*geo[0][:3])
    pos = np.array([origin.geodetic_to_enu(*g[:3])[:2] for g in geo])
    d = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    pairs = {(min(i, int(j)), max(i, int(j))) for i in range(len(images)) for j in np.argsort(d[i])[1:9]}
    bf = cv2.BFMatcher(cv2.NORM_L2)
    verified = 0
    for i, j in sorted(pairs):
        m = bf.knnMatch(feats[i][1], feats[j][1], k=2)
        pr = np.array([(a.queryIdx, a.trainIdx) for a, *b in m
                       if b and a.distance < 0.8 * b[0].distance]).reshape(-1, 2)
        if len(pr) < 20:
            continue
        E, inl = essential_ransac(cam.pixel_to_normalized(feats[i][0][pr[:, 0]]),
                                  cam.pixel_to_normalized(feats[j][0][pr[:, 1]]), 2.0 / cam.fx)
        verified += int(E is not None and inl.sum() >= 20)
    total = time.perf_counter() - t0
    return {'photos': len(images), 'features_s': round(t_feat, 2), 'matching_s': round(total, 2),
            'pairs': len(pairs), 'verified_pairs': verified, 'photos_per_s': round(len(images) / total, 3)}


def ours(folder: Path) -> dict:
    t0 = time.perf_counter()
    block = read_photo_block(folder)
    t_match = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as out:
        t1 = time.perf_counter()
        res = triangulate(folder, out, TriangulateOptions())
        t_all = time.perf_counter() - t1
    n = block.stats['photos']
    return {'photos': n, 'matching_s': round(t_match, 2), 'matching_photos_per_s': round(n / t_match, 3),
            'triangulate_s': round(t_all, 2), 'triangulate_photos_per_s': round(n / t_all, 3),
            'verified_pairs': block.stats['pairs_verified'], 'pairs': block.stats['pairs_tried'],
            'oriented': res.registered, 'reprojection_rms_px': round(res.report['reprojection_rms_px'], 3)}


def simulated_photos(n: int, where: Path) -> Path:
    from photogram_ros.sim.scenario import preset, simulate
    lines = max(2, int(round(n / 20)))
    simulate(preset('survey', photos=True, fps=2.0, n_lines=lines, line_length_m=140.0), where / 'flight')
    return where / 'flight' / 'photos'


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--photos', nargs='*', default=None, help='photo folders (default: brighton_beach)')
    ap.add_argument('--sim-photos', type=int, default=100,
                    help='a simulated survey of about this many photos (0: none)')
    ap.add_argument('--no-baseline', action='store_true')
    ap.add_argument('--out', default=None, help='the result file (JSON lines through bench/machine.py\'s ResultWriter; '
                                                'default /tmp/photo_triangulation.jsonl)')
    a = ap.parse_args()
    w = ResultWriter.for_bench(a.out, 'photo_triangulation', ['photogram_ros', 'config'])
    folders = [Path(p) for p in a.photos] if a.photos is not None else ([BRIGHTON] if BRIGHTON.is_dir() else [])
    with tempfile.TemporaryDirectory() as tmp:
        if a.sim_photos:
            folders.append(simulated_photos(a.sim_photos, Path(tmp)))
        for folder in folders:
            row = {'bench': 'photo_triangulation', 'data': str(folder), 'ours': ours(folder)}
            if not a.no_baseline:
                row['baseline'] = baseline_matching(folder)
                row['matching_speed_ratio'] = round(row['ours']['matching_photos_per_s']
                                                    / row['baseline']['photos_per_s'], 2)
            row['machine'] = machine_info()
            w.write(row)
    return 0


if __name__ == '__main__':
    sys.exit(main())
