"""A simulated photo survey cut in two halves, for manual tie points (tests/test_manual_tie_points.py).

The photos are matched as usual; then every track of the eastern half gets ids of its own, so no
automatic tie point joins the halves (as over a band of water). Manual tie points are ground points
in the band between the halves, projected into the photos from the true cameras (the DEM gives their
heights), with 0.5 px of noise, as an operator would mark them.
"""

from __future__ import annotations

import numpy as np

from photogram_ros.core.rotations import invert_T, transform_points

CUT_ID_OFFSET = 50_000_000


def photo_truth(truth, names):
    """{photo name: FrameTruth} (the simulator names photos IMG_<frame index>)."""
    return {n: truth.frames[int(n[4:8])] for n in names}


def band_x_m(truth, names) -> float:
    """East coordinate (truth map frame, m) between the western and eastern halves of the cameras."""
    x = np.array([ft.map_T_cam[0, 3] for ft in photo_truth(truth, names).values()])
    return float((x.min() + x.max()) / 2)


def cut_block(block, truth):
    """Give the eastern half's tracks ids of their own (in place); returns (western, eastern) photo names."""
    pt = photo_truth(truth, [r.name for r in block.records])
    xm = band_x_m(truth, list(pt))
    west = [n for n, ft in pt.items() if ft.map_T_cam[0, 3] < xm]
    east = [n for n in pt if n not in west]
    for rec in block.records:
        if rec.name in east:
            rec.track_ids = np.asarray(rec.track_ids, np.int64) + CUT_ID_OFFSET
    return west, east


def mtp_rows(truth, names, n: int = 4, noise_px: float = 0.5, seed: int = 3) -> list[str]:
    """`px py image name` rows of n manual tie points in the band between the halves, each marked in
    every photo that sees it (20 px from the border)."""
    rng = np.random.default_rng(seed)
    pt = photo_truth(truth, names)
    xm = band_x_m(truth, names)
    y = np.array([ft.map_T_cam[1, 3] for ft in pt.values()])
    ys = np.linspace(y.min() + 5.0, y.max() - 5.0, n)
    rows = []
    for k, yk in enumerate(ys):
        xk = xm + (3.0 if k % 2 else -3.0)
        X = np.array([xk, yk, float(truth.dem.sample(xk, yk))])
        for name, ft in pt.items():
            cam = truth.camera
            pc = transform_points(invert_T(ft.map_T_cam), X[None])
            uv, ok = cam.project(pc)
            # In the image before distortion too: the lens model folds points far outside back in.
            flat = np.array([[cam.fx * pc[0, 0] / pc[0, 2] + cam.cx, cam.fy * pc[0, 1] / pc[0, 2] + cam.cy]])
            if ok[0] and cam.in_image(uv, margin_px=20)[0] and cam.in_image(flat, margin_px=20)[0]:
                u, v = uv[0] + rng.normal(0.0, noise_px, 2)
                rows.append(f'{u:.2f} {v:.2f} {name} MTP{k + 1:02d}')
    return rows


def control_rows(photos_dir, truth, names: list[str], band_m: float = 5.0):
    """(CRS line, gcp_list rows): the GCPs of the western half only (the eastern half has none) and every
    check point; names: every photo."""
    lines = (photos_dir / 'gcp_list.txt').read_text().splitlines()
    xm = band_x_m(truth, names)
    tx = {t.name: float(t.center_enu[0]) for t in truth.targets}
    keep = [r for r in lines[1:] if r.split()[6].startswith('CHK') or tx[r.split()[6]] < xm - band_m]
    return lines[0], keep


def check_sides(truth, names) -> dict:
    """{check point name: 'west' | 'band' | 'east'}."""
    xm = band_x_m(truth, names)
    return {t.name: ('band' if abs(t.center_enu[0] - xm) < 5.0 else 'west' if t.center_enu[0] < xm else 'east')
            for t in truth.targets if t.name.startswith('CHK')}
