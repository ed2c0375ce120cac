"""Simulator worlds and rendered frames shared by the test modules of one session.

Building a world (terrain texture) costs seconds, so each distinct world is built once. The random
generator is returned as it stood after the build, so rendering from it gives the same noise every time.
"""

from __future__ import annotations

import copy
from functools import lru_cache

import numpy as np

from photogram_ros.core.rotations import make_T


@lru_cache(maxsize=4)
def world(preset_name: str = 'tiny'):
    """(cfg, flight, terrain, targets, rng after the build) of a preset world."""
    from photogram_ros.sim.scenario import build_world, preset
    cfg = preset(preset_name)
    rng = np.random.default_rng(cfg.seed)
    flight, terrain, targets = build_world(cfg, rng)
    return cfg, flight, terrain, targets, rng


@lru_cache(maxsize=8)
def rendered(times: tuple, preset_name: str = 'tiny') -> list:
    """[(t, map_T_cam, BGR image)] at flight times `times`, rendered with the world's noise stream."""
    from photogram_ros.sim.render import Exposure, Renderer
    cfg, flight, terrain, _, rng = world(preset_name)
    rng = copy.deepcopy(rng)
    r = Renderer(terrain, cfg.camera())
    out = []
    for t in times:
        st = flight.state(t)
        T = make_T(st.map_R_cam, st.pos_enu)
        out.append((t, T, r.render(T, Exposure(), rng)))
    return out
