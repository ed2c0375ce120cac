"""`--self-calibrate auto` refines f only where the block determines it: when the final adjustment's focal length
trades off with the cameras' height (core/at_report.py undetermined_focal), the block is adjusted again with f held at
its given value and the report says so; an f the user asked for and the block does not determine is a warning in the
verdict. A focal that moved little is held by adjusting the block again from where it is; one that ran far (beyond
FOCAL_READJUST_MAX of the given) by triangulating the block again. The decision is forced on the tiny survey to test
the paths it takes."""

from __future__ import annotations

import json

import pytest

from photogram_ros.cli import main
from photogram_ros.core.at_report import undetermined_focal
from photogram_ros.io import aerial_triangulation
from photogram_ros.sim.scenario import preset, simulate

FORCED = {'determined': False, 'reason': 'forced by the test', 'height_correlation': 0.999}


def test_nothing_to_hold_when_f_was_not_refined():
    assert undetermined_focal(None, ('k1', 'k2')) == {}


@pytest.fixture(scope='module')
def tiny_photos(tmp_path_factory):
    flight = tmp_path_factory.mktemp('focal') / 'flight'
    simulate(preset('tiny', photos=True), flight)
    return flight / 'photos'


def _triangulate(photos, out, *extra) -> tuple[int, dict]:
    rc = main(['triangulate', str(photos), '--gcp', str(photos / 'gcp_list.txt'), '--out', str(out),
               '--lever-arm=0,-0.05,-0.2', *extra])
    return rc, json.loads((out / 'report.json').read_text())


@pytest.mark.slow
@pytest.mark.parametrize('moved_far', [False, True], ids=['adjusted_again', 'triangulated_again'])
def test_auto_holds_an_undetermined_focal_and_says_so(tiny_photos, tmp_path, monkeypatch, capsys, moved_far):
    if moved_far:   # every refined focal counts as one that ran far
        monkeypatch.setattr(aerial_triangulation, 'FOCAL_READJUST_MAX', -1.0)
    calls, refined = [], []
    adjust = aerial_triangulation._triangulate_records

    def forced(at, refine):
        calls.append(tuple(refine))
        return dict(FORCED)

    def spy(block, opt, control, target_obs, refine, *args, **kwargs):
        refined.append(tuple(refine))
        return adjust(block, opt, control, target_obs, refine, *args, **kwargs)

    monkeypatch.setattr(aerial_triangulation, 'undetermined_focal', forced)
    monkeypatch.setattr(aerial_triangulation, '_triangulate_records', spy)
    rc, rep = _triangulate(tiny_photos, tmp_path / 'auto')
    assert len(calls) == 1 and 'f' in calls[0]   # asked once, of the adjustment that refined f
    said = capsys.readouterr()
    if moved_far:   # triangulated again, f held
        assert 'f' in refined[-2] and refined[-1] == tuple(r for r in refined[-2] if r != 'f')
        assert 'full adjustment with f held' not in said.out + said.err
    else:           # the same block adjusted again: no third triangulation
        assert 'f' in refined[-1] and len(refined) == 2   # GNSS-only (the control's check), then with the GCPs
        assert 'full adjustment with f held' in said.out + said.err
    held = [a for a in rep['assumptions'] if a.startswith('self-calibration (auto): f held at')]
    assert len(held) == 1 and 'forced by the test' in held[0]
    sc = rep['self_calibration']
    assert sc['fx']['after'] == pytest.approx(sc['fx']['before'], abs=1e-9)   # f fixed in the final adjustment
    assert rc == 0 and rep['verdict']['status'] != 'failed'


@pytest.mark.slow
def test_an_undetermined_focal_the_user_asked_for_is_a_warning(tiny_photos, tmp_path, monkeypatch):
    from photogram_ros.core import at_report
    monkeypatch.setattr(aerial_triangulation, 'focal_determination', lambda at, sig: dict(FORCED))
    monkeypatch.setattr(at_report, 'focal_determination', lambda at, sig: dict(FORCED))
    rc, rep = _triangulate(tiny_photos, tmp_path / 'asked', '--self-calibrate', 'f,k1,k2')
    found = [f for f in rep['verdict']['findings'] if f['check'] == 'self_calibration']
    assert len(found) == 1 and found[0]['status'] == 'warning' and 'forced by the test' in found[0]['text']
    assert rep['verdict']['status'] in ('warning', 'failed')
    assert not any(a.startswith('self-calibration (auto): f held') for a in rep['assumptions'])
