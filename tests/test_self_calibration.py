"""Stepwise self-calibration (core/self_calibration.py): a candidate intrinsic is kept only when it pays in
reprojection; on simulated keyframes the final adjustment ("auto") finds a lens's k1 and leaves out a k1 the
lens does not have."""

import dataclasses

import numpy as np
import pytest

from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions
from photogram_ros.core.self_calibration import Trial, height_bowl, select_stepwise
from photogram_ros.errors import ConfigError
from photogram_ros.sim.observations import simulate_keyframes
from photogram_ros.sim.scenario import build_world, preset


def _table(rms: dict):
    """evaluate() from a table {refined intrinsics (sorted): reprojection RMS px}; counts its calls."""
    calls = []

    def evaluate(refine):
        calls.append(tuple(refine))
        return Trial(tuple(refine), rms[tuple(sorted(refine))])
    return evaluate, calls


def test_brighton_like_gains_keep_k2_and_leave_k1_out():
    # bench/notes_dsm_shape.md, brighton triangulate: none 0.695, k1 0.6946, k2 0.6330, both 0.6306 px.
    evaluate, calls = _table({(): 0.695, ('k1',): 0.6946, ('k2',): 0.6330, ('k1', 'k2'): 0.6306})
    sel = select_stepwise(('k1', 'k2'), evaluate)
    assert sel.kept == ('k2',)
    d = {x.name: x for x in sel.decisions}
    assert d['k2'].kept and d['k2'].gain_px == pytest.approx(0.062)
    assert not d['k1'].kept and d['k1'].gain_px == pytest.approx(0.0024) and 'threshold' in d['k1'].reason
    assert calls == [(), ('k1',), ('k2',), ('k2', 'k1')]
    text = sel.text()
    assert 'kept k2' in text and 'k1 left out' in text and '0.0024 px' in text
    assert sel.to_dict()['kept'] == ['k2'] and len(sel.to_dict()['trials']) == 4


def test_a_lens_with_k1_keeps_both():
    evaluate, _ = _table({(): 2.4, ('k1',): 0.62, ('k2',): 1.3, ('k1', 'k2'): 0.35})
    sel = select_stepwise(('k1', 'k2'), evaluate)
    assert sel.kept == ('k1', 'k2')
    assert all(d.kept for d in sel.decisions)


def test_undetermined_or_failed_parameters_are_left_out():
    def evaluate(refine):
        # f pays most but moves by 2 px at a sigma of 1 px; a correlation with the height alone is not used.
        sig = {'f': 1.0, 'k1': 0.001} if refine else {}
        moved = {n: {'f': 2.0, 'k1': -0.08}[n] for n in refine}
        return Trial(tuple(refine), 1.0 - 0.2 * ('f' in refine) - 0.1 * ('k1' in refine), moved=moved, sigmas=sig,
                     height_correlation={'k1': -0.95} if 'k1' in refine else {})
    sel = select_stepwise(('f', 'k1'), evaluate)
    assert sel.kept == ()
    assert 'not determined' in sel.decisions[0].reason
    sel = select_stepwise(('k1',), evaluate)
    assert sel.kept == ('k1',)
    with pytest.raises(ConfigError):
        select_stepwise(('k9',), evaluate)
    with pytest.raises(ConfigError):
        select_stepwise(('k1',), evaluate, min_gain_fraction=-1.0)
    # base is always refined, candidates come after it
    sel = select_stepwise(('k1',), evaluate, base=('f',))
    assert sel.kept == ('f', 'k1') and sel.trials[0].refine == ('f',)
    assert 'stepwise from k1; f refined throughout' in sel.text() and 'with f refined' in sel.text()
    with pytest.raises(ConfigError):
        select_stepwise(('k1',), evaluate, min_sigmas=-1.0)


def test_the_covariance_is_asked_only_of_a_candidate_that_pays():
    evaluate, _ = _table({(): 0.695, ('k1',): 0.6946, ('k2',): 0.6330, ('k1', 'k2'): 0.6306})
    asked = []

    def determine(trial):
        asked.append(trial.refine)
        trial.height_correlation = {n: 0.2 for n in trial.refine}
        trial.sigmas = {n: 0.001 for n in trial.refine}
    sel = select_stepwise(('k1', 'k2'), evaluate, determine=determine)
    assert asked == [('k2',)] and sel.kept == ('k2',)
    assert sel.to_dict()['trials'][2]['height_correlation'] == {'k2': 0.2}


def test_height_bowl_measures_a_dome_against_scatter():
    rng = np.random.default_rng(1)
    E, N = np.meshgrid(np.linspace(-40, 40, 9), [-20.0, 0.0, 20.0])
    xy = np.column_stack([E.ravel(), N.ravel()])
    r2 = np.sum(xy ** 2, axis=1)
    dz = 3.0 + 0.01 * xy[:, 0] - 0.5 * r2 / r2.max() + rng.normal(0, 0.03, len(r2))
    b = height_bowl(xy, dz)
    assert b['radius_m'] == pytest.approx(np.sqrt(r2.max()))
    assert b['rise_m'] == pytest.approx(-0.5, abs=0.06)
    assert 0.015 < b['scatter_m'] < 0.06
    assert height_bowl(xy[:5], dz[:5]) == {'n': 5}


@pytest.fixture(scope='module')
def tiny():
    cfg = preset('tiny', n_gcp=0, n_check=0)
    return cfg, build_world(cfg, np.random.default_rng(cfg.seed))


def _auto(tiny, dist):
    """The final adjustment ("auto") of the tiny flight seen through a lens `dist`, from an EXIF-like camera
    (the true one without distortion)."""
    cfg, world = tiny
    sk = simulate_keyframes(dataclasses.replace(cfg, dist=dist), gnss_mode='rtk_fixed', world=world)
    cam0 = dataclasses.replace(sk.camera, dist=(0.0, 0.0, 0.0, 0.0, 0.0))
    at = IncrementalAT(cam0, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m),
                                                final_self_calibration='auto'), origin=sk.origin)
    for r in sk.records:
        at.add_keyframe(r)
    rep = at.full_adjustment()
    return at, rep


def test_auto_finds_the_simulated_lens(tiny):
    at, rep = _auto(tiny, (-0.12, 0.05, 0.0, 0.0, 0.0))
    sel = at.self_calibration
    print(sel.text())
    assert set(sel.kept) == {'k1', 'k2'}
    assert at.camera.dist[0] == pytest.approx(-0.12, abs=0.01)
    assert rep.reprojection_rms_px < 0.5


def test_auto_leaves_out_a_k1_the_lens_has_not(tiny):
    at, rep = _auto(tiny, (0.0, 0.05, 0.0, 0.0, 0.0))
    sel = at.self_calibration
    print(sel.text())
    assert sel.kept == ('k2',)
    assert at.camera.dist[0] == 0.0 and at.camera.dist[1] == pytest.approx(0.05, abs=0.01)
