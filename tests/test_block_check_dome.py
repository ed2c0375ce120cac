"""The block check's dome (core/block_check.py): cameras that dome against their geotag heights far beyond the
geotags' own consistency are a bent block (a warning naming the rise); geotags that wander, a layout that does
not determine a quadratic (one or two lines) and a level block are not."""

import numpy as np
import pytest

from photogram_ros.core.block_check import BlockCheckOptions, BlockInputs, check_block


def _block(rise_m: float, geotag_sigma_m: float, lines=(-25.0, 0.0, 25.0), seed: int = 0,
           self_calibration: dict | None = None) -> BlockInputs:
    """A nadir block of parallel lines 90 m long, 40 m up; camera heights = geotag heights + a paraboloid
    rising by `rise_m` at the farthest camera + the geotags' noise (sigma `geotag_sigma_m`)."""
    rng = np.random.default_rng(seed)
    E, N = np.meshgrid(np.linspace(-45.0, 45.0, 10), np.asarray(lines, float))
    E, N = E.ravel(), N.ravel()
    n = len(E)
    r2 = E ** 2 + N ** 2
    fix = np.column_stack([E, N, 40.0 + 0.002 * E + rng.normal(0.0, geotag_sigma_m, n)])
    C = np.column_stack([E, N, 40.0 + 0.002 * E + rise_m * r2 / r2.max()])
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:, :3, 3] = C
    return BlockInputs([f'p{i:02d}.jpg' for i in range(n)], T, fix, np.tile([3.0, 5.0], (n, 1)), np.zeros(n),
                       adjustment={'status': 'converged'}, self_calibration=self_calibration or {})


def test_a_domed_block_warns_with_its_rise():
    sel = {'candidates': ['k1', 'k2'], 'kept': ['k1', 'k2']}
    v = check_block(_block(-0.6, 0.05, self_calibration=sel))
    d = v.figures['dome']
    print(v.summary, d)
    assert v.status == 'warning' and [f.check for f in v.findings] == ['dome']
    assert d['rise_m'] == pytest.approx(-0.6, abs=0.1) and d['scatter_m'] == pytest.approx(0.05, rel=0.4)
    text = v.findings[0].text
    assert 'dome' in text and f'{d["rise_m"]:+.2f} m' in text and 'radial distortion' in text
    assert 'kept k1, k2 of k1, k2' in text


@pytest.mark.parametrize('rise_m, sigma_m', [(0.0, 0.05), (-0.1, 0.02), (-0.6, 0.3), (0.4, 0.5)])
def test_level_blocks_and_loose_geotags_stay_ok(rise_m, sigma_m):
    # level; a 10 cm dome (below dome_warn_m); geotags that scatter (a GNSS, not a barometer) hide 0.6 m
    for seed in range(5):
        v = check_block(_block(rise_m, sigma_m, seed=seed))
        assert v.status == 'ok', (seed, v.summary, v.figures['dome'])


def test_two_lines_do_not_determine_a_dome():
    v = check_block(_block(-0.6, 0.05, lines=(-12.0, 12.0)))
    assert v.status == 'ok' and v.figures['dome']['rise_sigma_m'] is None


def test_a_block_in_flight_is_not_judged():
    b = _block(-0.6, 0.05)
    b.adjustment = {}
    v = check_block(b)
    assert v.status == 'ok' and 'dome' not in v.figures


def test_the_threshold_is_an_option():
    b = _block(-0.6, 0.05)
    assert check_block(b, BlockCheckOptions(dome_warn_ratio=50.0)).status == 'ok'
    assert check_block(b, BlockCheckOptions(dome_warn_m=1.0)).status == 'ok'
