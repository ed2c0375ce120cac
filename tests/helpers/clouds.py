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


ORIGIN_LLH = (47.3977, 8.5456, 488.0)   # the simulator's take-off point


def fused_map(folder, cell_m: float, clouds, origin_llh=ORIGIN_LLH, tile_cells: int = 256):
    """A map folder at `folder` with its origin, every pair cloud of `clouds` fused and flushed; its MapStore."""
    from photogram_ros.core.fusion import Fusion, FusionConfig
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.io.map_store import MapStore
    store = MapStore(folder, cell_m, tile_cells)
    store.set_origin(LocalFrame(*origin_llh))
    fusion = Fusion(FusionConfig(cell_m, tile_cells), store)
    for cloud in clouds:
        fusion.add(cloud)
    fusion.flush()
    return store
