"""Milliseconds per keyframe pair: the full stereo module vs a bare StereoSGBM.compute on the same pair.

Usage: .venv/bin/python bench/stereo_speed.py [--repeats N] [--param name=value ...]
Renders a survey pair (B/H 0.22, 40 m) with the simulator at 640x480 and 1280x960. "full" is
photogram_ros.core.stereo.stereo_pair (pair checks, rectification maps, remap, SGBM, filtering,
points in map with colour); "bare" is StereoSGBM.compute alone on the module's rectified grey pair
with the same parameters and disparity range ("bare_unfiltered" also without uniqueness/speckle/LR).
SGBM computes nothing for the first min + num disparities columns; the module pads the pair so that
every column is matched (on these pairs that is most of the image), so the baseline of the headline
ratio, "bare_padded", is the same compute on the pair padded alike: the same area matched. The ratio
against the unpadded compute (less area matched) is printed too.
Prints one JSON line per size with medians and the overhead ratio (target <= 1.5), also with the
left-right check (lr_check) on and off against the same bare baseline, in wall time and in
process CPU time (the latter varies less with other processes' load), and says what each side includes.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from photogram_ros.core import stereo  # noqa: E402
from photogram_ros.core.rotations import make_T  # noqa: E402
from photogram_ros.params import from_assignments  # noqa: E402
from photogram_ros.sim.render import Exposure, Renderer  # noqa: E402
from photogram_ros.sim.scenario import build_world, preset  # noqa: E402


def render_pair(scale: int):
    cfg = preset('tiny', width_px=640 * scale, height_px=480 * scale, focal_px=520.0 * scale)
    rng = np.random.default_rng(cfg.seed)
    flight, terrain, _ = build_world(cfg, rng)
    cam = cfg.camera()
    r = Renderer(terrain, cam)
    out = []
    for t in (2.0, 3.75):
        st = flight.state(t)
        T = make_T(st.map_R_cam, st.pos_enu)
        out.append((T, r.render(T, Exposure(), rng)))
    return cam, out


def _median_ms(fn, repeats):
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(ts))


def bench(scale: int, params: stereo.StereoParams, repeats: int) -> dict:
    cam, ((Ta, ia), (Tb, ib)) = render_pair(scale)
    depth = (20.0, 55.0)
    res = stereo.stereo_pair(cam, ia, Ta, ib, Tb, params, depth)
    # The module's own rectified grey pair (left remapped in colour, then grey; right grey, then remapped).
    left = cv2.cvtColor(cv2.remap(ia, *res.rect.maps_left, cv2.INTER_LINEAR), cv2.COLOR_BGR2GRAY)
    right = cv2.remap(cv2.cvtColor(ib, cv2.COLOR_BGR2GRAY), *res.rect.maps_right, cv2.INTER_LINEAR)
    sgbm = stereo.make_sgbm(params, res.min_disparity, res.num_disparities)
    pad = res.min_disparity + res.num_disparities
    left_p, right_p = (cv2.copyMakeBorder(im, 0, 0, pad, 0, cv2.BORDER_REPLICATE) for im in (left, right))
    plain = stereo.make_sgbm(params, res.min_disparity, res.num_disparities, filtered=False)
    # The same pipeline with the left-right check switched the other way (lr_check doubles SGBM work).
    other = replace(params, lr_check=not params.lr_check)
    # Interleave the four so that load from other processes hits them alike.
    full_ms, bare_ms, plain_ms, other_ms, parts, padded_ms = [], [], [], [], [], []
    cpu = {'full': [], 'bare': [], 'other': [], 'padded': []}
    for _ in range(repeats):
        c0 = time.process_time()
        full_ms.append(_median_ms(lambda: parts.append(stereo.stereo_pair(cam, ia, Ta, ib, Tb, params, depth)
                                                       .timings_ms), 1))
        c1 = time.process_time()
        bare_ms.append(_median_ms(lambda: sgbm.compute(left, right), 1))
        cpu['full'].append(c1 - c0)
        cpu['bare'].append(time.process_time() - c1)
        plain_ms.append(_median_ms(lambda: plain.compute(left, right), 1))
        c2 = time.process_time()
        other_ms.append(_median_ms(lambda: stereo.stereo_pair(cam, ia, Ta, ib, Tb, other, depth), 1))
        cpu['other'].append(time.process_time() - c2)
        c3 = time.process_time()
        padded_ms.append(_median_ms(lambda: sgbm.compute(left_p, right_p), 1))
        cpu['padded'].append(time.process_time() - c3)
    full, bare_unpadded, bare_u, full_o, bare = (float(np.median(v)) for v in (full_ms, bare_ms, plain_ms,
                                                                                other_ms, padded_ms))
    full_cpu, bare_unpadded_cpu, other_cpu, bare_cpu = (float(np.median(cpu[k])) * 1e3
                                                        for k in ('full', 'bare', 'other', 'padded'))
    on = 'on' if params.lr_check else 'off'
    off = 'off' if params.lr_check else 'on'
    stages = {k: round(float(np.median([p[k] for p in parts])), 2) for k in parts[0]}
    stages_sgbm = stages['sgbm_ms']
    return {'bench': 'stereo_speed', 'image': f'{cam.width}x{cam.height}',
            'rectified': f'{res.rect.width}x{res.rect.height}', 'num_disparities': res.num_disparities,
            'mode': params.mode, 'downscale': params.downscale, 'points': int(res.cloud.size),
            'full_ms': round(full, 2), 'bare_padded_sgbm_ms': round(bare, 2),
            'bare_sgbm_ms': round(bare_unpadded, 2), 'bare_unfiltered_sgbm_ms': round(bare_u, 2),
            'overhead_ratio': round(full / bare, 3), 'ratio_vs_unpadded': round(full / bare_unpadded, 3),
            'ratio_vs_unpadded_cpu': round(full_cpu / bare_unpadded_cpu, 3),
            'ratio_vs_unfiltered': round(full / bare_u, 3),
            # Same ratio with the module's own SGBM stage replaced by the bare timing: on a loaded
            # machine the wall ratio also carries the noise between two runs of the same SGBM.
            'overhead_ratio_stages': round((full - stages_sgbm + bare) / bare, 3),
            # CPU seconds of the whole process (all threads): the work done, less sensitive than wall
            # time to other processes' load on a shared machine (waiting for a core is not counted).
            'full_cpu_ms': round(full_cpu, 2), 'bare_padded_sgbm_cpu_ms': round(bare_cpu, 2),
            'overhead_ratio_cpu': round(full_cpu / bare_cpu, 3),
            'lr_check': params.lr_check,
            # The same ratios with the left-right check on and off (same bare baseline).
            f'overhead_ratio_lr_{on}': round(full / bare, 3), f'overhead_ratio_lr_{off}': round(full_o / bare, 3),
            f'overhead_ratio_cpu_lr_{on}': round(full_cpu / bare_cpu, 3),
            f'overhead_ratio_cpu_lr_{off}': round(other_cpu / bare_cpu, 3),
            f'full_ms_lr_{off}': round(full_o, 2),
            'target_ratio': 1.5, 'stages_ms': stages, 'threads': cv2.getNumThreads(),
            'baseline': BASELINE, 'full_includes': FULL}


BASELINE = ('bare_padded_sgbm_ms: one StereoSGBM.compute (same mode, P1/P2, block, disparity range, and SGBM\'s '
            'built-in uniqueness and speckle filters; its own left-right check is off, see make_sgbm) on the '
            'already-rectified grey pair padded on the left by min+num disparities as the module does (so the same '
            'columns are matched), matcher created once; no rectification, remap, filters or points. bare_sgbm_ms: '
            'the same on the unpadded pair (SGBM leaves its first min+num columns unmatched)')
FULL = ('full_ms: stereo_pair end to end: pair checks, rectification maps, remap of both images, '
        'SGBM (new matcher per pair; a second SGBM on the mirrored pair over the disparities the first found when '
        'lr_check is on), local-consistency/texture/edge filters, hole filling when fill_holes_m > 0, sub-pixel '
        'disparity, grazing/depth filters, points in map with colour and confidence')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--repeats', type=int, default=7)
    ap.add_argument('--scales', default='1,2', help='image sizes as multiples of 640x480')
    ap.add_argument('--param', action='append', default=[], help='StereoParams override name=value')
    a = ap.parse_args(argv)
    params = from_assignments(stereo.StereoParams, a.param)
    for s in (int(x) for x in a.scales.split(',')):
        print(json.dumps(bench(s, params, a.repeats)), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
