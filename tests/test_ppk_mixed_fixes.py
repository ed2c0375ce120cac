"""Fixes of mixed quality (DJI RTK photos, a third flagged FLOAT beside RTK-fixed ones): each fix counts by the
sigma it states (core/gnss_datum.py `stated_sigmas_hv`, core/gnss_rounds.py `estimate_noise`), and only the
precise ones are fit to place the block by a similarity (`GnssDatum.similarity_fixes`).

The figures these guard end to end are in bench/results/ppk_formats_*.jsonl (bench/ppk_formats.py: a third of
the photos FLOAT and 1 m off against the clean survey); here the rules themselves, on a stub block whose
adjusted cameras sit at known offsets from their fixes."""

from types import SimpleNamespace

import numpy as np
import pytest

from photogram_ros.core.gnss_datum import GnssDatum
from photogram_ros.core.gnss_rounds import GnssRounds

FIXED_SD = (0.0136, 0.0286)      # RTK fixed (per horizontal axis, vertical), m: the simulator's
FLOAT_SD = (0.5, 0.8)            # a DJI FLOAT photo's RtkStd*, m


def _block(errors_enu, sds):
    """A stub block: keyframe k's camera at the origin of its own pose, its fix `errors_enu[k]` away from it
    (fix = camera - error, so the residual camera - fix is the error), with sigmas `sds[k]` (h, v)."""
    kfs = []
    for k, (e, (sh, sv)) in enumerate(zip(errors_enu, sds)):
        T = np.eye(4)
        T[:3, 3] = [10.0 * k, 5.0 * (k % 3), 100.0]
        kfs.append(SimpleNamespace(kid=k, name=f'IMG_{k:04d}.JPG', map_T_cam=T, antenna_offset=None,
                                   fix_enu=T[:3, 3] - np.asarray(e, float), fix_cov=np.diag([sh ** 2, sh ** 2, sv ** 2])))
    return SimpleNamespace(kfs=kfs, registered=list(range(len(kfs))), georeferenced=True, points={},
                           n_gcps=lambda: 0)


def _rounds(block):
    opt = SimpleNamespace(gimbal=False, lever_arm_cam_m=(0.0, 0.0, 0.0), gnss_noise_min_keyframes=8,
                          gnss_tighten=False, gnss_tighten_floor_m=0.05, gnss_outlier_sigma=5.0, full_iterations=1,
                          assume_nadir=False)
    datum = GnssDatum(block, opt)
    return GnssRounds(block, datum, SimpleNamespace(solve=lambda *a, **k: None), opt), datum


def _mixed(n=24, float_offset_m=1.0, seed=5):
    """n fixes, every third FLOAT and `float_offset_m` off horizontally; the fixed ones with their own noise."""
    rng = np.random.default_rng(seed)
    err, sds = [], []
    for k in range(n):
        e = rng.normal(0.0, 1.0, 3) * np.array([FIXED_SD[0], FIXED_SD[0], FIXED_SD[1]])
        if k % 3 == 2:
            a = rng.uniform(0, 2 * np.pi)
            e = e + float_offset_m * np.array([np.cos(a), np.sin(a), 0.0])
        err.append(e)
        sds.append(FLOAT_SD if k % 3 == 2 else FIXED_SD)
    return err, sds


def test_stated_sigmas_are_each_fixs_own():
    err, sds = _mixed(6)
    _, datum = _rounds(_block(err, sds))
    s = datum.stated_sigmas_hv(range(6))
    assert s.shape == (6, 2)
    np.testing.assert_allclose(s[2], FLOAT_SD)
    np.testing.assert_allclose(s[0], FIXED_SD)


def test_similarity_takes_the_precise_fixes_only():
    err, sds = _mixed(12)
    _, datum = _rounds(_block(err, sds))
    got = datum.similarity_fixes(range(12), min_count=3)
    assert got == [k for k in range(12) if k % 3 != 2]


def test_similarity_takes_every_fix_when_they_are_alike_or_too_few_are_precise():
    err, _ = _mixed(12, float_offset_m=0.0)
    _, datum = _rounds(_block(err, [FIXED_SD] * 12))
    assert datum.similarity_fixes(range(12), min_count=3) == list(range(12))
    # Two precise fixes among ten float ones: fewer than min_count, nothing better to place the block by.
    sds = [FIXED_SD if k < 2 else FLOAT_SD for k in range(12)]
    _, datum = _rounds(_block(err, sds))
    assert datum.similarity_fixes(range(12), min_count=3) == list(range(12))


def test_float_fixes_within_their_sigma_neither_inflate_the_noise_nor_are_rejected():
    """A third FLOAT, 1 m off (2 of their stated 0.5 m): the fixed ones' noise is as stated, so no scale factor;
    the float ones are where their sigma says they may be, so none is rejected."""
    err, sds = _mixed(24)
    rounds, datum = _rounds(_block(err, sds))
    out = rounds.estimate_noise()
    # Reported on the fixes' RMS stated sigma (what the report's noise figures compare against).
    assert out['stated_h_m'] == pytest.approx(np.sqrt((2 * FIXED_SD[0] ** 2 + FLOAT_SD[0] ** 2) / 3))
    assert out['scale_h'] == 1.0 and out['scale_v'] == 1.0
    assert out['rejected'] == []
    # The factor on each fix's own sigma (pooled, the residuals' spread was the fixed ones' 1 cm against a stated
    # 29 cm RMS: a factor of 0.03, which would say the float photos were as good as the fixed ones).
    assert 0.3 < out['estimated_h_m'] / out['stated_h_m'] < 1.5


def test_a_float_fix_far_beyond_its_sigma_is_rejected():
    """One FLOAT photo 6 m off (12 of its stated sigmas) among float ones 1 m off: it alone is rejected."""
    err, sds = _mixed(24)
    err[5] = err[5] + np.array([6.0, 0.0, 0.0])
    rounds, datum = _rounds(_block(err, sds))
    out = rounds.estimate_noise()
    assert out['rejected'] == ['IMG_0005.JPG']


def test_fixes_of_one_quality_scale_as_before():
    """All fixed, their noise 3x what they state: the factor is the residuals' spread over the stated sigma."""
    rng = np.random.default_rng(2)
    err = [rng.normal(0.0, 1.0, 3) * 3.0 * np.array([FIXED_SD[0], FIXED_SD[0], FIXED_SD[1]]) for _ in range(40)]
    rounds, _ = _rounds(_block(err, [FIXED_SD] * 40))
    out = rounds.estimate_noise()
    assert 2.0 < out['scale_h'] < 4.0 and 2.0 < out['scale_v'] < 4.0
    assert out['estimated_h_m'] == pytest.approx(out['scale_h'] * FIXED_SD[0])
