"""bench/block_verdicts.py: its broken blocks (tipped, folded, geotags scattered) and the must-show of issue 44 on
its result file (bench/results/block_verdicts_*.jsonl): no FAILED for a block whose shape agrees with its
reference within 2 %, FAILED for every tipped or folded block."""

import json

import numpy as np

from bench import block_verdicts as bv
from figures import RESULTS
from photogram_ros.core.block_check import BlockInputs, check_block, tilt_from_nadir_deg


def _block(strips=5, per=6):
    """A nadir block of `strips` east-west strips flown back and forth (flight order), 50 m over flat ground."""
    C = []
    for k in range(strips):
        xs = np.arange(per) * 20.0
        C += [[x, k * 30.0, 50.0] for x in (xs if k % 2 == 0 else xs[::-1])]
    C = np.array(C)
    n = len(C)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:, :3, 3] = C
    tie = {'reprojection_px': 0.5, 'ray_angle_deg': {'median': 20.0, 'p10': 8.0, 'points': 500},
           'component': [0] * n, 'parts': 1}
    return BlockInputs([f'P{i:02d}.JPG' for i in range(n)], T, C.copy(), np.tile([5.0, 2.0], (n, 1)), np.zeros(n),
                       gnss_noise={'stated_h_m': 5.0, 'stated_v_m': 2.0, 'estimated_h_m': 0.5, 'estimated_v_m': 0.5,
                                   'used_h_m': 0.5, 'used_v_m': 0.5, 'n': n, 'rejected': []}, tie=tie)


def test_the_bench_breaks_a_good_block_so_the_check_fails_it():
    b = _block()
    assert check_block(b).status == 'ok'
    folded, turned = bv.folded(b, 30.0)
    # The last strip (a third of five, at least one) turned 30 degrees with the ground it sees.
    assert turned == b.names[-6:]
    assert np.allclose(tilt_from_nadir_deg(folded.map_T_cam[-6:]), 30.0) and np.allclose(folded.ground_z_m[:-6], 0.0)
    v = check_block(folded)
    assert v.status == 'failed' and 'strips' in v.decided_by, v.summary
    for deg in (30.0, 85.0):
        t = bv.tipped(b, deg)
        assert np.allclose(tilt_from_nadir_deg(t.map_T_cam), deg)
        v = check_block(t)
        assert v.status == 'failed', v.summary
    far = bv.far_geotags(b)
    assert np.std(far.fix_enu_m[:, :2] - b.fix_enu_m[:, :2]) > 10.0
    assert check_block(far).status != 'failed' and check_block(bv.folded(far)[0]).status == 'failed'


def test_shape_agreement_is_a_share_of_the_block_after_a_similarity():
    rng = np.random.default_rng(0)
    ref = rng.uniform(-100, 100, (20, 3))
    R = bv._rot([0.3, 0.2, 1.0], 40.0)
    est = 0.5 * ref @ R.T + 7.0
    s = bv.shape_of(est, ref)
    assert s['shape_rms_m'] < 1e-9 and s['block_size_m'] > 100.0
    noisy = ref + rng.normal(0, 1.0, ref.shape)
    s = bv.shape_of(noisy, ref)
    assert 0.005 < s['shape_share'] < 0.02


def test_holds_is_the_must_show():
    assert bv.holds({'kind': 'folded', 'verdict': {'status': 'failed'}}) is True
    assert bv.holds({'kind': 'tipped', 'verdict': {'status': 'warning'}}) is False
    assert bv.holds({'kind': 'triangulate', 'shape_share': 0.018, 'verdict': {'status': 'failed'}}) is False
    assert bv.holds({'kind': 'triangulate', 'shape_share': 0.018, 'verdict': {'status': 'warning'}}) is True
    assert bv.holds({'kind': 'triangulate', 'shape_share': 0.05, 'verdict': {'status': 'failed'}}) is None


RESULT = 'block_verdicts_dcf2d59.jsonl'   # bench/results: bench/block_verdicts.py on the real sets


def test_the_result_file_holds_the_must_show_on_every_real_set_and_variant():
    path = RESULTS / RESULT
    rows = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    assert {r['set'] for r in rows} >= {'brighton', 'toledo'}, path.name
    broken = [r for r in rows if r['kind'] in ('tipped', 'folded')]
    assert broken and all(r['verdict']['status'] == 'failed' for r in broken), path.name
    agree = [r for r in rows if r['kind'] == 'triangulate' and (r.get('shape_share') or 1.0) <= bv.AGREE_SHARE]
    assert agree and all(r['verdict']['status'] != 'failed' for r in agree), path.name
    assert not [r for r in rows if r['holds'] is False], path.name
