"""Scoring disparity maps against ground truth in the Middlebury layout (imL, imR, groundtruth, masks)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from photogram_ros.errors import DataError


@dataclass
class Scene:
    name: str
    left: np.ndarray          # BGR uint8
    right: np.ndarray
    gt_px: np.ndarray         # float32 disparity, NaN where unknown
    ndisp: int
    masks: dict               # name -> bool (H, W), evaluated pixels


def load_scene(folder: str | Path) -> Scene:
    """imL.png, imR.png, groundtruth.png (disparity = value / scale, 0 = unknown), info.txt 'scale ndisp'."""
    folder = Path(folder)
    need = [folder / n for n in ('imL.png', 'imR.png', 'groundtruth.png', 'info.txt')]
    missing = [p.name for p in need if not p.exists()]
    if missing:
        raise DataError(f'{folder} is not a stereo scene folder: missing {missing}')
    try:
        scale, ndisp = [float(v) for v in need[3].read_text().split()[:2]]
    except ValueError as exc:
        raise DataError(f'{need[3]} must hold two numbers, "scale ndisp"') from exc
    left, right = cv2.imread(str(need[0])), cv2.imread(str(need[1]))
    gt_raw = cv2.imread(str(need[2]), cv2.IMREAD_UNCHANGED)
    if left is None or right is None or gt_raw is None:
        raise DataError(f'cannot read the images of {folder}')
    if gt_raw.ndim == 3:
        gt_raw = gt_raw[..., 0]
    gt = gt_raw.astype(np.float32) / np.float32(scale)
    gt[gt_raw == 0] = np.nan
    masks = {'gt': np.isfinite(gt)}
    for name in ('nonocc', 'all', 'disc'):
        p = folder / f'{name}.png'
        if p.exists():
            m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            masks[name] = (m == 255) & np.isfinite(gt)
    return Scene(folder.name, left, right, gt, int(round(ndisp)), masks)


def score(disparity_px: np.ndarray, gt_px: np.ndarray, mask: np.ndarray) -> dict:
    """bad-1, bad-2 (fraction of kept pixels in `mask` off by more than 1 / 2 px) and density (kept / mask)."""
    kept = mask & np.isfinite(disparity_px)
    n_mask, n_kept = int(mask.sum()), int(kept.sum())
    err = np.abs(disparity_px[kept] - gt_px[kept])
    return {'bad1': float(np.mean(err > 1.0)) if n_kept else float('nan'),
            'bad2': float(np.mean(err > 2.0)) if n_kept else float('nan'),
            'density': n_kept / n_mask if n_mask else 0.0}
