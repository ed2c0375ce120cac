"""Milliseconds per keyframe pair: the full stereo module vs a bare StereoSGBM.compute on the same pair.

Usage: .venv/bin/python bench/stereo_speed.py [--repeats N] [--param name=value ...] [--real-1080p]
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

`--real-1080p`: a real 1920x1080 pair of ../shared/data/video/phantom3_village (poses from its
trajectory, 166 m above the ground) matched with the settings derived from its GSD (core/gsd.py:
downscale 0.25, lengths x3.4) against, in the same run, the simulator's settings the shipped
configs held before (downscale 0.5, relief 25 m, 2 m hole fill, 1 m edge step): one JSON line with
both times and the speed-up ratio.

The lines go through bench/machine.py's ResultWriter (commit, clean-tree flag, cores, load) to --out and stdout; a
line's `kind` says which measurement it is (stereo_speed, stereo_speed_real_1080p).
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import ResultWriter  # noqa: E402
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


PHANTOM3 = Path(__file__).resolve().parents[1].parent / 'shared' / 'data' / 'video' / 'phantom3_village'


def real_1080p_pair(gap: int = 2, first: int = 40):
    """Camera, ground height and two (map_T_cam, image) of the phantom3 frames `gap` apart."""
    from photogram_ros.core.rotations import R_from_quat
    from photogram_ros.io.frame_import import frame_files, read_map2dfusion_config
    cam, _ = read_map2dfusion_config(PHANTOM3 / 'config.cfg')
    rows = np.loadtxt(PHANTOM3 / 'trajectory.txt')
    frames = frame_files(PHANTOM3 / 'rgb')
    out = []
    for i in (first, first + gap):
        t, x, y, z, qx, qy, qz, qw = rows[i]
        T = make_T(R_from_quat([qx, qy, qz, qw]), np.array([x, y, z]))
        out.append((T, cv2.imread(str(frames[i][1]), cv2.IMREAD_COLOR)))
    return cam, out


def bench_real(repeats: int) -> dict:
    from photogram_ros.core import gsd
    cam, ((Ta, ia), (Tb, ib)) = real_1080p_pair()
    ground_m = 0.0
    height = float(Ta[2, 3] - ground_m)
    settings = gsd.derive(cam.width, cam.height, cam.fx, height)
    auto = stereo.StereoParams(**{k: gsd.AUTO for k in ('downscale', 'fill_holes_m', 'edge_step_m')},
                               min_texture=2.0)
    new, _ = gsd.resolve(auto, settings)
    old = stereo.StereoParams(downscale=0.5, fill_holes_m=2.0, edge_step_m=1.0, min_texture=2.0)
    ranges = {'new': (height - settings.relief_m, height + settings.relief_m), 'old': (height - 25.0, height + 25.0)}
    runs = {'new': [], 'old': []}
    cpu = {'new': [], 'old': []}
    last = {}
    for _ in range(repeats):
        for name, p in (('old', old), ('new', new)):
            c0, t0 = time.process_time(), time.perf_counter()
            last[name] = stereo.stereo_pair(cam, ia, Ta, ib, Tb, p, ranges[name])
            runs[name].append((time.perf_counter() - t0) * 1e3)
            cpu[name].append((time.process_time() - c0) * 1e3)
    med = {k: float(np.median(v)) for k, v in runs.items()}
    med_cpu = {k: float(np.median(v)) for k, v in cpu.items()}
    return {'bench': 'stereo_speed_real_1080p', 'image': f'{cam.width}x{cam.height}', 'height_m': round(height, 1),
            'gsd_cm': round(settings.gsd_m * 100, 2),
            'new': {'downscale': new.downscale, 'relief_m': settings.relief_m, 'fill_holes_m': new.fill_holes_m,
                    'edge_step_m': new.edge_step_m, 'ms': round(med['new'], 1), 'cpu_ms': round(med_cpu['new'], 1),
                    'rectified': f'{last["new"].rect.width}x{last["new"].rect.height}' if last['new'].rect else None,
                    'num_disparities': last['new'].num_disparities, 'points': int(last['new'].cloud.size),
                    'status': last['new'].status},
            'baseline_old_settings': {'downscale': 0.5, 'relief_m': 25.0, 'fill_holes_m': 2.0, 'edge_step_m': 1.0,
                                      'ms': round(med['old'], 1), 'cpu_ms': round(med_cpu['old'], 1),
                                      'rectified': (f'{last["old"].rect.width}x{last["old"].rect.height}'
                                                    if last['old'].rect else None),
                                      'num_disparities': last['old'].num_disparities,
                                      'points': int(last['old'].cloud.size), 'status': last['old'].status},
            'speedup_ratio': round(med['old'] / med['new'], 2),
            'speedup_ratio_cpu': round(med_cpu['old'] / med_cpu['new'], 2), 'repeats': repeats,
            'stages_ms_new': {k: round(v, 1) for k, v in last['new'].timings_ms.items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--repeats', type=int, default=7)
    ap.add_argument('--scales', default='1,2', help='image sizes as multiples of 640x480')
    ap.add_argument('--param', action='append', default=[], help='StereoParams override name=value')
    ap.add_argument('--real-1080p', action='store_true', help='only the real 1080p pair: derived vs old settings')
    ap.add_argument('--out', default=None, help='the result file (JSON lines; default /tmp/stereo_speed.jsonl)')
    a = ap.parse_args(argv)
    w = ResultWriter.for_bench(a.out, 'stereo_speed', ['photogram_ros/core/stereo.py', 'photogram_ros/core/gsd.py'])

    def emit(row: dict) -> None:
        w.write({'kind': row.pop('bench'), **row})
    if a.real_1080p:
        emit(bench_real(a.repeats))
        return 0
    # The module's former defaults (full resolution, no hole filling), so the overhead ratio stays comparable;
    # the parameters now default to lengths from the GSD (core/gsd.py; --real-1080p measures those).
    params = from_assignments(stereo.StereoParams, ['downscale=1.0', 'fill_holes_m=0.0', 'edge_step_m=1.0', *a.param])
    for s in (int(x) for x in a.scales.split(',')):
        emit(bench(s, params, a.repeats))
    return 0


if __name__ == '__main__':
    sys.exit(main())
