"""Features and pair matching of `triangulate PHOTOS` on Dask (io/dask_cluster.py): the same matches as
in one process, on a local cluster and on a `dask scheduler` + 2 `dask worker` processes on 127.0.0.1."""

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT
from photogram_ros.cli import main
from photogram_ros.errors import ConfigError
from photogram_ros.io import dask_cluster
from photogram_ros.io.dask_cluster import InProcessRunner, open_runner
from photogram_ros.io.photo_block import read_photo_block
from photogram_ros.sim.scenario import preset, simulate


@pytest.fixture(scope='module')
def survey(tmp_path_factory):
    """A small simulated photo survey (about 20 photos, 10 s) and its block read in this process."""
    flight = tmp_path_factory.mktemp('dask') / 'flight'
    simulate(preset('tiny', photos=True), flight)
    photos = flight / 'photos'
    return photos, read_photo_block(photos)


def _same_block(a, b) -> None:
    """Two blocks of the same folder hold the same matches: the same pair statistics, and per photo
    the same features in the same tracks."""
    for key in ('photos', 'pairs_tried', 'pairs_verified', 'pair_status', 'widened_photos', 'track_lengths',
                'features_median', 'features_min'):
        assert a.stats[key] == b.stats[key], key
    assert [r.name for r in a.records] == [r.name for r in b.records]
    for ra, rb in zip(a.records, b.records):
        np.testing.assert_array_equal(ra.track_ids, rb.track_ids)
        np.testing.assert_array_equal(ra.uv, rb.uv)
    assert a.assumptions == b.assumptions


def test_one_worker_is_this_process_and_bad_options_are_refused(monkeypatch):
    with open_runner(1) as r:
        assert isinstance(r, InProcessRunner)
        assert r.run(pow, [(2, 3), (3, 2)]) == [8, 9]
    with pytest.raises(ConfigError, match='--workers takes 1 or more'):
        with open_runner(0):
            pass
    with pytest.raises(ConfigError, match='give one of them'):
        with open_runner(2, 'tcp://127.0.0.1:8786'):
            pass
    with pytest.raises(ConfigError, match='tcp://HOST:PORT'):
        with open_runner(1, '127.0.0.1:8786'):
            pass
    monkeypatch.setattr(dask_cluster, 'CONNECT_TIMEOUT_S', 1.0)
    with socket.socket() as s:      # a port nobody listens on
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    with pytest.raises(ConfigError, match='no Dask scheduler answered'):
        with open_runner(1, f'tcp://127.0.0.1:{port}'):
            pass


def _pair_sum(a, b):
    return a[0] + b[0]


def test_local_cluster_runs_in_order_keeps_results_on_the_workers_and_reports_progress(monkeypatch):
    monkeypatch.setattr(dask_cluster, 'PROGRESS_EVERY_S', 0.0)
    lines, seen = [], []
    with open_runner(2, log=lines.append) as runner:
        assert runner.workers == 2 and lines == ['local Dask cluster: 2 worker processes of 1 thread']
        kept = runner.run(divmod, [(k, 3) for k in range(12)], 'pieces', lines.append, keep=True)
        assert all(type(h).__name__ == 'Future' for h in kept)
        sums = runner.run(_pair_sum, [(kept[k], kept[k + 1]) for k in range(11)],
                          on_result=lambda k, r: seen.append(k))
        runner.release(kept)
        with pytest.raises(ZeroDivisionError):
            runner.run(divmod, [(1, 0)])
    assert sums == [k // 3 + (k + 1) // 3 for k in range(11)] and sorted(seen) == list(range(11))
    assert lines[-1].startswith('pieces: 12/12 on 2 workers (')
    assert any(re.fullmatch(r'pieces: \d+/12 on 2 workers \(\d+ s, about \d+ s left\)', s) for s in lines)


def _page_faults_of_temporaries(n: int) -> int:
    """Minor page faults of this process over n numpy temporaries of 1.6 MB each."""
    import resource
    x = np.ones((200, 1000))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        x * 1.0001 + 1.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


def test_local_cluster_workers_reuse_large_buffers():
    # Dask's nanny sets MALLOC_TRIM_THRESHOLD_ in its workers: without reuse_freed_buffers each
    # temporary is mapped afresh, about 400 faults of 4 KiB each (800,000 over these 2,000).
    with open_runner(2) as runner:
        faults = runner.run(_page_faults_of_temporaries, [(2000,), (2000,)])
    assert max(faults) < 20_000, faults


@pytest.mark.slow
def test_local_cluster_gives_the_same_matches_with_progress(survey, monkeypatch):
    photos, alone = survey
    monkeypatch.setattr(dask_cluster, 'PROGRESS_EVERY_S', 0.0)
    lines = []
    with open_runner(2, log=lines.append) as runner:
        assert runner.workers == 2
        block = read_photo_block(photos, runner=runner, log=lines.append)
    _same_block(alone, block)
    n = alone.stats['photos']
    assert f'features: {n}/{n} on 2 workers' in '\n'.join(lines)
    assert any('features: 1/' in s and 's left)' in s for s in lines)
    assert any(re.fullmatch(r'matching pairs: (\d+)/\1, \d+ verified on 2 workers \(\d+ s\)', s) for s in lines)


@pytest.mark.slow
def test_triangulate_command_workers_2_same_report_as_workers_1(survey, tmp_path):
    photos, _ = survey
    # The EXIF camera, self-calibrated as `triangulate` does by default: whatever its verdict (exit 0 or
    # 4: tests/test_triangulate_command.py), the same with either worker count.
    reps, rcs = {}, {}
    for w in ('1', '2'):
        out = tmp_path / f'w{w}'
        rcs[w] = main(['triangulate', str(photos), '--gcp', str(photos / 'gcp_list.txt'), '--out', str(out),
                       '--lever-arm=0,-0.05,-0.2', '--workers', w])
        reps[w] = json.loads((out / 'report.json').read_text())
    assert rcs['1'] == rcs['2'] and rcs['1'] in (0, 4)
    assert reps['1']['self_calibration'] == reps['2']['self_calibration']
    assert reps['1']['check']['rmse']['n'] == 2
    assert reps['1']['check'] == reps['2']['check']
    assert reps['1']['matching']['pairs_verified'] == reps['2']['matching']['pairs_verified']
    assert reps['1']['reprojection_rms_px'] == reps['2']['reprojection_rms_px']


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@contextmanager
def scheduler_and_two_workers(cwd):
    """A `dask scheduler` and 2 `dask worker` processes of 1 thread on 127.0.0.1 (workers in `cwd`) for the
    length of the block; yields the scheduler's address."""
    dask = shutil.which('dask', path=str(Path(sys.executable).parent))
    assert dask, 'the dask command of dask[distributed] is not installed beside this Python'
    address = f'tcp://127.0.0.1:{_free_port()}'
    env = {**os.environ, 'PYTHONPATH': str(ROOT)}
    procs = [subprocess.Popen([dask, 'scheduler', '--host', '127.0.0.1', '--port', address.rsplit(':', 1)[1],
                               '--no-dashboard'], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        for _ in range(2):
            procs.append(subprocess.Popen([dask, 'worker', address, '--nthreads', '1', '--host', '127.0.0.1',
                                           '--no-dashboard'], env=env, cwd=cwd,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        from distributed import Client
        with Client(address, timeout=60) as c:
            c.wait_for_workers(2, timeout=120)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        deadline = time.monotonic() + 30
        for p in procs:
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()


@pytest.mark.slow
def test_scheduler_and_two_worker_processes_on_localhost(survey, tmp_path):
    photos, alone = survey
    with scheduler_and_two_workers(tmp_path) as address:
        lines = []
        with open_runner(1, address, log=lines.append) as runner:
            assert runner.workers == 2
            block = read_photo_block(photos, runner=runner, log=lines.append)
        _same_block(alone, block)
        assert f'Dask cluster at {address}: 2 workers' in lines
        n = alone.stats['photos']
        assert f'features: {n}/{n} on 2 workers at {address} (' in '\n'.join(lines)
