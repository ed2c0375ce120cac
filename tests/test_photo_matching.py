"""core/photo_matching.py: reduced-size features mapped back to the full photo, candidate pairs, tracks."""

from __future__ import annotations

import cv2
import numpy as np

from photogram_ros.core import photo_matching as pm
from photogram_ros.core.camera import PinholeCamera


def _texture(w, h, seed=0):
    """A random blob texture (features at many scales), as uint8 grey."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for s in (3, 9, 27):
        noise = rng.normal(0, 1, (h // s + 2, w // s + 2)).astype(np.float32)
        img += cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
    img = (img - img.min()) / np.ptp(img) * 255
    return img.astype(np.uint8)


def test_reduced_size_uses_libjpeg_powers_of_two_and_never_enlarges():
    assert pm.reduced_size(4000, 2250, 1000) == (4, 1000, 563)
    assert pm.reduced_size(5472, 3648, 1000) == (4, 1000, 667)     # 1368 decoded, then resized
    assert pm.reduced_size(640, 480, 1000) == (1, 640, 480)
    assert pm.reduced_size(2400, 1800, 1000) == (2, 1000, 750)


def test_features_on_the_reduced_image_land_on_full_photo_pixels():
    """The same texture seen at full size and reduced 4x: features found on the reduced image map back
    to where the full-size image has them (pixel centres at integers in both)."""
    full = _texture(2000, 1200)
    small = cv2.resize(full, (500, 300), interpolation=cv2.INTER_AREA)
    opt = pm.MatchingOptions(max_features=2000)
    a = pm.extract('small', small, (4.0, 4.0), opt)
    b = pm.extract('full', full, (1.0, 1.0), pm.MatchingOptions(max_features=20000))
    cam = PinholeCamera(2000, 1200, 1500.0, 1500.0, 999.5, 599.5)
    r = pm.match_pair(a, b, cam, opt, px_per_feature_px=4.0)
    assert r.verified and r.inliers > 200
    d = a.uv[r.matches[:, 0]] - b.uv[r.matches[:, 1]]
    # Unbiased (a half-pixel slip would show as a 1.5 px mean offset) and about 1 reduced pixel apart.
    assert np.all(np.abs(np.median(d, axis=0)) < 0.5), np.median(d, axis=0)
    assert np.median(np.linalg.norm(d, axis=1)) < 2.0


def test_pair_statuses_say_where_a_pair_failed():
    cam = PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5)
    opt = pm.MatchingOptions()
    a = pm.extract('a', _texture(640, 480, 1), opt=opt)
    b = pm.extract('b', _texture(640, 480, 2), opt=opt)          # unrelated texture
    r = pm.match_pair(a, b, cam, opt)
    assert not r.verified and r.status in ('too_few_matches', 'too_few_inliers') and len(r.matches) == 0
    empty = pm.PhotoFeatures('e', np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    assert pm.match_pair(a, empty, cam, opt).status == 'too_few_features'
    shifted = pm.extract('s', np.roll(_texture(640, 480, 1), 40, axis=1), opt=opt)
    ok = pm.match_pair(a, shifted, cam, opt)
    assert ok.verified and ok.inliers >= opt.min_inliers and ok.ratio_matches >= ok.inliers


def test_candidates_by_distance_widen_with_the_gnss_uncertainty():
    # Two lines of photos 10 m apart along, 30 m across.
    pos = np.array([[10.0 * i, 30.0 * j, 0.0] for j in range(2) for i in range(6)])
    order, first = pm.candidate_order(pos, 2)
    assert first.tolist() == [2] * 12
    assert set(order[0, :2].tolist()) == {1, 2}
    pairs = pm.candidate_pairs(order, first)
    assert (0, 6) not in pairs and (0, 1) in pairs
    # Poor GNSS (sigma 5 m): every photo within the 2nd distance + 14 m is a first candidate too.
    order, first = pm.candidate_order(pos, 2, sigma_h_m=5.0)
    assert (0, 6) in pm.candidate_pairs(order, first) and first[0] > 2
    # A photo without a position: every photo.
    pos[3] = np.nan
    order, first = pm.candidate_order(pos, 2)
    assert first[3] == 11


def test_candidates_by_footprint_overlap_follow_the_heading():
    """Photos 30 m apart along x with 60 x 20 m footprints: overlapping when the long side lies along
    the line (rotation 0), not when it is across (90 deg)."""
    pos = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 25.0, 0.0]])
    along = np.array([[60.0, 20.0, 0.0]] * 3)
    order, first = pm.candidate_order(pos, 5, footprints=along)
    assert order[0, 0] == 1 and first[0] == 1          # (0, 2): 25 m across a 20 m footprint
    across = np.array([[60.0, 20.0, 90.0]] * 3)
    order, first = pm.candidate_order(pos, 5, footprints=across)
    assert order[0, 0] == 2 and first[0] == 1


def test_more_candidates_only_for_weakly_linked_photos():
    order = np.array([[1, 2, 3], [0, 2, 3], [1, 3, 0], [2, 1, 0]])
    tried = {(0, 1), (1, 2), (2, 3)}
    extra = pm.more_candidates(order, tried, np.array([1, 2, 2, 1]), min_pairs=2, max_extra=1)
    assert extra == [(0, 2), (1, 3)]


def test_tracks_chain_through_photos_and_drop_ambiguous_chains():
    # Feature 0 of photo 0 = 0 of photo 1 = 0 of photo 2 (a 3-photo track); photo 0's features 1 and 2
    # both chain to photo 1's feature 1 (ambiguous: dropped).
    matches = {(0, 1): np.array([[0, 0], [1, 1], [2, 1]]), (1, 2): np.array([[0, 0]])}
    tracks = pm.build_tracks([3, 2, 1], matches)
    assert tracks[0][0] == tracks[1][0] == tracks[2][0] >= 0
    assert tracks[0][1] == tracks[0][2] == tracks[1][1] == -1
    lengths = pm.track_lengths(tracks)
    assert lengths[tracks[0][0]] == 3
