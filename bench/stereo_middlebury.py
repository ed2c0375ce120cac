"""Stereo module vs plain OpenCV SGBM on Middlebury-layout scenes: one JSON line per scene and method.

Usage: .venv/bin/python bench/stereo_middlebury.py SCENE_DIR [SCENE_DIR ...] [--param name=value ...]
           [--out bench/results/stereo_middlebury_COMMIT.jsonl]
Both methods use the same SGBM core parameters (mode, block size, P1/P2, disparity range); "plain" has
no uniqueness, speckle or left-right filtering, "ours" is photogram_ros.core.stereo.match with the given
parameters, "ours_lr_on"/"ours_lr_off" the same with the left-right check (lr_check) forced on/off.
Errors are measured on the pixels each method keeps within the nonocc mask (bad-1, bad-2), and
density is the fraction of mask pixels that get a disparity.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import ResultWriter  # noqa: E402
from photogram_ros.core import stereo  # noqa: E402
from photogram_ros.core.stereo_eval import load_scene, score  # noqa: E402
from photogram_ros.params import from_assignments  # noqa: E402


def evaluate(scene_dir, params: stereo.StereoParams, repeats: int = 3) -> list[dict]:
    sc = load_scene(scene_dir)
    left, right = (cv2.cvtColor(i, cv2.COLOR_BGR2GRAY) for i in (sc.left, sc.right))
    num = 16 * ((sc.ndisp + 15) // 16)
    mask = sc.masks.get('nonocc', sc.masks['gt'])
    rows = []
    plain = stereo.make_sgbm(params, 0, num, filtered=False)
    ours = stereo.make_sgbm(params, 0, num)
    variants = {'ours': params, 'ours_lr_on': replace(params, lr_check=True, lr_scale=1.0),
                'ours_lr_half': replace(params, lr_check=True, lr_scale=0.5),
                'ours_lr_off': replace(params, lr_check=False)}
    for method in ('plain_sgbm', 'ours', 'ours_lr_on', 'ours_lr_half', 'ours_lr_off'):
        best = float('inf')
        for _ in range(repeats):
            t0 = time.perf_counter()
            if method == 'plain_sgbm':
                d = stereo.disparity_from_sgbm(plain.compute(left, right), 0)
            else:
                d = stereo.match(left, right, variants[method], 0, num, matcher=ours).disparity_px
            best = min(best, (time.perf_counter() - t0) * 1e3)
        s = score(d, sc.gt_px, mask)
        rows.append({'scene': sc.name, 'method': method, 'mask': 'nonocc' if 'nonocc' in sc.masks else 'gt',
                     'bad1': round(s['bad1'], 4), 'bad2': round(s['bad2'], 4), 'density': round(s['density'], 4),
                     'ms': round(best, 2), 'size': f'{left.shape[1]}x{left.shape[0]}', 'ndisp': num})
    p = rows[0]
    for o in rows[1:]:
        o['bad2_ratio_vs_plain'] = round(o['bad2'] / p['bad2'], 3) if p['bad2'] else None
        o['ms_ratio_vs_plain'] = round(o['ms'] / p['ms'], 3)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('scenes', nargs='+', help='scene folders (imL.png, imR.png, groundtruth.png, info.txt)')
    ap.add_argument('--param', action='append', default=[], help='StereoParams override name=value')
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--out', default='/tmp/stereo_middlebury.jsonl', help='result file (JSON lines)')
    a = ap.parse_args(argv)
    params = from_assignments(stereo.StereoParams, a.param)
    writer = ResultWriter(a.out, 'stereo_middlebury', ['photogram_ros/core/stereo.py', 'photogram_ros/core/stereo_eval.py'])
    for scene in a.scenes:
        for row in evaluate(scene, params, a.repeats):
            print(json.dumps(writer.write({**row, 'params': a.param})), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
