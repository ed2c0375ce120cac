"""The GNSS bias estimate with GCPs: RTK fixes a few centimetres off (the simulator's wandering bias) are
estimated to the centimetre, against the true mean error of the flight's fixes."""

from __future__ import annotations

import dataclasses

import numpy as np

from photogram_ros.core.block_check import check_block, inputs_from_at
from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions
from photogram_ros.sim.observations import simulate_keyframes
from test_incremental import _rmse_hv, _run, world  # noqa: F401  (a fixture)


def test_rtk_bias_of_a_few_centimetres_is_estimated_with_five_gcps(world):  # noqa: F811
    cfg, w = world
    sk, at, rep, _, chk = _run(cfg, w, 'rtk_fixed', use_gcps=True, seed=7)
    gnss_err = np.array([sk.origin.geodetic_to_enu(r.fix.lat_deg, r.fix.lon_deg, r.fix.h_m)
                         - (T[:3, 3] + r.antenna_offset_map_m) for r, T in zip(sk.records, sk.true_map_T_cam)])
    true_bias = gnss_err.mean(axis=0)
    off = np.linalg.norm(at.gnss_bias_enu - true_bias)
    h, v = _rmse_hv(chk)
    print(f'RTK + 5 GCPs: true mean GNSS error {np.round(true_bias * 100, 1)} cm, estimated bias '
          f'{np.round(at.gnss_bias_enu * 100, 1)} cm ({off * 100:.2f} cm apart); check RMSE h {h * 100:.2f} cm, '
          f'v {v * 100:.2f} cm')
    assert at.gnss_bias_estimated
    settle = at.gnss_bias_rounds
    print(f'bias estimate: {settle}')
    assert settle['settled'] and settle['last_step_m'] < 0.001 and 2 <= settle['rounds'] <= 10
    v_check = check_block(inputs_from_at(at, adjustment={'status': 'converged'}))
    assert v_check.figures['gnss_bias']['settled'] and not any(f.check == 'gnss_bias' for f in v_check.findings)
    assert abs(true_bias[2]) > 0.03                        # this flight's fixes are 4 cm low: a bias to find
    assert off <= 1.5 * 0.0193                             # measured 1.93 cm (3.93 cm with the bias left at 0.2 cm)
    assert v <= 1.5 * 0.0117                               # measured 1.17 cm (3.75 cm with the bias left at 0.2 cm)


def test_a_bias_estimate_that_did_not_settle_is_a_warning(world):  # noqa: F811
    """One adjustment with the bias as unknowns (never taken as settled: the outliers it removes can move the
    bias): the block check says the bias did not settle, with the step it took."""
    cfg, w = world
    sk = simulate_keyframes(dataclasses.replace(cfg, seed=7), gnss_mode='rtk_fixed', world=w)
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m), bias_iterations=1),
                       origin=sk.origin, control=sk.control)
    for r in sk.records:
        at.add_keyframe(r)
    rep = at.full_adjustment()
    v = check_block(inputs_from_at(at, adjustment={'status': rep.status}))
    found = [f for f in v.findings if f.check == 'gnss_bias']
    assert at.gnss_bias_rounds['rounds'] == 1 and not at.gnss_bias_rounds['settled']
    assert at.gnss_bias_rounds['last_step_m'] > 0.03     # measured 5.5 cm: the flight's fixes are 4 cm low
    assert v.status in ('warning', 'failed') and len(found) == 1 and found[0].status == 'warning'
    assert 'did not settle in 1 adjustments' in found[0].text and 'cm' in found[0].text, found[0].text


def test_gcps_without_any_fix_have_no_bias_to_settle(world):  # noqa: F811
    """Photos without geotags, 5 GCPs: there is no GNSS bias to estimate, and the block check says nothing of
    one (the GCPs alone place the block)."""
    cfg, w = world
    sk = simulate_keyframes(dataclasses.replace(cfg, seed=7), gnss_mode='rtk_fixed', world=w)
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m)),
                       origin=sk.origin, control=sk.control)
    for r in sk.records:
        at.add_keyframe(dataclasses.replace(r, fix=None))
    rep = at.full_adjustment()
    v = check_block(inputs_from_at(at, adjustment={'status': rep.status}))
    assert len(at.registered) == len(sk.records)
    assert at.gnss_bias_rounds == {} and 'gnss_bias' not in v.figures
    assert not any(f.check == 'gnss_bias' for f in v.findings)
    assert at.georeferenced and at.gcps_in_block() == 5   # placed by its GCPs (tests/test_gcp_georeference.py)


def test_a_glitched_geotag_the_adjustment_rejected_does_not_move_the_bias(world):  # noqa: F811
    """RTK + 5 GCPs, one keyframe's fix 25 m east and 10 m up of where it was (a glitched geotag): the adjustment
    rejects that fix, and the bias, estimated from the fixes it uses, stays where the clean flight puts it. (A bias
    taken as the mean residual of every fix, the glitch among them, moves by its 27 m over the flight's keyframes.)"""
    cfg, w = world
    sk = simulate_keyframes(dataclasses.replace(cfg, seed=7), gnss_mode='rtk_fixed', world=w)
    runs = {}
    for tag, glitch in (('clean', None), ('glitched', len(sk.records) // 2)):
        at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m)),
                           origin=sk.origin, control=sk.control)
        for i, r in enumerate(sk.records):
            if i == glitch:
                enu = sk.origin.geodetic_to_enu(r.fix.lat_deg, r.fix.lon_deg, r.fix.h_m) + np.array([25.0, 0.0, 10.0])
                lat, lon, h = sk.origin.enu_to_geodetic(enu)
                r = dataclasses.replace(r, fix=dataclasses.replace(r.fix, lat_deg=float(lat), lon_deg=float(lon),
                                                                   h_m=float(h)))
            at.add_keyframe(r)
        at.full_adjustment()
        runs[tag] = at
    glitched = runs['glitched']
    assert [glitched.kfs[k].name for k in glitched.gnss_rejected] == [sk.records[len(sk.records) // 2].name]
    moved = np.linalg.norm(glitched.gnss_bias_enu - runs['clean'].gnss_bias_enu)
    print(f'bias clean {np.round(runs["clean"].gnss_bias_enu * 100, 1)} cm, with the glitch '
          f'{np.round(glitched.gnss_bias_enu * 100, 1)} cm: moved {moved * 100:.2f} cm')
    assert glitched.gnss_bias_rounds['settled']
    assert moved < 1.5 * 0.0016                                  # measured 0.16 cm (the loop before it: 107 m)
