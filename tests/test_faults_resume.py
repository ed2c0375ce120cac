"""Resume after a crash (issue 48): the keyframes a map holds from before the restart are counted. Those stored
with a pose are oriented (the products use them); those stored without one (taken before the crash, never
oriented: their features were not stored, so the resumed run's adjuster cannot take them) are counted as taken
and not oriented, with the reason, instead of the report's "N of N" over this run's keyframes only."""

from __future__ import annotations

import json
import os

import numpy as np


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
