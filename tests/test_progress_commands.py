"""Progress lines of the long commands (io/progress.py): `export` says each product, `replay` the frames
with a percent and an ETA, its end-of-flight steps and its exports; --quiet says none of it."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, SAMPLE_BAG
from helpers.clouds import pair_cloud


@pytest.fixture(scope='module')
def small_map(tmp_path_factory):
    """A map folder of 4 fused pair clouds over a gentle slope (no keyframe images)."""
    from photogram_ros.core.fusion import Fusion, FusionConfig
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.io.map_store import MapStore
    d = tmp_path_factory.mktemp('progress') / 'map'
    store = MapStore(d, 0.08, 256)
    store.set_origin(LocalFrame(47.3977, 8.5456, 488.0))
    f = Fusion(FusionConfig(0.08, 256), store)
    rng = np.random.default_rng(5)
    for k in range(4):
        f.add(pair_cloud(rng, lambda x, y: 2.0 + 0.04 * x, -10.0 + 8 * k, 5.0, 10.0, 8.0, 60.0, 0.01))
    f.flush()
    return d


def test_export_says_each_product_as_it_starts(small_map, tmp_path, capsys):
    from photogram_ros import cli
    assert cli.main(['export', str(small_map), '--crs', 'EPSG:32632', '--out', str(tmp_path / 'a'),
                     '--min-pairs', '1', '--contours-m', '0.5']) == 0
    err = capsys.readouterr().err.splitlines()
    steps = [m[1] for m in (re.fullmatch(r'export: (.+) \(step (\d)/8\), \d+ s elapsed', s) for s in err) if m]
    assert steps == ['cloud', 'LAS', 'LAZ', 'PLY', 'DSM', 'DTM', 'contours', 'ortho']
    assert re.fullmatch(r'export: 8 steps in \d+ s \(longest: .+, \d+ s\)', err[-1])
    assert cli.main(['export', str(small_map), '--crs', 'EPSG:32632', '--out', str(tmp_path / 'b'),
                     '--products', 'dsm', '--quiet']) == 0
    assert capsys.readouterr().err == ''


@pytest.mark.slow
@pytest.mark.ros
def test_replay_of_the_sample_bag_says_percent_eta_and_every_step(tmp_path):
    """The sample flight (76 frames; about 70 s on a loaded 2-core machine): the frames counted against the
    bag's total with an ETA, a final 100 %, the end-of-flight steps, the dense matching's keyframes and
    each product."""
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(SAMPLE_BAG), '--out',
                        str(tmp_path / 'out'), '--domain', os.environ['ROS_DOMAIN_ID']], cwd=ROOT,
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout + r.stderr
    out = r.stdout.splitlines()
    frames = [m for m in (re.fullmatch(r'replay: (\d+)/76 frames \((\d+) %\), \d+ s elapsed, ETA ([^;]+)(; .*)?', s)
                          for s in out) if m]
    assert frames, r.stdout
    assert all(int(m[2]) == int(100 * int(m[1]) / 76) for m in frames)
    assert any(re.fullmatch(r'\d+ s|[\d.]+ min', m[3]) for m in frames), r.stdout   # an ETA, not "unknown"
    assert any(re.fullmatch(r'replay: 76/76 frames \(100 %\) in \d+ s(; .*)?', s) for s in out), r.stdout
    ends = [s for s in out if s.startswith('replay: end of flight: ')]
    assert [re.sub(r' \(step.*', '', s)[len('replay: end of flight: '):] for s in ends[:-1]] == [
        'the last frames through the graph', "the tracker's last keyframes", 'final adjustment',
        'the last stereo pairs', "closing the map's coverage"]
    assert re.fullmatch(r'replay: end of flight: 5 steps in .*', ends[-1])
    assert any(re.fullmatch(r'export: dense matching: (\d+)/\1 keyframes \(100 %\) in .*', s)
               for s in out), r.stdout
    assert [re.sub(r' \(step.*', '', s)[len('export: '):] for s in out if re.match(r'export: \w+ \(step', s)] == [
        'cloud', 'LAS', 'LAZ', 'PLY', 'DSM', 'DTM', 'ortho']
    assert any(re.fullmatch(r'export: ortho: (\d+)/\1 keyframes \(100 %\) in .*', s) for s in out), r.stdout


def test_replay_frame_totals_of_a_bag_a_photo_folder_and_a_video(tmp_path):
    """The totals the replay's percent is of: the bag's image count, the folder's photos, the video's frames."""
    import cv2

    from photogram_ros.io.bag import BagReader
    from photogram_ros.io.image_source import FolderSource, VideoSource
    from photogram_ros.nodes.replay_session import frame_total, frame_total_of_source
    with BagReader(SAMPLE_BAG) as bag:
        assert frame_total(bag.topics()) == 76
    assert frame_total({}) is None
    folder = tmp_path / 'photos'
    folder.mkdir()
    for k in range(5):
        cv2.imwrite(str(folder / f'IMG_{k}.jpg'), np.full((48, 64, 3), 40 * k, np.uint8))
    assert frame_total_of_source(FolderSource(folder)) == 5
    video = tmp_path / 'v.avi'
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*'MJPG'), 10.0, (64, 48))
    for k in range(12):
        w.write(np.full((48, 64, 3), 10 * k, np.uint8))
    w.release()
    assert frame_total_of_source(VideoSource(str(video), start_ns=0)) == 12
