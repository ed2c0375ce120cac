"""`triangulate PHOTOS` with split-merge (io/split_merge_action.py split_merge_block): the merged block
against the single block of the same simulated survey, in this process and on a `dask scheduler` + 2
`dask worker` processes started here on 127.0.0.1."""

import json

import pytest

from photogram_ros.cli import main
from photogram_ros.core.split_merge import SplitMergeOptions
from photogram_ros.errors import ConfigError
from photogram_ros.io.aerial_triangulation import TriangulateOptions
from photogram_ros.io.triangulate_action import triangulate
from photogram_ros.params import from_dict
from photogram_ros.sim.scenario import preset, simulate
from test_photo_dask import scheduler_and_two_workers

SPLIT = 30          # photos per sub-block's core: the survey below (40 photos) splits in 2
LEVER = (0.0, -0.05, -0.2)
# Measured on this survey by bench/split_merge_small.py (bench/results/split_merge_small_55acd7a.jsonl; the
# simulation is not the same to the bit from machine to machine): check-point RMSE split in 2 sub-blocks (24, 24
# photos) and adjusted globally after the merge 1.31 / 1.06 cm (H / V; the merged block before it 2.88 / 4.95 cm),
# the single block 1.04 / 1.17 cm; the shared cameras 13.5 cm RMS apart before and 6.67 cm after the merge's
# similarities (the sub-blocks each on their own geotags and GCPs); the global adjustment (8 solves, 31 iterations)
# moved the cameras 9.81 cm RMS. Gated at 1.5x those figures, and the ratios to the single block at the 10 % the
# issue asks (horizontally the split block measured 1.25x the single block's).
CHECK_SPLIT_M = {'horizontal_m': 1.5 * 0.0131, 'vertical_m': 1.5 * 0.0106}
CHECK_RATIO = {'horizontal_m': 1.1, 'vertical_m': 1.1}
OVERLAP_RMS_M = 1.5 * 0.0667
GLOBAL_MOVED_RMS_M = 1.5 * 0.0981


@pytest.fixture(scope='module')
def survey(tmp_path_factory):
    """A small simulated photo survey: 2 lines of 140 m, 40 photos, 5 GCPs and 4 check points (the recipe of
    bench/photo_triangulation_scale.py)."""
    flight = tmp_path_factory.mktemp('split') / 'flight'
    simulate(preset('survey', photos=True, fps=0.65, n_lines=2, line_length_m=140.0), flight)
    return flight / 'photos'


@pytest.fixture(scope='module')
def single(survey, tmp_path_factory):
    return triangulate(survey, tmp_path_factory.mktemp('single'),
                       TriangulateOptions(gcp=str(survey / 'gcp_list.txt'), lever_arm_cam_m=LEVER, split=None),
                       progress=False)


@pytest.fixture(scope='module')
def split_here(survey, tmp_path_factory):
    lines = []
    res = triangulate(survey, tmp_path_factory.mktemp('split_here'),
                      TriangulateOptions(gcp=str(survey / 'gcp_list.txt'), lever_arm_cam_m=LEVER,
                                         split=SplitMergeOptions(split_photos=SPLIT)), log=lines.append)
    return res, lines


def test_split_options_are_validated(tmp_path, capsys):
    assert main(['triangulate', str(tmp_path), '--out', str(tmp_path / 'o'), '--split-photos', '3']) == 2
    assert "'split_photos' = 3 is outside" in capsys.readouterr().err
    with pytest.raises(ConfigError, match='overlap_m'):
        from_dict(SplitMergeOptions, {'overlap_m': -1.0})


@pytest.mark.slow
def test_split_merge_check_points_match_the_single_block(split_here, single):
    res, lines = split_here
    rep, out = res.report, res.out
    sm = rep['split_merge']
    ck, ck1 = rep['check']['rmse'], single.report['check']['rmse']
    g = sm['global_adjustment']
    print('check RMSE split / single:', {k: (ck.get(k), ck1.get(k)) for k in ('n', 'horizontal_m', 'vertical_m')},
          'overlaps:', sm['overlaps'])
    print('global adjustment:', {k: g[k] for k in ('status', 'solves', 'iterations', 'wall_s')}, g['camera_moves'],
          'merged block\'s check RMSE:', sm['merged_check_rmse'])
    assert len(sm['sub_blocks']) == 2 and not sm['left_out']
    assert all((out / 'sub_blocks' / f'{k:02d}' / 'report.json').exists() for k in range(2))
    # Every photo oriented, each once; the overlap agrees after the merge's similarities.
    assert res.registered == res.inputs == single.inputs
    assert sm['overlaps'] and all(o['camera_rms_m'] < OVERLAP_RMS_M for o in sm['overlaps'])
    assert any('adjustment of the sub-blocks: 2/2 sub-blocks' in s for s in lines)
    assert ck['n'] == ck1['n'] == 4
    for k in ('horizontal_m', 'vertical_m'):
        assert ck[k] <= CHECK_SPLIT_M[k], (k, ck[k], ck1[k])
    # The global adjustment ran after the merge: converged, moved the cameras by centimetres, and its check
    # points are better than the merged block's horizontally.
    assert g['status'] in ('converged', 'max_iterations') and g['solves'] >= 1 and g['iterations'] >= 1
    assert g['seed']['oriented'] == res.registered
    assert 0 < g['camera_moves']['centre_rms_m'] <= GLOBAL_MOVED_RMS_M
    assert ck['horizontal_m'] < sm['merged_check_rmse']['horizontal_m']
    assert rep['timing_s']['global_adjustment'] > 0
    assert res.verdict['status'] != 'failed'
    assert res.verdict['figures']['split_merge']['global_adjustment'] == g['status']
    assert (out / 'poses.csv').read_text().count('\n') == res.registered + 1
    assert json.loads((out / 'report.json').read_text())['check']['rmse'] == ck
    # The split block's check points within 10 % of the single block's (last: every gate above is checked first).
    for k in ('horizontal_m', 'vertical_m'):
        assert ck[k] <= CHECK_RATIO[k] * ck1[k], (k, ck[k], ck1[k])


@pytest.mark.slow
def test_split_merge_on_a_scheduler_and_two_workers_matches_in_process(survey, split_here, tmp_path):
    with scheduler_and_two_workers(tmp_path) as address:
        out = tmp_path / 'cluster'
        rc = main(['triangulate', str(survey), '--gcp', str(survey / 'gcp_list.txt'), '--out', str(out),
                   '--lever-arm=0,-0.05,-0.2', '--split-photos', str(SPLIT), '--quiet', '--scheduler', address])
    assert rc in (0, 4)
    here, there = split_here[0].report, json.loads((out / 'report.json').read_text())
    assert len(there['split_merge']['sub_blocks']) == 2
    assert there['registered'] == here['registered']
    assert there['check']['rmse']['n'] == here['check']['rmse']['n'] == 4
    for k in ('horizontal_m', 'vertical_m'):
        assert there['check']['rmse'][k] == pytest.approx(here['check']['rmse'][k], rel=1e-3, abs=1e-4)
    assert there['verdict']['status'] == here['verdict']['status']
    # The cluster's run self-calibrates the same camera as this process.
    for k in ('fx', 'cx', 'cy', 'k1', 'k2'):
        assert there['self_calibration'][k]['after'] == pytest.approx(here['self_calibration'][k]['after'],
                                                                      rel=1e-6, abs=1e-9)
