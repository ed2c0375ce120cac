"""The in-flight fix gate (core/gnss_rounds.py `gate_fix`) judges a new keyframe's fix against where the block's
other fixes, at least as precise as it, put the block, not against the block as if it sat on its fixes: a block
that drifted off its GNSS by more than `gnss_gate_m` (a third of DJI RTK photos flagged FLOAT and 1 m off, as in
bench/ppk_formats.py's sample preset) must not refuse its precise (RTK fixed) fixes while it keeps the FLOAT ones;
a glitched fix stays refused."""

from types import SimpleNamespace

import numpy as np

from photogram_ros.core.gnss_datum import GnssDatum
from photogram_ros.core.gnss_rounds import GnssRounds

FIXED_SD = (0.0136, 0.0286)      # RTK fixed (per horizontal axis, vertical), m: the simulator's
FLOAT_SD = (0.5, 0.8)            # a DJI FLOAT photo's RtkStd*, m
DRIFT_ENU_M = np.array([1.4, -0.6, 0.3])    # the block off its fixes: beyond the 1 m gate


def _kf(k, error_enu, sd):
    T = np.eye(4)
    T[:3, 3] = [10.0 * k, 5.0 * (k % 3), 100.0]
    sh, sv = sd
    return SimpleNamespace(kid=k, name=f'IMG_{k:04d}.JPG', map_T_cam=T, antenna_offset=None,
                           fix_enu=T[:3, 3] - np.asarray(error_enu, float), fix_cov=np.diag([sh ** 2, sh ** 2, sv ** 2]))


def _drifted_block(n=24, seed=5):
    """n keyframes oriented from tie points, every third FLOAT and 1 m off, the whole block DRIFT_ENU_M off its
    fixes; then a new keyframe (id n) of each kind to gate, at the same drift."""
    rng = np.random.default_rng(seed)
    kfs = []
    for k in range(n):
        e = DRIFT_ENU_M + rng.normal(0.0, 1.0, 3) * np.array([FIXED_SD[0], FIXED_SD[0], FIXED_SD[1]])
        if k % 3 == 2:
            a = rng.uniform(0, 2 * np.pi)
            e = e + np.array([np.cos(a), np.sin(a), 0.0])
        kfs.append(_kf(k, e, FLOAT_SD if k % 3 == 2 else FIXED_SD))
    return SimpleNamespace(kfs=kfs, registered=list(range(n)), georeferenced=True, points={}, n_gcps=lambda: 0)


def _rounds(block):
    opt = SimpleNamespace(gimbal=False, lever_arm_cam_m=(0.0, 0.0, 0.0), gnss_outlier_sigma=5.0, gnss_gate_m=1.0,
                          max_reprojection_px=4.0, loss='huber', loss_scale_px=1.0, window_iterations=5)
    datum = GnssDatum(block, opt)
    # The window trial has nothing to adjust here: it never rescues a fix the gate calls far.
    adjustment = SimpleNamespace(window_selection=lambda: SimpleNamespace(free_kfs=[], fixed_kfs=[], track_ids=[]),
                                 build=lambda *a: SimpleNamespace(prob=None, kids=[]))
    return GnssRounds(block, datum, adjustment, opt), datum


def _gate(block, kf):
    block.kfs.append(kf)
    block.registered.append(kf.kid)
    rounds, datum = _rounds(block)
    return rounds.gate_fix(kf), datum


def test_a_drifted_block_keeps_its_precise_fixes_as_it_keeps_its_float_ones():
    n = 24
    fixed_refused, datum = _gate(_drifted_block(n), _kf(n, DRIFT_ENU_M + [0.01, -0.005, 0.02], FIXED_SD))
    float_refused, _ = _gate(_drifted_block(n), _kf(n, DRIFT_ENU_M + [0.8, 0.5, 0.0], FLOAT_SD))
    assert not float_refused                      # 1.7 m off, within 2 x 5 of its 0.5 m
    assert not fixed_refused and not datum.rejected   # 1.5 m off, as every other precise fix of the block


def test_a_glitched_fix_is_still_refused_in_a_drifted_block():
    n = 24
    refused, datum = _gate(_drifted_block(n), _kf(n, DRIFT_ENU_M + [4.0, 2.0, 0.0], FIXED_SD))
    assert refused and datum.rejected == {n}
    refused, datum = _gate(_drifted_block(n), _kf(n, DRIFT_ENU_M + [0.0, 9.0, 0.0], FLOAT_SD))
    assert refused and datum.rejected == {n}      # beyond 2 x 5 of its 0.5 m from the precise fixes' datum


def test_a_block_on_its_fixes_gates_as_before():
    """No drift: the gate is the fix's own (2 x gnss_outlier_sigma of its sigma, at least gnss_gate_m)."""
    n = 24
    block = _drifted_block(n)
    for kf in block.kfs:
        kf.fix_enu = kf.fix_enu + DRIFT_ENU_M
    near, _ = _gate(block, _kf(n, [0.5, 0.5, 0.0], FIXED_SD))
    block = _drifted_block(n)
    for kf in block.kfs:
        kf.fix_enu = kf.fix_enu + DRIFT_ENU_M
    far, _ = _gate(block, _kf(n, [1.3, 0.0, 0.0], FIXED_SD))
    assert not near and far
