"""Control in flight (core/control_live.py), checked before the adjustment leans on it.

The adjuster is fed keyframe by keyframe, as bundle_node feeds it, on a simulated RTK flight with five
GCPs and four check points. Each test hands it the control file a surveyor might really give, with
placeholder heights of 400 m or 0, one GCP 30 m off, a misread marker, or only one GCP. Each test then
asserts two things:
- the fault is named;
- the block is not strained: the spread of the GNSS residuals (about their mean) stays within 1.2x of
  the same flight adjusted without control.
The check points are measured against the simulator's truth.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from photogram_ros.core.control_live import LiveControl
from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions
from photogram_ros.sim.observations import simulate_keyframes
from photogram_ros.sim.scenario import build_world, preset

MAX_STRAIN = 1.2
ORIGIN_H_M = 488.0          # the simulator's take-off point, ellipsoidal


@pytest.fixture(scope='module')
def flight():
    cfg = preset('tiny', n_gcp=5, n_check=4)
    world = build_world(cfg, np.random.default_rng(cfg.seed))
    return simulate_keyframes(cfg, world=world, attitude_sigma_deg=None)


def _fly(sk, control=None, records=None):
    """(adjuster, live control, faults) after every keyframe and the final adjustment, as bundle_node runs them."""
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m)), origin=sk.origin)
    live, faults, held_while_provisional = None, [], []
    if control is not None:
        live = LiveControl({c.name: float(c.map_xyz[2] + ORIGIN_H_M) for c in control})
        live.set_surveyed(control)
        at.set_control(live.adjuster_control())
    for r in records or sk.records:
        at.add_keyframe(r)
        if live is None:
            continue
        if r.target_uv and at.kfs[-1].stamp_ns == r.stamp_ns:
            live.observe(len(at.kfs) - 1, r.target_uv)
        faults += live.update(at)
        if not at.georeferenced or at.georef_provisional:
            held_while_provisional.append(live.summary()['gcps_held'] + live.summary()['gcps_not_seen'])
    if live is not None:
        faults += live.update(at, final=True)
        live.held_while_provisional = held_while_provisional
    at.full_adjustment()
    return at, live, faults


def _spread(at) -> float:
    g = np.array(list(at.gnss_residuals().values()))
    return float(np.sqrt(np.mean(np.sum((g - g.mean(axis=0)) ** 2, axis=1))))


def _checks(sk, at):
    """Check-point RMSE (horizontal, vertical, count) against the truth, from the adjusted cameras."""
    truth = {c.name: c.map_xyz for c in sk.control}
    r = np.array([at.intersect_target(c.name)[0] - truth[c.name] for c in sk.control
                  if c.role == 'check' and at.intersect_target(c.name)])
    return float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1)))), float(np.sqrt(np.mean(r[:, 2] ** 2))), len(r)


@pytest.fixture(scope='module')
def baseline(flight):
    at, _, _ = _fly(flight)
    return _spread(at)


def _heights(sk, z_file_m):
    """The correct file with every GCP height written as z_file_m (ellipsoidal)."""
    return [dataclasses.replace(c, map_xyz=np.array([c.map_xyz[0], c.map_xyz[1], z_file_m - ORIGIN_H_M]))
            if c.role == 'gcp' else c for c in sk.control]


def test_correct_file_every_gcp_used_after_it_was_checked(flight, baseline):
    at, live, faults = _fly(flight, list(flight.control))
    h, v, n = _checks(flight, at)
    print(f'correct file: check RMSE {h * 100:.1f} / {v * 100:.1f} cm over {n}; strain {_spread(at) / baseline:.2f}')
    assert not faults and live.summary()['gcps_full'] == 5 and live.summary()['control_detections_rejected'] == 0
    assert all(live.use_of(c.name) == ('full' if c.role == 'gcp' else 'check') for c in flight.control)
    # Held (check points to the adjuster) while the georeference was provisional or absent.
    assert live.held_while_provisional and all(n == 5 for n in live.held_while_provisional)
    assert all(at.target_track(c.name) in at.points for c in flight.control if c.role == 'gcp')
    assert n == 4 and h < flight.gsd_m and v < 1.5 * flight.gsd_m
    assert _spread(at) <= MAX_STRAIN * baseline


@pytest.mark.parametrize('z_file_m, why', [(400.0, '400.000 m in the file, the same to the millimetre'),
                                           (0.0, 'exactly 0 m in the file')])
def test_placeholder_heights_are_used_horizontally_only(flight, baseline, z_file_m, why):
    at, live, faults = _fly(flight, _heights(flight, z_file_m))
    h, v, n = _checks(flight, at)
    print(f'heights {z_file_m} m: check RMSE {h * 100:.1f} / {v * 100:.1f} cm; strain {_spread(at) / baseline:.2f}')
    print('\n'.join(faults))
    assert live.summary()['gcps_horizontal_only'] == 5
    gcps = [p for p in live.vetting.points.values() if p.role == 'gcp']
    assert all(p.vertical == 'contradicted' and p.horizontal == 'agrees' and why in p.reason for p in gcps)
    assert live.vetting.height_suspect == 'control_heights'
    assert any('the suspect is the control file\'s heights' in f for f in faults)
    assert sum(f.startswith('GCP GCP0') and 'used horizontally only' in f for f in faults) == 5
    # Not bent to the placeholder: the heights are the GNSS's, the check points still right.
    assert _spread(at) <= MAX_STRAIN * baseline
    assert n == 4 and h < flight.gsd_m and v < 1.5 * flight.gsd_m
    assert all(c.sigma_m[2] >= 1e3 for c in live.adjuster_control() if c.role == 'gcp')


def test_gcp_with_wrong_coordinates_is_not_used(flight, baseline):
    moved = [dataclasses.replace(c, map_xyz=c.map_xyz + [30.0, 0.0, 0.0]) if c.name == 'GCP02' else c
             for c in flight.control]
    at, live, faults = _fly(flight, moved)
    p = live.vetting.points['GCP02']
    assert live.use_of('GCP02') == 'unused' and p.horizontal == 'contradicted'
    assert p.d_h_m == pytest.approx(30.0, abs=0.5)
    assert any(f.startswith('GCP GCP02 not used') and 'wrong coordinates' in f for f in faults)
    assert live.summary()['gcps_full'] == 4
    assert at.is_check(at.target_track('GCP02'))    # never a prior
    assert _spread(at) <= MAX_STRAIN * baseline
    h, v, _ = _checks(flight, at)
    assert h < flight.gsd_m and v < 1.5 * flight.gsd_m


def test_misread_marker_is_dropped(flight, baseline):
    recs = list(flight.records)
    k = [i for i, r in enumerate(recs) if 'GCP01' in r.target_uv][1]
    recs[k] = dataclasses.replace(recs[k], target_uv={**recs[k].target_uv, 'GCP01': np.array([50.0, 60.0])})
    at, live, faults = _fly(flight, list(flight.control), recs)
    bad = [f for f in live.vetting.rows if f.fate == 'outlier']
    assert [(f.row.name, f.row.image) for f in bad] == [('GCP01', recs[k].name)]
    assert bad[0].residual_m > 5 and 'misread marker' in bad[0].reason
    assert any('GCP01 in' in f and 'rejected' in f for f in faults)
    tid = at.target_track('GCP01')
    kf = at.kfs[k]
    assert not kf.active[kf.index(tid)]                                    # out of the adjustment
    assert all(k2 != k for k2, _ in live.observations('GCP01', set(at.registered)))
    assert live.use_of('GCP01') == 'full' and _spread(at) <= MAX_STRAIN * baseline


def test_one_gcp_is_used_and_the_block_is_not_strained(flight, baseline):
    one = [c if c.role == 'check' or c.name == 'GCP03' else dataclasses.replace(c, role='check')
           for c in flight.control]
    at, live, faults = _fly(flight, one)
    assert live.summary()['gcps'] == 1 and live.use_of('GCP03') == 'full' and not faults
    assert _spread(at) <= MAX_STRAIN * baseline


def test_a_flight_that_never_turns_takes_its_gcps_as_given_and_says_so():
    """One straight line: the GNSS leaves the roll about it undetermined, so no GNSS-only block can judge
    the control, and only the GCPs fix that roll. They are used as given at the end of the flight, with a
    note; heights that the file itself shows to be placeholders are still used horizontally only."""
    cfg = preset('tiny', n_lines=1, n_gcp=5, n_check=4, line_length_m=60.0)
    sk = simulate_keyframes(cfg, world=build_world(cfg, np.random.default_rng(cfg.seed)), attitude_sigma_deg=None)
    plain, _, _ = _fly(sk)
    at, live, faults = _fly(sk, list(sk.control))
    h0, _, _ = _checks(sk, plain)
    h, v, n = _checks(sk, at)
    print(f'straight line, RTK: check RMSE {h * 100:.1f} / {v * 100:.1f} cm with the GCPs, {h0 * 100:.1f} cm H without')
    assert at.georef_provisional and live.summary()['gcps_full'] == 5
    assert any('could not be checked' in f and 'never turned' in f for f in faults)
    assert n == 4 and h < 0.3 * h0 and h < sk.gsd_m
    at, live, faults = _fly(sk, _heights(sk, 400.0))
    assert live.summary()['gcps_horizontal_only'] == 5
    assert all('placeholder' in live.vetting.points[c.name].reason for c in sk.control if c.role == 'gcp')
    assert sum('not checked against the block' in f for f in faults) == 5


def test_gcps_georeference_a_straight_line_its_3d_gnss_cannot():
    """One straight line under 3D GNSS (~2 m): the fixes' spread across the line is noise, so the GNSS alone
    gives at most a provisional georeference (the roll about the line assumed from the near-nadir camera, said
    provisional to the end). The GCPs, used as given at the end of the flight, place it within a GSD."""
    cfg = preset('tiny', n_lines=1, n_gcp=5, n_check=4, line_length_m=60.0)
    sk = simulate_keyframes(cfg, world=build_world(cfg, np.random.default_rng(cfg.seed)), attitude_sigma_deg=None,
                            gnss_mode='3d')
    plain, _, _ = _fly(sk)
    assert not plain.georeferenced or plain.georef_provisional
    at, live, faults = _fly(sk, list(sk.control))
    h, v, n = _checks(sk, at)
    print(f'straight line, 3D GNSS: check RMSE {h * 100:.1f} / {v * 100:.1f} cm with the GCPs; without them '
          f'georeferenced {plain.georeferenced}, provisional {plain.georef_provisional}')
    assert at.georeferenced and live.summary()['gcps_full'] == 5
    # The GCPs are used as given at the end (no GNSS-only block could check them): still said provisional, as
    # on an RTK line (test_a_flight_that_never_turns_takes_its_gcps_as_given_and_says_so).
    assert at.georef_provisional
    assert n == 4 and h < sk.gsd_m and v < 1.5 * sk.gsd_m
