"""The triangulation report's honesty figures: CE90/LE90, no inf/NaN, the iteration limit said."""

import json

import numpy as np
import pytest

from photogram_ros.core.at_report import build_report, convergence
from photogram_ros.core.evaluation import ce90_le90
from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions
from photogram_ros.io.at_report import write_report
from photogram_ros.sim.observations import simulate_keyframes
from photogram_ros.sim.scenario import preset


def test_ce90_le90_match_the_normal_distributions_quantiles():
    rng = np.random.default_rng(3)
    r = rng.normal(0.0, [0.03, 0.03, 0.05], size=(200_000, 3))
    c = ce90_le90(r)
    # Oracles: the Rayleigh 90 % radius sigma * sqrt(2 ln 10), the normal 95 % two-sided point 1.6449.
    assert c['ce90_m'] == pytest.approx(0.03 * np.sqrt(2 * np.log(10)), rel=0.01)
    assert c['le90_m'] == pytest.approx(0.05 * 1.6449, rel=0.01)
    assert c['ce90_empirical_m'] == pytest.approx(c['ce90_m'], rel=0.01)
    assert c['le90_empirical_m'] == pytest.approx(c['le90_m'], rel=0.01)
    assert c['circular'] and 'coarse' not in c['method']
    # Elongated errors: flagged as outside the circular formula's validity.
    e = ce90_le90(rng.normal(0.0, [0.01, 0.05, 0.02], size=(12, 3)))
    assert not e['circular'] and 'coarse' in e['method'] and ce90_le90(np.zeros((0, 3))) == {'n': 0}


@pytest.fixture(scope='module')
def stopped_block():
    """A simulated block whose full adjustment stops at its iteration limit (1 iteration; without the GNSS
    bias's rounds, which go on to convergence)."""
    sk = simulate_keyframes(preset('tiny', n_gcp=5, n_check=4), gnss_mode='rtk_float')
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m), full_iterations=1,
                                                     window_iterations=1, estimate_gnss_bias=False),
                       origin=sk.origin, control=sk.control)
    for r in sk.records:
        at.add_keyframe(r)
    return at, at.full_adjustment(iterations=1, rounds=1)


def test_iteration_limit_says_how_far_from_converged(stopped_block):
    at, rep = stopped_block
    assert rep.status == 'max_iterations'
    c = convergence(at, rep.status)
    assert c is not None and np.isfinite(c['next_relative_cost_decrease']) and c['next_relative_cost_decrease'] >= 0
    assert np.isfinite(c['max_camera_move_m']) and isinstance(c['matters'], bool)
    assert 'iteration limit' in c['text'] and ('MATTERS' in c['text']) == c['matters']
    assert convergence(at, 'converged') is None


def test_a_photo_without_valid_residuals_says_why_and_the_report_has_no_inf(stopped_block, tmp_path):
    at, _ = stopped_block
    k = at.registered[3]
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    saved = at.kfs[k].map_T_cam.copy()
    at.kfs[k].map_T_cam = saved @ flip          # looking up: every point behind the camera
    try:
        rep = build_report(at, ['test'])
    finally:
        at.kfs[k].map_T_cam = saved
    row = next(p for p in rep['per_image'] if p['image'] == at.kfs[k].name)
    assert row['reprojection_rms_px'] is None and 'behind the camera' in row['note']
    assert np.isfinite(rep['reprojection_rms_px'])
    write_report(rep, tmp_path)
    text = (tmp_path / 'report.json').read_text()
    assert 'NaN' not in text and 'Infinity' not in text
    json.loads(text)
    md = (tmp_path / 'report.md').read_text()
    assert ' inf ' not in md and '| inf' not in md and '| nan' not in md and 'behind the camera' in md
