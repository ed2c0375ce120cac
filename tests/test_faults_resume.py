"""Resume after a crash (issue 48): the keyframes a map holds from before the restart are counted. Those stored
with a pose are oriented (the products use them); those stored without one (taken before the crash, never
oriented: their features were not stored, so the resumed run's adjuster cannot take them) are counted as taken
and not oriented, with the reason, instead of the report's "N of N" over this run's keyframes only."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest


def _map_with_keyframes(root, posed: list[int], unposed: list[int]):
    from photogram_ros.io.map_store import MapStore
    store = MapStore(root, cell_m=0.5, tile_cells=64)
    for s in posed + unposed:
        store.save_keyframe_image(s, b'\xff\xd8 not decoded here \xff\xd9')
    for s in posed:
        store.save_keyframe_pose(s, np.eye(4))
    return store


def test_keyframes_taken_before_a_crash_are_counted_as_taken_and_those_without_a_pose_as_not_oriented(tmp_path,
                                                                                                        capsys):
    from photogram_ros.commands.run import count_keyframes_before, keyframes_before
    from photogram_ros.io.flight_report import keyframe_accounting
    root = tmp_path / 'map'
    assert keyframes_before(root) is None   # a new map: nothing to count
    store = _map_with_keyframes(root, posed=[10, 20, 25], unposed=[30, 40])
    for p in store.keyframes_dir.iterdir():   # saved an hour before the restart
        os.utime(p, (p.stat().st_mtime - 3600,) * 2)
    before = keyframes_before(root)
    assert {k: before[k] for k in ('posed', 'unposed')} == {'posed': [10, 20, 25], 'unposed': [30, 40]}
    # The resumed run: 3 new keyframes, all oriented (25 among them: taken again, its image saved anew, counted
    # as this run's); the stored 30 and 40 stay without a pose.
    for s in (50, 25, 70):
        store.save_keyframe_image(s, b'\xff\xd8\xff\xd9')
        store.save_keyframe_pose(s, np.eye(4))
    counts = {'tracker': {'keyframes': 3}, 'bundle': {'keyframes_received': 3, 'keyframes_oriented': 3}}
    oriented = len(store.keyframes())
    plain = keyframe_accounting(json.loads(json.dumps(counts)), oriented)
    assert plain["keyframes_taken"] == 3 and oriented == 5   # before: 5 "oriented" of 3 taken
    resumed = count_keyframes_before(counts, before, root)
    assert resumed == {'keyframes': 4, 'posed': 2, 'unposed': 2, 'still_unposed': 2}
    acc = keyframe_accounting(counts, oriented)
    assert acc['keyframes_taken'] == 7 and acc['keyframes_oriented'] == 5 and acc['keyframes_not_oriented'] == 2, acc
    assert acc['keyframes_not_oriented_by_reason'] == {
        'not oriented: taken before the restart without a pose': 2}, acc
    out = capsys.readouterr().out
    assert 'resumed map: 4 keyframes taken before this run (2 oriented then, 2 without a pose, not oriented' in out


def _run(cfg, *args, timeout_s: float = 1200.0):
    import subprocess
    import sys

    from conftest import ROOT
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'run', '--params', str(cfg), '--nodes',
                        'camera,tracker,bundle,stereo,map', *args], cwd=ROOT, capture_output=True, text=True,
                       timeout=timeout_s)
    return r.returncode, r.stdout + r.stderr


@pytest.mark.slow
@pytest.mark.ros
def test_run_after_a_crash_counts_the_keyframes_taken_before_it(tmp_path):
    """brighton's first 10 photos through `run` (no products), then the crash made by hand: flight_end.json gone and
    the first 3 keyframes' poses gone (the adjuster had not oriented them); `run` on its last 12 photos resumes the
    map, its adjuster anchored at the map's origin. Its report counts the earlier keyframes as taken and the 3
    without a pose as not oriented, with the reason (before: "N of N" over the second run's keyframes only), and
    the second run's keyframes are oriented in the map's frame."""
    import shutil

    from conftest import shared_data
    photos = sorted(shared_data('photos', 'brighton_beach', 'images').glob('*.JPG'))
    assert len(photos) == 18
    # brighton flies 3 lines of 6 photos; each part holds a turn (a single line's poses stay provisional). The
    # second part starts with the 4 last photos of the first (taken again: this run's keyframes).
    for name, part in (('a', photos[:10]), ('b', photos[6:])):
        (tmp_path / name).mkdir()
        for p in part:
            shutil.copy2(p, tmp_path / name / p.name)
        (tmp_path / f'{name}.yaml').write_text(
            f'camera_node:\n  ros__parameters:\n    source: {tmp_path / name}\n    rate: 0.0\n'
            f'map_node:\n  ros__parameters:\n    map_dir: {tmp_path / "map"}\n')
    rc, out = _run(tmp_path / 'a.yaml', '--no-export')
    assert rc == 0, out[-3000:]
    kf = tmp_path / 'map' / 'keyframes'
    poses = sorted(kf.glob('*.json'))
    assert len(poses) >= 7, out[-3000:]
    (tmp_path / 'map' / 'flight_end.json').unlink()
    for p in poses[:3]:
        p.unlink()
    rc, out = _run(tmp_path / 'b.yaml', '--out', str(tmp_path / 'products'))
    assert 'resuming it' in out, out[-3000:]
    rep = json.loads((tmp_path / 'products' / 'report.json').read_text())
    n_before = rep['run']['resumed']['keyframes']
    assert 3 <= n_before <= 6, rep['run']['resumed']   # the keyframes of the first 6 photos
    assert f'resumed map: {n_before} keyframes taken before this run ({n_before - 3} oriented then, 3 without a pose' \
        in out, out[-3000:]
    taken_now = rep['run']['counts']['tracker']['keyframes'] - n_before
    print(f'resumed: {n_before} keyframes before, {taken_now} in the second run; report {rep["keyframes_oriented"]} '
          f'of {rep["keyframes_taken"]} oriented, by reason {rep["keyframes_not_oriented_by_reason"]}')
    assert rep['run']['resumed'] == {'keyframes': n_before, 'posed': n_before - 3, 'unposed': 3, 'still_unposed': 3}
    assert taken_now >= 6 and rep['keyframes_taken'] == n_before + taken_now, rep['run']['counts']
    assert rep['keyframes_oriented'] <= rep['keyframes_taken'] - 3
    assert rep['keyframes_not_oriented_by_reason'].get('not oriented: taken before the restart without a pose') == 3
    assert 'the adjuster anchors map at its origin' in out and 'map origin changed' not in out, out[-3000:]
    # The second run's keyframes are oriented, in the map's frame: near the first run's neighbours.
    assert rep['keyframes_oriented'] >= n_before - 3 + 0.8 * taken_now, rep
