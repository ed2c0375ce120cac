"""The keyframe features table with ArUco target rows (msgs.py's reserved track-id range)."""

import numpy as np
import pytest

from photogram_ros import msgs
from photogram_ros.core.control import TARGET_DTYPE
from photogram_ros.core.tracker import FEATURE_DTYPE
from photogram_ros.errors import DataError


def _table(n_tracks=50, markers=(0, 7, 49)):
    rng = np.random.default_rng(3)
    obs = np.zeros(n_tracks, FEATURE_DTYPE)
    obs['track_id'] = np.sort(rng.choice(10**6, n_tracks, replace=False))
    for f in ('u', 'v', 'xn', 'yn'):
        obs[f] = rng.uniform(-1, 640, n_tracks)
    tg = np.zeros(len(markers), TARGET_DTYPE)
    tg['marker_id'] = markers
    for f in ('u', 'v', 'xn', 'yn'):
        tg[f] = rng.uniform(0, 480, len(markers))
    return obs, tg


def test_round_trip_msg_numpy_msg():
    obs, tg = _table()
    m1 = msgs.keyframe_features_msg(obs, 1_780_000_000_123_456_789, 'camera_optical', tg)
    assert m1.width == len(obs) + len(tg) and [f.name for f in m1.fields] == list(FEATURE_DTYPE.names)
    feats, targets = msgs.keyframe_table_from_msg(m1)
    assert feats.dtype == FEATURE_DTYPE and targets.dtype == TARGET_DTYPE
    assert np.array_equal(feats, obs) and np.array_equal(targets, tg)
    m2 = msgs.keyframe_features_msg(feats, msgs.ns_from_time(m1.header.stamp), m1.header.frame_id, targets)
    assert bytes(m2.data) == bytes(m1.data) and m2.header == m1.header and m2.fields == m1.fields
    # A reader that knows nothing of targets gets the tracks only.
    assert np.array_equal(msgs.features_from_keyframe_msg(m1), obs)
    # The target rows sit in the reserved id range.
    ids = msgs.points_from_pointcloud2(m1)['track_id'].astype(np.int64)
    assert np.array_equal(ids[len(obs):] - msgs.TARGET_TRACK_ID_BASE, tg['marker_id'])


def test_tables_without_targets_and_float32_producers():
    obs, _ = _table(markers=())
    m = msgs.keyframe_features_msg(obs, 5, targets=np.zeros(0, TARGET_DTYPE))
    feats, targets = msgs.keyframe_table_from_msg(m)
    assert len(targets) == 0 and np.array_equal(feats, obs)
    assert bytes(m.data) == bytes(msgs.keyframe_features_msg(obs, 5).data)   # the old message, unchanged
    # Another producer's float32 table with a marker row.
    t32 = np.zeros(2, [('track_id', '<u4'), ('u', '<f4'), ('v', '<f4'), ('xn', '<f4'), ('yn', '<f4')])
    t32['track_id'] = [12, msgs.TARGET_TRACK_ID_BASE + 3]
    t32['u'] = [1.5, 2.5]
    feats, targets = msgs.keyframe_table_from_msg(msgs.pointcloud2_msg(t32, 5))
    assert feats['track_id'].tolist() == [12] and targets['marker_id'].tolist() == [3]
    assert targets['u'][0] == 2.5 and targets.dtype == TARGET_DTYPE


def test_reserved_range_is_guarded():
    obs, tg = _table()
    obs['track_id'][-1] = msgs.TARGET_TRACK_ID_BASE
    with pytest.raises(DataError, match='reserved for targets'):
        msgs.keyframe_features_msg(obs, 5)
    obs, tg = _table()
    tg['marker_id'][0] = msgs.MAX_MARKER_ID + 1
    with pytest.raises(DataError, match='marker ids must lie in'):
        msgs.keyframe_features_msg(obs, 5, targets=tg)
