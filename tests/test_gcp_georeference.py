"""A block without GNSS placed by its GCPs alone: photos without geotags (or a GNSS that never came)
and 3 or more surveyed targets. Checked against the simulator's truth (check points, camera centres);
a block with too few GCPs is said to be in no map frame rather than judged as if it were."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from photogram_ros.core.block_check import BlockInputs, check_block, inputs_from_at
from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions
from photogram_ros.core.at_report import build_report
from photogram_ros.io.at_report import verdict_lines
from photogram_ros.sim.observations import simulate_keyframes
from test_incremental import _rmse_hv, world  # noqa: F401  (a fixture)


def _without_fixes(cfg, w, control_names=None):
    sk = simulate_keyframes(dataclasses.replace(cfg, seed=7), gnss_mode='rtk_fixed', world=w)
    control = [c for c in sk.control if control_names is None or c.name in control_names or c.role != 'gcp']
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m)),
                       origin=sk.origin, control=control)
    for r in sk.records:
        at.add_keyframe(dataclasses.replace(r, fix=None))
    rep = at.full_adjustment()
    return sk, at, rep


def _check_errors(sk, at):
    """(n, 3) adjusted minus surveyed position of the check points the report finds in the block, map m."""
    rep = build_report(at, gsd_m=sk.gsd_m)
    return np.array([p['residual_m'] for p in rep['check']['points'] if p['name'].startswith('CHK')])


def test_five_gcps_place_a_block_without_any_fix(world):  # noqa: F811
    cfg, w = world
    sk, at, rep = _without_fixes(cfg, w)
    assert len(at.registered) == len(sk.records) and at.georeferenced and not at.georef_provisional
    assert at.gcps_in_block() == 5
    chk = _check_errors(sk, at)
    h, v = _rmse_hv(chk)
    cam = np.array([at.kfs[k].map_T_cam[:3, 3] - sk.true_map_T_cam[k][:3, 3] for k in at.registered])
    cam_rmse = float(np.sqrt(np.mean(np.sum(cam ** 2, axis=1))))
    print(f'no fix, 5 GCPs: {len(chk)} check points RMSE h {h * 100:.2f} cm v {v * 100:.2f} cm '
          f'({h / sk.gsd_m:.2f} / {v / sk.gsd_m:.2f} GSD); camera centres {cam_rmse * 100:.2f} cm')
    assert len(chk) == 4
    assert h <= 1.5 * 0.0139 and v <= 1.5 * 0.0127             # measured 1.39 / 1.27 cm
    assert cam_rmse <= 1.5 * 0.0238                             # measured 2.38 cm
    verdict = check_block(inputs_from_at(at, adjustment={'status': rep.status}))
    assert not any(f.check in ('georeference', 'ground_below', 'nadir') for f in verdict.findings), verdict.findings
    assert verdict.figures['georeference'] == {'georeferenced': True, 'cameras_with_fix': 0, 'gcps_in_block': 5}
    assert verdict.figures['nadir']['share_within_deg'] == 1.0


def test_two_gcps_leave_the_block_unplaced_and_the_check_says_so(world):  # noqa: F811
    cfg, w = world
    two = sorted(c.name for c in simulate_keyframes(dataclasses.replace(cfg, seed=7), gnss_mode='rtk_fixed',
                                                    world=w).control if c.role == 'gcp')[:2]
    sk, at, rep = _without_fixes(cfg, w, two)
    assert len(at.registered) == len(sk.records) and not at.georeferenced
    verdict = check_block(inputs_from_at(at, adjustment={'status': rep.status}))
    found = {f.check: f for f in verdict.findings}
    assert verdict.status == 'failed' and found['georeference'].status == 'failed'
    assert 'not georeferenced: 0 of' in found['georeference'].text and '2 GCPs' in found['georeference'].text
    # An arbitrary frame has no up: the checks that need it are not judged (no "tipped over").
    assert 'ground_below' not in found and 'nadir' not in found
    assert verdict.figures['nadir']['note'].startswith('not judged')
    lines = verdict_lines({'verdict': verdict.to_dict()})
    assert lines[0] == '**Verdict: FAILED**' and any('nadir: not judged' in x for x in lines)


@pytest.mark.parametrize('placed', [True, False, None])
def test_the_georeference_check_on_hand_made_inputs(placed):
    """A level block looking down: failed only when it is known not to be placed."""
    n = 6
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = np.diag([1.0, -1.0, -1.0])              # optical axis straight down
    T[:, 0, 3] = np.arange(n) * 10.0
    T[:, 2, 3] = 100.0
    b = BlockInputs([f'p{i}' for i in range(n)], T, np.full((n, 3), np.nan), np.full((n, 2), np.nan),
                    np.zeros(n), georeferenced=placed, gcps_in_block=1)
    v = check_block(b)
    assert (v.status == 'failed') == (placed is False)
    assert any(f.check == 'georeference' for f in v.findings) == (placed is False)
    assert ('share_within_deg' in v.figures['nadir']) == (placed is not False)
    assert ('share' in v.figures['ground_below']) == (placed is not False)
