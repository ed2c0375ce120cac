"""core/other_image.py, the tracker's second look at a break (features_fallback), without ROS: synthetic textures
shifted as a camera translated over flat ground would see them."""

from __future__ import annotations

import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.other_image import OtherImageFallback, first_per_id
from photogram_ros.core.photo_matching import MatchingOptions
from photogram_ros.core.tracker import TrackerParams
from test_photo_matching import _texture

W, H = 640, 480
CAM = PinholeCamera(W, H, 500.0, 500.0, 319.5, 239.5)


GROUND = _texture(W + 400, H, 1)


def _view(x0: int) -> np.ndarray:
    return np.ascontiguousarray(GROUND[:, x0:x0 + W])


NONE = (np.empty((0, 2), np.float32), np.empty(0, np.uint32))


def _fallback(**params):
    """The fallback as the tracker makes it, with features_on 'normalised': the raw image is the other one."""
    counter = [0]

    def new_ids(n):
        t = np.arange(counter[0], counter[0] + n, dtype=np.int64)
        counter[0] += n
        return t
    inside = lambda uv: CAM.in_image(uv, margin_px=8)   # noqa: E731
    opt = MatchingOptions(max_features=2000, features_per_mpx=8000.0, min_inliers=15, ransac_method='usac')
    return OtherImageFallback(CAM, opt, inside, new_ids, lambda stamp_ns: None, TrackerParams(**{'features_fallback': True, **params}),
                              hold_weak=2), counter


def _publish(fb, key, raw, klt=NONE, near=()):
    """Keyframe `key` (frame `key`) of raw grey `raw` publishes; returns the tracks it adds (pts, ids)."""
    return fb.publish(key, key, np.zeros_like(raw), raw, klt, NONE, list(near))


def _recover(fb, index, raw, keys):
    return fb.recover(index, np.zeros_like(raw), raw, index, [(k, k) for k in keys])


def test_one_id_per_track_the_first_keeps_it():
    ids = np.array([5, -1, 5, 7, 7, -1, 3], np.int64)
    first_per_id(ids)
    assert ids.tolist() == [5, -1, -1, 7, -1, -1, 3]


def test_a_frame_at_a_break_continues_the_tracks_a_keyframe_published_on_its_other_image():
    fb, counter = _fallback()
    add_pts, add_ids = _publish(fb, 0, _view(0), (np.array([[100.0, 100.0]], np.float32), np.array([10_000], np.uint32)))
    assert len(add_ids) > 100 and len(np.unique(add_ids)) == len(add_ids)
    assert counter[0] >= len(add_ids)   # new ids from the tracker's counter
    # The ground moved 120 px: the frame's features that match take the keyframe's ids, where the truth has them.
    got = _recover(fb, 1, _view(120), [0])
    assert got is not None and fb.bridged == 1
    pts, ids = got
    assert len(ids) >= 15 and len(np.unique(ids)) == len(ids)
    where = {int(i): p for i, p in zip(add_ids, add_pts)}
    moved = np.array([where[int(i)] - p for i, p in zip(ids, pts) if int(i) in where])
    assert len(moved) == len(ids)
    assert np.median(np.abs(moved[:, 0] - 120.0)) < 1.0 and np.median(np.abs(moved[:, 1])) < 1.0


def test_unrelated_ground_bridges_nothing():
    fb, _ = _fallback()
    _publish(fb, 0, _view(0))
    assert _recover(fb, 1, _texture(W, H, 7), [0]) is None and fb.bridged == 0
    assert _recover(fb, 2, _view(100), [5]) is None   # a keyframe that published nothing


def test_a_later_keyframe_links_a_weak_one_it_overlaps_and_a_linked_one_is_let_go():
    fb, _ = _fallback()
    _, ids0 = _publish(fb, 0, _view(0))   # the first: weak
    _, ids1 = _publish(fb, 1, _texture(W, H, 9))   # not weak
    fb.keep([1])
    # Keyframe 2 overlaps keyframe 0 (by GNSS): its features of the same ground take keyframe 0's ids.
    _, ids2 = _publish(fb, 2, _view(150), near=[0, 1])
    assert len(np.intersect1d(ids2, ids0)) >= 15
    assert len(np.intersect1d(ids2, ids1)) == 0   # keyframe 1 is not weak: not matched
    # Not overlapping by GNSS: not matched.
    fb2, _ = _fallback()
    _, a = _publish(fb2, 0, _view(0))
    _, b = _publish(fb2, 1, _view(150))
    assert len(np.intersect1d(a, b)) == 0
    # A later frame's usual features verified keyframe 0: no longer weak, its features dropped with the old ones.
    fb.linked(0)
    fb.keep([2])
    assert _recover(fb, 3, _view(100), [0]) is None
    assert fb.nbytes() > 0


def test_a_published_feature_on_a_shown_track_takes_its_id():
    fb, _ = _fallback()
    f, _ = fb.features(0, _view(0))
    shown_pts = f.uv[:300] + 0.3
    shown_ids = np.arange(5000, 5300, dtype=np.uint32)
    _, add_ids = _publish(fb, 0, _view(0), (shown_pts.astype(np.float32), shown_ids))
    assert not np.isin(add_ids, shown_ids).any()     # shown already: not added twice
    # ... but published: a later frame's matches continue them.
    _, ids = _recover(fb, 1, _view(120), [0])
    assert np.isin(ids, shown_ids).sum() >= 5


def test_off_or_without_another_image_nothing_is_published_nor_recovered():
    fb, _ = _fallback(features_fallback=False)
    extra = (np.ones((1, 2), np.float32), np.array([3], np.uint32))
    assert fb.publish(0, 0, _view(0), _view(0), NONE, extra, []) is extra
    assert _recover(fb, 1, _view(120), [0]) is None
    on, _ = _fallback()
    assert on.image_of(_view(0), None) is None          # normalize 'none': the same image, no other
    raw_usual, _ = _fallback(features_on='raw')
    g, r = _view(0), _view(1)
    assert raw_usual.image_of(g, r) is g and on.image_of(g, r) is r
