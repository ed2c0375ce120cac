"""io/split_merge_action.py split_merge_block on a synthetic block (no images): the sub-blocks' adjustments are
stood in for by a runner that returns each sub-block as its own adjustment would leave it (moved and bent: see
test_split_merge.py), then the merge, the global adjustment after it, the block check and the outputs run as in
`triangulate`. Also the merged block as the result when the global adjustment is off or fails, and a failed
sub-block named in the verdict after the global adjustment."""

import json

import numpy as np
import pytest

import photogram_ros.io.split_merge_action as atm
from photogram_ros.core.block_check import BlockInputs
from photogram_ros.core.split_merge import SplitMergeOptions, partition
from photogram_ros.errors import DataError
from photogram_ros.io.aerial_triangulation import TriangulateOptions
from photogram_ros.io.split_merge_action import SubBlockRun, split_merge_block
from photogram_ros.io.keyframe_block import KeyframeBlock
from test_split_merge import _deformed_sub_blocks, _moves, _observed_block

SPLIT = 32     # the 64-photo block in 2 sub-blocks
# Measured (this block, the sub-blocks moved by up to 5 cm / 0.5 mrad / 0.05 % and bent by 10 cm): camera centres
# against the truth, RMS, 0.0266 m after the global adjustment (as tests/test_split_merge.py's, which adjusts the
# same seed in core only). Gated at 1.5x.
CENTRE_RMS_M = 1.5 * 0.0266


class _StandIn:
    """A runner whose 'sub-blocks' job returns each sub-block as the synthetic adjustment leaves it."""
    workers, where = 1, ''

    def __init__(self, runs):
        self.runs = runs

    def run(self, fn, calls, what=None, log=None, keep=False, on_result=None, extra=None):
        assert what == 'sub-blocks' and len(list(calls)) == len(self.runs)
        return self.runs


def _runs(cam, C, X, truth, records, part, failed=()):
    subs = _deformed_sub_blocks(C, X, truth, part, _moves(part.n, rot_rad=0.0005, scale=0.0005, shift_m=0.05),
                                0.10, 0.005)
    runs = []
    by_name = {r.name: r for r in records}
    for sb in subs:
        if sb.index in failed:
            sb.status, sb.summary, sb.map_T_cam = 'failed', 'FAILED: its adjustment stopped: stand-in', {}
            runs.append(SubBlockRun(sb, {}, None, 1.0, 1.0))
            continue
        names = list(sb.names)
        T = np.array([sb.map_T_cam[n] for n in names])
        fix = np.array([T[i, :3, 3] for i in range(len(names))])
        inputs = BlockInputs(names, T, fix, np.tile([0.02, 0.03], (len(names), 1)), np.zeros(len(names)),
                             {}, {'status': 'converged'}, True, len(names))
        per_image = [{'image': n, 'observations': len(by_name[n].track_ids), 'reprojection_rms_px': 0.3,
                      'gnss_residual_enu_m': [0.0, 0.0, 0.0]} for n in names]
        rep = {'per_image': per_image, 'check': {'points': [], 'rmse': {}}, 'adjustment_status': 'converged',
               'camera': {'fx': cam.fx}}
        runs.append(SubBlockRun(sb, rep, inputs, 1.0, 1.0, cam))
    return runs


@pytest.fixture
def block():
    cam, origin, C, X, truth, records = _observed_block()
    kb = KeyframeBlock(cam, origin, records, [], len(records), None, False, {}, [], True, {})
    return kb, cam, C, X, truth, partition(C, SplitMergeOptions(split_photos=SPLIT))


def _adjust(block, tmp_path, failed=(), selections=None, **sm):
    """selections: each sub-block's self_calibration_selection in its report (the camera is then one from the
    EXIF, whose intrinsics `auto` self-calibrates)."""
    kb, cam, C, X, truth, part = block
    opt = TriangulateOptions(split=SplitMergeOptions(split_photos=SPLIT, **sm))
    runs = _runs(cam, C, X, truth, kb.records, part, failed)
    if selections is not None:
        kb.camera_from_exif = True
        for r, sel in zip(runs, selections):
            if sel is not None:
                r.report['self_calibration_selection'] = sel
    return split_merge_block(kb, tmp_path, opt, _StandIn(runs), None)


def test_the_global_adjustment_after_the_merge_recovers_the_truth(block, tmp_path, monkeypatch):
    truth = block[4]
    poses = {}
    real = atm._global_adjustment

    def keep(*a, **k):      # the adjusted IncrementalAT, to compare its cameras with the truth
        out = real(*a, **k)
        poses.update({out['at'].kfs[i].name: out['at'].kfs[i].map_T_cam for i in out['at'].registered})
        return out
    monkeypatch.setattr(atm, '_global_adjustment', keep)
    res = _adjust(block, tmp_path)
    rep = json.loads((tmp_path / 'report.json').read_text())
    g = rep['split_merge']['global_adjustment']
    assert g['status'] == 'converged' and g['solves'] >= 1 and g['seed']['oriented'] == len(truth)
    assert g['refine'] == [] and g['refine_chosen_by'] == 'none'   # a calibrated camera: nothing to refine
    assert res.registered == len(truth) == rep['registered']
    d = np.array([poses[n][:3, 3] - truth[n][:3, 3] for n in truth])
    rms = float(np.sqrt(np.mean(np.sum(d ** 2, axis=1))))
    print(f'camera centres against the truth after the global adjustment: {rms:.4f} m RMS; moved '
          f'{g["camera_moves"]["centre_rms_m"]:.4f} m from the merged block')
    assert rms <= CENTRE_RMS_M
    assert g['camera_moves']['centre_rms_m'] > 5 * rms      # it undid what the merge could not
    assert rep['verdict']['figures']['split_merge']['global_adjustment'] == 'converged'
    assert rep['timing_s']['global_adjustment'] > 0
    assert any('global adjustment of the whole block' in a for a in rep['assumptions'])
    assert (tmp_path / 'poses.csv').read_text().count('\n') == len(truth) + 1


def test_without_the_global_adjustment_the_merged_block_is_the_result(block, tmp_path):
    res = _adjust(block, tmp_path, global_adjustment=False)
    rep = res.report
    assert 'global_adjustment' not in rep['split_merge']
    assert rep['verdict']['figures']['split_merge']['global_adjustment'] == 'off'
    assert res.registered == 64
    assert any('no global adjustment after the merge (split.global_adjustment off)' in a for a in rep['assumptions'])


def test_a_global_adjustment_that_fails_is_named_and_the_merged_block_kept(block, tmp_path, monkeypatch):
    def fails(*a, **k):
        raise DataError('stand-in failure')
    monkeypatch.setattr(atm, '_global_adjustment', fails)
    res = _adjust(block, tmp_path)
    texts = [f['text'] for f in res.verdict['findings']]
    assert any('global adjustment after the merge did not finish (it stopped: stand-in failure)' in t for t in texts)
    assert res.verdict['status'] in ('warning', 'failed')
    assert res.report['verdict']['figures']['split_merge']['global_adjustment'] == 'failed'
    assert res.registered == 64


def test_a_failed_sub_block_is_named_after_the_global_adjustment(block, tmp_path):
    part = block[5]
    res = _adjust(block, tmp_path, failed=(1,))
    rep = res.report
    assert rep['split_merge']['left_out'] == [1]
    assert res.verdict['status'] == 'failed'
    assert any('sub-block 1 left out of the merge' in f['text'] for f in res.verdict['findings'])
    # The global adjustment ran on what the other sub-block oriented: its photos only.
    assert rep['split_merge']['global_adjustment']['seed']['oriented'] == len(part.members[0]) == res.registered


def _stepwise(*kept):
    return {'method': 'stepwise', 'candidates': ['k1', 'k2'], 'kept': list(kept)}


def test_the_global_adjustment_holds_the_distortion_the_sub_blocks_chose(block, tmp_path, monkeypatch):
    """Every sub-block selected its self-calibration stepwise: the global adjustment refines the base terms and
    holds the distortion at the sub-blocks' mean camera, with no trials of its own."""
    from photogram_ros.core.at_problem import BlockAdjustment

    def no_trials(*a, **k):
        raise AssertionError('the global adjustment ran a stepwise selection of its own')
    monkeypatch.setattr(BlockAdjustment, 'select_self_calibration', no_trials)
    res = _adjust(block, tmp_path, selections=[_stepwise('k1'), _stepwise()])
    g = res.report['split_merge']['global_adjustment']
    assert g['refine_chosen_by'] == 'sub_blocks' and not {'k1', 'k2'} & set(g['refine'])
    assert g['status'] == 'converged'
    assert any('distortion held at the sub-blocks\' photo-weighted mean' in a and 'sub-block 0 kept k1' in a
               and 'sub-block 1 kept none' in a for a in res.report['assumptions'])


def test_without_every_sub_blocks_selection_the_global_adjustment_selects_its_own(block, tmp_path):
    res = _adjust(block, tmp_path, selections=[_stepwise('k1'), None])
    g = res.report['split_merge']['global_adjustment']
    assert g['refine_chosen_by'] == 'stepwise'
    assert res.report['self_calibration_selection']['method'] == 'stepwise'


def test_sub_blocks_selection_refines_the_base_terms_only():
    from types import SimpleNamespace
    from photogram_ros.io.split_merge_action import sub_blocks_selection

    def runs(*sels):
        return [SimpleNamespace(report={} if s is None else {'self_calibration_selection': s}) for s in sels]
    cands = ('f', 'k1', 'k2', 'cx', 'cy')
    assert sub_blocks_selection(runs(_stepwise('f', 'k1'), _stepwise('f', 'k2')), cands) == ('f', 'cx', 'cy')
    assert sub_blocks_selection(runs(_stepwise(), _stepwise()), ('k1', 'k2')) == ()
    assert sub_blocks_selection(runs(_stepwise('k1'), None), cands) is None
    assert sub_blocks_selection(runs({'method': 'given', 'kept': ['k1']}), cands) is None
