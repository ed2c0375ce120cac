"""A keyframe taken before the block's first pair that shares only a few two-view tracks with one later keyframe
(brighton_beach every other photo: DJI_0018 with DJI_0028, 22 inliers) is oriented in flight from two views scaled
by GNSS (core/at_two_view.py) where the truth has it; and refused when its fix puts the baseline elsewhere than its
images do. Synthetic keyframes (sim/observations.py, the tiny world of tests/test_incremental.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions
from photogram_ros.core.rotations import angle_between_R
from photogram_ros.sim.observations import simulate_keyframes
from photogram_ros.sim.scenario import build_world, preset

LATE = 6          # this keyframe comes first, before the pair that starts the block
N_SHARED = 20     # two-view tracks it shares with keyframe LATE + 1 (fewer than min_relative_inliers)


@pytest.fixture(scope='module')
def flight():
    cfg = preset('tiny', n_gcp=5, n_check=4)
    w = build_world(cfg, np.random.default_rng(cfg.seed))
    return simulate_keyframes(cfg, gnss_mode='rtk_fixed', world=w)


def _two_view_only(sk):
    """The records with keyframe LATE first, seeing only N_SHARED tracks, which keyframe LATE + 1 alone shares
    with it (renamed there): no point it sees is known to the block, only two-view tracks to one keyframe."""
    recs = list(sk.records)
    a, b = recs[LATE], recs[LATE + 1]
    common = np.intersect1d(a.track_ids[a.track_ids >= 0], b.track_ids)[:N_SHARED]
    assert len(common) == N_SHARED
    new = {int(t): 10_000_000 + int(t) for t in common}
    keep = np.isin(a.track_ids, common)
    a = dataclasses.replace(a, track_ids=np.array([new[int(t)] for t in a.track_ids[keep]]), uv=a.uv[keep],
                            target_uv={})
    b = dataclasses.replace(b, track_ids=np.array([new.get(int(t), int(t)) for t in b.track_ids]))
    order = [a] + recs[:LATE] + [b] + recs[LATE + 2:]
    truth = [LATE] + list(range(LATE)) + list(range(LATE + 1, len(recs)))
    return order, truth


def _fly(sk, recs):
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m)), origin=sk.origin)
    reps = [at.add_keyframe(r) for r in recs]
    return at, reps


def test_a_keyframe_before_the_first_pair_orients_from_two_views_and_gnss(flight):
    sk = flight
    recs, truth = _two_view_only(sk)
    at, reps = _fly(sk, recs)
    assert reps[0].status == 'waiting_for_initialisation'
    # Oriented in flight (not by the end-of-flight second chance), from two views, and said so.
    assert at.kfs[0].map_T_cam is not None
    assert at.two_view_oriented[0].startswith('registered_two_view (')
    T, T_true = at.kfs[0].map_T_cam, sk.true_map_T_cam[truth[0]]
    err_m = float(np.linalg.norm(T[:3, 3] - T_true[:3, 3]))
    err_deg = float(np.degrees(angle_between_R(T[:3, :3], T_true[:3, :3])))
    # Its rotation relative to its partner's, against the truth's (whatever the block's own rotation error).
    P, P_true = at.kfs[LATE + 1].map_T_cam, sk.true_map_T_cam[LATE + 1]
    rel_deg = float(np.degrees(angle_between_R(P[:3, :3].T @ T[:3, :3], P_true[:3, :3].T @ T_true[:3, :3])))
    others = np.array([np.linalg.norm(at.kfs[k].map_T_cam[:3, 3] - sk.true_map_T_cam[truth[k]][:3, 3])
                       for k in at.registered if k != 0])
    rms = float(np.sqrt(np.mean(others ** 2)))
    print(f'{at.two_view_oriented[0]}; centre {err_m:.2f} m, rotation {err_deg:.2f} deg ({rel_deg:.2f} deg against '
          f'its partner\'s) from the truth; the other keyframes {rms:.2f} m RMS')
    assert rel_deg < 0.5 and err_deg < 1.0
    assert err_m < max(3.0 * rms, 0.5)


def test_a_two_view_pose_the_gnss_baseline_disagrees_with_is_refused(flight):
    sk = flight
    recs, truth = _two_view_only(sk)
    # Keyframe LATE's fix moved 3 m across its baseline to keyframe LATE + 1 (about 5 m): the fixes' direction
    # between the two is some 30 degrees off the one the images give.
    base = sk.true_map_T_cam[LATE + 1][:3, 3] - sk.true_map_T_cam[LATE][:3, 3]
    across = np.cross(base, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    fix = recs[0].fix
    enu = np.asarray(sk.origin.geodetic_to_enu(fix.lat_deg, fix.lon_deg, fix.h_m), float).ravel() + 3.0 * across
    lat, lon, h = LocalFrame.enu_to_geodetic(sk.origin, enu[None])
    recs[0] = dataclasses.replace(recs[0], fix=dataclasses.replace(
        fix, lat_deg=float(np.ravel(lat)[0]), lon_deg=float(np.ravel(lon)[0]), h_m=float(np.ravel(h)[0])))
    at, _ = _fly(sk, recs)
    assert at.kfs[0].map_T_cam is None and 0 not in at.two_view_oriented
    why = at.registration.two_view(at.kfs[0], at.registered, 'waiting')
    print(why.status)
    assert not why.registered and 'baseline direction' in why.status
    # Nor at the end of the flight (the second chance goes through the same gates).
    at.retry_unregistered()
    assert at.kfs[0].map_T_cam is None
