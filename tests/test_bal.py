"""Real BAL problems: read (plain and .bz2) and solve to within 1 % of Ceres's final cost."""

from __future__ import annotations

import bz2

import numpy as np
import pytest
from conftest import shared_data

from photogram_ros.core.bundle import BundleOptions, bundle_adjust
from photogram_ros.io.bal import read_bal
from photogram_ros.errors import DataError

# Ceres (pycolmap, SPARSE_SCHUR) final 0.5 * sum r^2 from ../shared/data/README.md.
CERES_COST = {'problem-49-7776-pre.txt': 1.3692e4, 'problem-21-11315-pre.txt': 3.0379e4}
OPTS = BundleOptions(loss='linear', refine_intrinsics=('f', 'k1', 'k2'), max_iterations=100,
                     function_tolerance=1e-4)


def test_reader_plain_and_bz2_agree(tmp_path):
    src = shared_data('bal', 'problem-49-7776-pre.txt')
    b = read_bal(src)
    assert (len(b.cam_t), len(b.points), len(b.obs_cam)) == (49, 7776, 31843)
    assert b.obs_uv[0] == pytest.approx([-332.65, 262.09])
    zipped = tmp_path / 'p.txt.bz2'
    zipped.write_bytes(bz2.compress(src.read_bytes()))
    z = read_bal(zipped)
    assert np.array_equal(z.points, b.points) and np.array_equal(z.obs_pt, b.obs_pt)
    # map_T_cams inverts the BAL (R, t): the camera centre maps to the camera origin.
    c = b.map_T_cams[5]
    assert np.allclose(b.cam_R[5] @ c[:3, 3] + b.cam_t[5], 0, atol=1e-9)
    trunc = tmp_path / 'cut.txt'
    trunc.write_text(''.join(src.read_text().splitlines(keepends=True)[:40000]))
    with pytest.raises(DataError):
        read_bal(trunc)


@pytest.mark.parametrize('name', sorted(CERES_COST))
def test_bal_reaches_ceres_cost(name):
    b = read_bal(shared_data('bal', name))
    res = bundle_adjust(b.problem(), OPTS)
    assert res.status == 'converged', res.reason
    # Our cost counts every observation, also the ones behind a camera that COLMAP skips.
    assert res.final_cost <= 1.01 * CERES_COST[name], res.final_cost
    assert res.iterations <= 30
    assert res.rms['reprojection_px'] == pytest.approx(np.sqrt(2 * res.final_cost / len(b.obs_cam)), rel=1e-9)


# Our solver's speed as a ratio to SciPy's least_squares measured in the same run (bench/bundle_bal.py
# --peers): gated at the result file's ratio / 1.5.
BAL_RESULT = 'bundle_bal*.jsonl'   # the newest result file of the bench, as the table renders it


@pytest.mark.slow
def test_bal_speed_against_scipy_in_the_same_run():
    import sys

    from conftest import ROOT
    from figures import newest_figure
    sys.path.insert(0, str(ROOT / 'bench'))
    from bench import bundle_bal as bb
    name = 'problem-49-7776-pre.txt'
    b = read_bal(shared_data('bal', name))
    ours, scipy = bb.run_ours(b, 1e-4), bb.run_scipy(b, 1e-4)
    ratio = scipy['seconds'] / ours['seconds']
    bal_result, m = newest_figure(BAL_RESULT, problem=name, solver='scipy_least_squares_trf')
    print(f'{name}: ours {ours["seconds"]:.2f} s, SciPy {scipy["seconds"]:.2f} s: {ratio:.1f}x '
          f'(measured {m["time_ratio_peer_over_ours"]:.1f}x, {bal_result})')
    assert ratio >= m['time_ratio_peer_over_ours'] / 1.5
    assert ours['final_cost'] <= 1.5 * m['cost_ratio_ours_over_peer'] * scipy['final_cost']
