"""`triangulate PHOTOS` with split-merge (io/aerial_triangulation.py split_merge_block): the merged block
against the single block of the same simulated survey, in this process and on a `dask scheduler` + 2
`dask worker` processes started here on 127.0.0.1."""

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import ROOT
from photogram_ros.cli import main
from photogram_ros.core.split_merge import SplitMergeOptions
from photogram_ros.errors import ConfigError
from photogram_ros.io.aerial_triangulation import TriangulateOptions, triangulate
from photogram_ros.sim.scenario import preset, simulate

SPLIT = 20          # photos per sub-block's core: the survey below splits in 2
LEVER = (0.0, -0.05, -0.2)


@pytest.fixture(scope='module')
def survey(tmp_path_factory):
    """A small simulated photo survey: 2 lines of 80 m, about 40 photos, 4 GCPs and 2 check points."""
    flight = tmp_path_factory.mktemp('split') / 'flight'
    simulate(preset('tiny', photos=True, line_length_m=80.0), flight)
    return flight / 'photos'


@pytest.fixture(scope='module')
def single(survey, tmp_path_factory):
    out = tmp_path_factory.mktemp('single')
    return triangulate(survey, out, TriangulateOptions(gcp=str(survey / 'gcp_list.txt'), lever_arm_cam_m=LEVER,
                                                       split=None), progress=False)


def test_split_options_are_validated(tmp_path, capsys):
    assert main(['triangulate', str(tmp_path), '--out', str(tmp_path / 'o'), '--split-photos', '3']) == 2
    assert "'split_photos' = 3 is outside" in capsys.readouterr().err
    with pytest.raises(ConfigError, match='overlap_m'):
        from photogram_ros.params import from_dict
        from_dict(SplitMergeOptions, {'overlap_m': -1.0})


@pytest.mark.slow
def test_split_merge_check_points_match_the_single_block(survey, single, tmp_path):
    lines = []
    res = triangulate(survey, tmp_path, TriangulateOptions(gcp=str(survey / 'gcp_list.txt'), lever_arm_cam_m=LEVER,
                                                           split=SplitMergeOptions(split_photos=SPLIT)),
                      log=lines.append)
    rep = res.report
    sm = rep['split_merge']
    assert len(sm['sub_blocks']) == 2 and not sm['left_out']
    assert all((tmp_path / 'sub_blocks' / f'{k:02d}' / 'report.json').exists() for k in range(2))
    # Every photo oriented once, each from the sub-block whose core it is in; the overlap agrees.
    assert res.registered == res.inputs == single.inputs
    assert sm['overlaps'] and all(o['camera_rms_m'] < 0.05 for o in sm['overlaps'])
    assert any('adjustment of the sub-blocks: 2/2 sub-blocks' in s for s in lines)
    ck, ck1 = rep['check']['rmse'], single.report['check']['rmse']
    assert ck['n'] == ck1['n'] == 2
    for k in ('horizontal_m', 'vertical_m'):
        # Within 10 % of the single block (or 1 cm, the noise of two check points on a tiny block).
        assert ck[k] <= max(1.1 * ck1[k], ck1[k] + 0.01), (k, ck[k], ck1[k])
    assert res.verdict['status'] != 'failed'
    assert 'split_merge' in res.verdict['figures']
    assert (tmp_path / 'poses.csv').read_text().count('\n') == res.registered + 1
    assert json.loads((tmp_path / 'report.json').read_text())['check']['rmse'] == ck


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_split_merge_on_a_scheduler_and_two_workers_matches_in_process(survey, tmp_path):
    dask = shutil.which('dask', path=str(Path(sys.executable).parent))
    assert dask, 'the dask command of dask[distributed] is not installed beside this Python'
    address = f'tcp://127.0.0.1:{_free_port()}'
    env = {**os.environ, 'PYTHONPATH': str(ROOT)}
    procs = [subprocess.Popen([dask, 'scheduler', '--host', '127.0.0.1', '--port', address.rsplit(':', 1)[1],
                               '--no-dashboard'], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        for _ in range(2):
            procs.append(subprocess.Popen([dask, 'worker', address, '--nthreads', '1', '--host', '127.0.0.1',
                                           '--no-dashboard'], env=env, cwd=tmp_path,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        from distributed import Client
        with Client(address, timeout=60) as c:
            c.wait_for_workers(2, timeout=120)
        reps = {}
        for where, extra in (('here', []), ('cluster', ['--scheduler', address])):
            out = tmp_path / where
            rc = main(['triangulate', str(survey), '--gcp', str(survey / 'gcp_list.txt'), '--out', str(out),
                       '--lever-arm=0,-0.05,-0.2', '--split-photos', str(SPLIT), '--quiet'] + extra)
            assert rc in (0, 4)
            reps[where] = json.loads((out / 'report.json').read_text())
        here, there = reps['here'], reps['cluster']
        assert len(there['split_merge']['sub_blocks']) == 2
        assert there['registered'] == here['registered']
        assert there['check']['rmse']['n'] == here['check']['rmse']['n'] == 2
        for k in ('horizontal_m', 'vertical_m'):
            assert there['check']['rmse'][k] == pytest.approx(here['check']['rmse'][k], rel=1e-3, abs=1e-4)
        assert there['verdict']['status'] == here['verdict']['status']
    finally:
        for p in reversed(procs):
            p.terminate()
        deadline = time.monotonic() + 30
        for p in procs:
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
