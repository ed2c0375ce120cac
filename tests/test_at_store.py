"""PointStore behaves as the dict it replaces (values, iteration order) while points freeze and thaw;
KeyframeSpill gives back what it stored."""

import numpy as np

from photogram_ros.core.at_store import KeyframeSpill, PointStore


def test_point_store_matches_a_dict_through_freeze_thaw_and_pop():
    rng = np.random.default_rng(3)
    ref, ps = {}, PointStore()
    for step in range(3000):
        t = int(rng.integers(0, 400))
        op = rng.random()
        if op < 0.5:
            v = rng.normal(size=3)
            ref[t] = v
            ps[t] = v
        elif op < 0.7:
            assert np.array_equal(ref.pop(t, np.zeros(3)), ps.pop(t, np.zeros(3)))
        elif op < 0.8:
            hot = [k for k in ref if not ps.is_frozen(k)][:20]
            ps.freeze(hot, [2] * len(hot))
        elif op < 0.85:
            ps.thaw(t)
        assert len(ps) == len(ref) and (t in ps) == (t in ref)
    assert list(ps) == list(ref)
    ids, xyz = ps.arrays()
    assert ids.tolist() == list(ref) and np.array_equal(xyz, np.array(list(ref.values())))
    assert ps.frozen_bytes > 0 and ps.n_hot < len(ref)
    # A frozen point's observation count: the point is gone once fewer than two keyframes see it.
    t = next(k for k in ref if ps.is_frozen(k))
    assert ps.frozen_count_decrement(t) == 1


def test_keyframe_spill_round_trip(tmp_path):
    sp = KeyframeSpill(str(tmp_path))
    ids = np.arange(5, dtype=np.int64) * 7
    uv, xn, act = np.random.default_rng(0).normal(size=(5, 2)), np.ones((5, 2)), np.array([1, 0, 1, 1, 0], bool)
    sp.save(3, ids, uv, xn, act)
    back = sp.load(3)
    for a, b in zip(back, (ids, uv, xn, act)):
        assert np.array_equal(a, b) and a.flags.c_contiguous
    assert sp.bytes_on_disk > 0
    tmp = KeyframeSpill()
    folder = tmp.folder
    assert folder.exists()
    del tmp
    assert not folder.exists()   # a private spill folder goes with its store
