"""A flight whose tracks were all lost early (the camera stopped on the first line): the block before the break
is too short to georeference on its own, the segment after it is not; both end in the map where their GNSS puts
them, against the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest

from test_incremental import _lost_every_track

from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions
from photogram_ros.sim.observations import simulate_keyframes
from photogram_ros.sim.scenario import build_world, preset


@pytest.fixture(scope='module')
def flight():
    cfg = preset('tiny')
    return simulate_keyframes(cfg, world=build_world(cfg, np.random.default_rng(cfg.seed)), attitude_sigma_deg=None)


@pytest.mark.parametrize('k_break', [3, 5, 7])
def test_a_break_early_on_the_first_line_leaves_a_short_block_that_joins_the_segment(flight, k_break):
    sk = flight
    recs = _lost_every_track(sk.records, k_break)
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m)), origin=sk.origin)
    reps = [at.add_keyframe(r) for r in recs]
    in_flight = len(at.registered)
    at.full_adjustment()
    err = {k: float(np.linalg.norm(at.kfs[k].map_T_cam[:3, 3] - sk.true_map_T_cam[k][:3, 3])) for k in at.registered}
    before = [k for k in at.registered if k < k_break]
    print(f'break at keyframe {k_break} of {len(recs)}: {in_flight} oriented in flight, {len(at.registered)} at the '
          f'end ({len(before)} before the break); centres within {max(err.values()):.3f} m of the truth; '
          f'{sum(r.joined > 0 for r in reps)} joins in flight')
    assert at.georeferenced and at.segments_joined == 1
    assert any(r.joined for r in reps)                                  # in flight, not only at the end
    assert len(at.registered) >= len(recs) - 3
    assert max(err.values()) < 1.5 * 0.064        # measured: 6.4 cm


def test_a_short_block_its_consumer_gnss_cannot_place_gives_way_to_the_segment(flight):
    """With a 3D fix (1.4 m of noise) the 4 keyframes before the break (15 m of line: under
    georef_line_min_keyframes, and its heading to 7 degrees only) cannot be placed: they are given up (not oriented, counted),
    and the flight after the break is mapped where its GNSS puts it, instead of nothing at all."""
    cfg = preset('tiny')
    sk = simulate_keyframes(cfg, gnss_mode='3d', world=build_world(cfg, np.random.default_rng(cfg.seed)),
                            attitude_sigma_deg=None)
    k_break = 4
    recs = _lost_every_track(sk.records, k_break)
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m)), origin=sk.origin)
    reps = [at.add_keyframe(r) for r in recs]
    at.full_adjustment()
    fixes = np.array([np.linalg.norm(at.kfs[k].fix_enu - sk.true_map_T_cam[k][:3, 3]) for k in at.registered])
    err = np.array([np.linalg.norm(at.kfs[k].map_T_cam[:3, 3] - sk.true_map_T_cam[k][:3, 3]) for k in at.registered])
    print(f'3D GNSS, break at {k_break}: {len(at.registered)} of {len(recs)} oriented, {at.unplaced_keyframes} given '
          f'up; centres {np.sqrt(np.mean(err ** 2)):.2f} m RMS from the truth, the fixes {np.sqrt(np.mean(fixes ** 2)):.2f} m')
    assert at.georeferenced and at.unplaced_keyframes == k_break and any(r.joined for r in reps)
    assert all(k >= k_break for k in at.registered) and len(at.registered) >= len(recs) - k_break - 1
    assert np.sqrt(np.mean(err ** 2)) < 1.5 * np.sqrt(np.mean(fixes ** 2))
