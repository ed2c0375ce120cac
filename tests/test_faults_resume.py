"""Resume after a crash (issue 48): the keyframes a map holds from before the restart are counted. Those stored
with a pose are oriented (the products use them); those stored without one (taken before the crash, never
oriented: their features were not stored, so the resumed run's adjuster cannot take them) are counted as taken
and not oriented, with the reason, instead of the report's "N of N" over this run's keyframes only."""

from __future__ import annotations

import json

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
    store = _map_with_keyframes(root, posed=[10, 20], unposed=[30, 40])
    before = keyframes_before(root)
    assert before == {'posed': [10, 20], 'unposed': [30, 40]}
    # The resumed run: 3 new keyframes, all oriented; the stored 30 got a pose meanwhile, 40 did not.
    for s in (50, 60, 70, 30):
        store.save_keyframe_image(s, b'\xff\xd8\xff\xd9')
        store.save_keyframe_pose(s, np.eye(4))
    counts = {'tracker': {'keyframes': 3}, 'bundle': {'keyframes_received': 3, 'keyframes_oriented': 3}}
    oriented = len(store.keyframes())
    plain = keyframe_accounting(json.loads(json.dumps(counts)), oriented)
    assert plain['keyframes_taken'] == 3 and oriented == 6   # before: 6 "oriented" of 3 taken
    resumed = count_keyframes_before(counts, before, root)
    assert resumed == {'keyframes': 4, 'posed': 2, 'unposed': 2, 'still_unposed': 1}
    acc = keyframe_accounting(counts, oriented)
    assert acc['keyframes_taken'] == 7 and acc['keyframes_oriented'] == 6 and acc['keyframes_not_oriented'] == 1, acc
    assert acc['keyframes_not_oriented_by_reason'] == {
        'not oriented: taken before the restart without a pose': 1}, acc
    out = capsys.readouterr().out
    assert 'resumed map: 4 keyframes taken before this run (2 oriented then, 1 without a pose, not oriented' in out
