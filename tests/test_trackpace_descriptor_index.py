"""One FLANN index per frame (photo_matching.DescriptorIndex): a frame matched against several keyframes
builds its kd-trees once, with the matches an index built for each pair gives."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_photo_matching import _texture  # noqa: E402

from photogram_ros.core import photo_matching as pm  # noqa: E402
from photogram_ros.core.camera import PinholeCamera  # noqa: E402


def test_one_index_searched_by_several_photos_gives_each_pair_its_own_matches(monkeypatch):
    cam = PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5)
    opt = pm.MatchingOptions()
    base = _texture(900, 480, 1)
    frame = pm.extract('f', base[:, :640], opt=opt)
    earlier = [pm.extract(str(s), base[:, s:s + 640], opt=opt) for s in (30, 90, 150)] + \
        [pm.extract('other', _texture(640, 480, 5), opt=opt)]
    per_pair = [pm.match_pair(e, frame, cam, opt) for e in earlier]
    built = []
    real = pm.DescriptorIndex.__init__

    def counting(self, desc):
        built.append(len(desc))
        real(self, desc)
    monkeypatch.setattr(pm.DescriptorIndex, '__init__', counting)
    index = pm.DescriptorIndex(frame.desc)
    shared = [pm.match_pair(e, frame, cam, opt, index_b=index) for e in earlier]
    assert built == [len(frame.desc)]   # the frame's trees, once for the four pairs
    assert [r.status for r in shared] == [r.status for r in per_pair]
    assert sum(r.verified for r in shared) >= 3 and not shared[-1].verified
    for a, b in zip(shared, per_pair):
        assert a.ratio_matches == b.ratio_matches and np.array_equal(a.matches, b.matches)


def test_an_index_of_too_few_descriptors_matches_nothing():
    idx = pm.DescriptorIndex(np.zeros((1, 128), np.float32))
    assert idx.size == 1 and idx.knn2(np.ones((5, 128), np.float32)) == []
