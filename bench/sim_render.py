"""Simulator rendering speed: frames per second at 640x480 and 1280x960.

Baseline in the same run: one cv2.remap of the texture at the same size (the texture lookup every
renderer must do), so the ratio shows what ray marching the DEM costs on top.
usage: .venv/bin/python bench/sim_render.py [--frames N]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import machine_info  # noqa: E402

from photogram_ros.core.rotations import make_T  # noqa: E402
from photogram_ros.sim.render import Exposure, Renderer  # noqa: E402
from photogram_ros.sim.scenario import build_world, preset  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--frames', type=int, default=10)
    a = ap.parse_args()
    print(json.dumps({'machine': machine_info()}))
    for w, h in ((640, 480), (1280, 960)):
        cfg = preset('tiny', width_px=w, height_px=h, focal_px=520.0 * w / 640)
        rng = np.random.default_rng(cfg.seed)
        flight, terrain, _ = build_world(cfg, rng)
        r = Renderer(terrain, cfg.camera())
        poses = [make_T(flight.state(t).map_R_cam, flight.state(t).pos_enu)
                 for t in np.linspace(0, flight.duration_s, a.frames)]
        t0 = time.perf_counter()
        for T in poses:
            r.render(T, Exposure(), rng)
        t_render = (time.perf_counter() - t0) / a.frames
        mx = np.random.default_rng(0).uniform(0, terrain.texture.shape[1] - 1, (h, w)).astype(np.float32)
        my = np.random.default_rng(1).uniform(0, terrain.texture.shape[0] - 1, (h, w)).astype(np.float32)
        t0 = time.perf_counter()
        for _ in range(a.frames):
            cv2.remap(terrain.texture.data, mx, my, cv2.INTER_LINEAR)
        t_remap = (time.perf_counter() - t0) / a.frames
        print(json.dumps({'bench': 'sim_render', 'size': f'{w}x{h}', 'frames_per_s': round(1 / t_render, 2),
                          'ms_per_frame': round(t_render * 1e3, 1), 'baseline_remap_ms': round(t_remap * 1e3, 2),
                          'ratio_to_baseline': round(t_render / t_remap, 1)}))


if __name__ == '__main__':
    main()
