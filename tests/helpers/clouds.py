"""Synthetic pair clouds for the map tests: points on a known surface with set noise and outliers."""

from __future__ import annotations

import numpy as np

from photogram_ros.core.stereo import CLOUD_DTYPE


def pair_cloud(rng, height_at, cx, cy, half_w, half_h, density_per_m2, sigma_z_m=0.0, outlier_fraction=0.0,
               rgb=0x406080) -> np.ndarray:
    """Points uniformly over a footprint box, z = surface + N(0, sigma) with gross outliers."""
    n = int(4 * half_w * half_h * density_per_m2)
    p = np.zeros(n, dtype=CLOUD_DTYPE)
    p['x'] = cx + rng.uniform(-half_w, half_w, n)
    p['y'] = cy + rng.uniform(-half_h, half_h, n)
    p['z'] = height_at(p['x'], p['y']) + rng.normal(0.0, sigma_z_m, n)
    bad = rng.random(n) < outlier_fraction
    p['z'][bad] += rng.choice([-1, 1], bad.sum()) * rng.uniform(2.0, 8.0, bad.sum())
    p['rgb'] = rgb
    p['confidence'] = 0.9
    return p
