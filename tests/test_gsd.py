"""GSD-derived settings (core/gsd.py): the simulator's values at its GSD, scaled elsewhere, AUTO resolved."""

from __future__ import annotations

import numpy as np
import pytest

from photogram_ros.core import gsd
from photogram_ros.errors import ConfigError

# What the shipped configs held for the simulator's 640x480, f = 520 px camera at 40 m.
SIMULATOR = {'downscale': 0.5, 'cell_m': 0.12, 'fill_holes_m': 2.0, 'edge_step_m': 1.0, 'depth_margin_m': 4.0,
             'min_tolerance_m': 0.3, 'relief_m': 25.0, 'dsm_max_spread_m': 0.5, 'dsm_fill_gaps_m': 3.0}


@pytest.mark.parametrize('height_m', [34.0, 36.0, 40.0, 44.0, 47.0])
def test_the_simulator_camera_gets_the_values_it_was_tuned_with(height_m):
    # The sample's keyframes fly 36-44 m above the median tie point: all of them give the same settings.
    s = gsd.derive(640, 480, 520.0, height_m)
    assert s.gsd_m == pytest.approx(height_m / 520.0)
    for name, want in SIMULATOR.items():
        assert getattr(s, name) == want, name


def test_a_1080p_camera_at_166_m_gets_lengths_scaled_with_its_cloud_spacing():
    s = gsd.derive(1920, 1080, 1220.0, 166.0)
    # About the simulator's pixel count matched: 480 x 270 px.
    assert s.downscale == 0.25
    assert s.spacing_m == pytest.approx(166.0 / 1220.0 / 0.25)
    ratio = s.spacing_m / (40.0 / 520.0 / 0.5)             # 3.54 by the independent formula
    assert ratio == pytest.approx(3.54, abs=0.01)
    assert s.scale == pytest.approx(4.0)                   # snapped to a power of sqrt(2)
    assert abs(np.log2(s.scale / ratio)) <= 0.25
    assert s.cell_m == pytest.approx(0.48) and s.dsm_max_spread_m == pytest.approx(2.0)
    assert s.dsm_fill_gaps_m == pytest.approx(12.0) and s.edge_step_m == pytest.approx(4.0)
    assert s.relief_m == pytest.approx(100.0)              # 25 m of 40 m, at 166 m (snapped to x4)
    assert 'GSD 13.6 cm' in s.summary()


def test_lengths_follow_the_height_and_a_given_downscale():
    base = gsd.derive(640, 480, 520.0, 40.0)
    twice = gsd.derive(640, 480, 520.0, 80.0)
    assert twice.cell_m == pytest.approx(2 * base.cell_m) and twice.relief_m == pytest.approx(2 * base.relief_m)
    # Matched at full resolution the cloud is twice as dense: half the lengths (the relief stays).
    full = gsd.derive(640, 480, 520.0, 40.0, downscale=1.0)
    assert full.downscale == 1.0 and full.cell_m == pytest.approx(base.cell_m / 2)
    assert full.relief_m == base.relief_m


@pytest.mark.parametrize('size, want', [((640, 480), 0.5), ((1280, 960), 0.25), ((1920, 1080), 0.25),
                                        ((4000, 3000), 0.125), ((320, 240), 1.0)])
def test_matching_downscale_keeps_about_the_reference_pixels(size, want):
    ds = gsd.matching_downscale(*size)
    assert ds == want
    assert size[0] * size[1] * ds * ds >= min(gsd.MATCH_PIXELS, size[0] * size[1]) or ds == 0.125


def test_resolve_fills_only_what_is_left_at_auto():
    from photogram_ros.core.pairs import PairCriteria
    from photogram_ros.core.stereo import StereoParams
    s = gsd.derive(1920, 1080, 1220.0, 166.0)
    p = StereoParams(downscale=gsd.AUTO, fill_holes_m=0.0, edge_step_m=gsd.AUTO)
    r, names = gsd.resolve(p, s)
    assert names == ['downscale', 'edge_step_m']
    assert r.downscale == 0.25 and r.edge_step_m == s.edge_step_m and r.fill_holes_m == 0.0   # the user's "off"
    assert p.downscale == gsd.AUTO                                                           # a copy
    c, names = gsd.resolve(PairCriteria(depth_margin_m=6.0), s)
    assert names == ['relief_m'] and c.relief_m == 100.0 and c.depth_margin_m == 6.0


def test_auto_is_the_only_value_below_a_lengths_range():
    from photogram_ros.core.fusion import Fusion, FusionConfig
    from photogram_ros.core.stereo import StereoParams
    from photogram_ros.params import from_dict
    assert from_dict(StereoParams, {'downscale': -1.0}).downscale == gsd.AUTO
    for bad in ({'downscale': 0.05}, {'downscale': -0.5}, {'fill_holes_m': -0.2}):
        with pytest.raises(ConfigError, match=list(bad)[0]):
            from_dict(StereoParams, bad)
    with pytest.raises(ConfigError, match='cell_m'):
        from_dict(FusionConfig, {'cell_m': 0.001})
    # Left at AUTO, the matcher and the fusion refuse to run rather than guess.
    with pytest.raises(ConfigError, match='resolve'):
        Fusion(FusionConfig(cell_m=gsd.AUTO))


def test_the_core_defaults_are_auto_and_resolve_from_the_pairs_height():
    # Left at their defaults, a pair of the simulator's camera 40 m up matches as the shipped configs did.
    from helpers.sim_world import rendered, world
    from photogram_ros.core.pairs import PairCriteria
    from photogram_ros.core.stereo import StereoParams, stereo_pair
    assert set(gsd.unresolved(StereoParams())) == {'downscale', 'fill_holes_m', 'edge_step_m'}
    assert set(gsd.unresolved(PairCriteria())) == {'relief_m', 'depth_margin_m'}
    cam = world('tiny')[0].camera()
    (_, Ta, ia), (_, Tb, ib) = rendered((2.0, 3.75))
    auto = stereo_pair(cam, ia, Ta, ib, Tb, StereoParams(), (20.0, 60.0))
    mine = stereo_pair(cam, ia, Ta, ib, Tb, StereoParams(downscale=0.5, fill_holes_m=2.0, edge_step_m=1.0),
                       (20.0, 60.0))
    assert auto.ok and auto.rect.f_px == pytest.approx(0.5 * (cam.fx + cam.fy) / 2)
    assert auto.cloud.size == mine.cloud.size


def test_dsm_rules_follow_the_map_cell():
    from photogram_ros.io.export import DsmParams
    assert gsd.dsm_lengths_for_cell(0.12) == (0.5, 3.0)
    r = DsmParams().for_cell(0.48)
    assert (r.max_spread_m, r.fill_gaps_m, r.min_count) == (2.0, 12.0, 3)
    mine = DsmParams(max_spread_m=0.8).for_cell(0.48)
    assert mine.max_spread_m == 0.8 and mine.fill_gaps_m == 12.0


@pytest.mark.parametrize('bad', [(0, 480, 520.0, 40.0), (640, 480, 520.0, -3.0), (640, 480, 520.0, float('nan'))])
def test_impossible_geometry_is_a_config_error(bad):
    with pytest.raises(ConfigError):
        gsd.derive(*bad)
