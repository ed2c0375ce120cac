"""The products after a flight hold a few keyframe images at a time, not the flight's (issue 48: `run`'s RSS while
making the products never above its in-flight peak; the figure is bench/faults_stop.py's): the dense matching
drops each image after its last pair (io/densify.ImageCache), the orthomosaic decodes each keyframe as it drapes
it (io/export.StoredKeyframes)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest


def _images(tmp_path, n, size=(40, 30)):
    paths = []
    for k in range(n):
        p = tmp_path / f'{k}.png'
        cv2.imwrite(str(p), np.full((size[1], size[0], 3), k, np.uint8))
        paths.append(p)
    return paths


def test_the_image_cache_drops_each_image_after_its_last_pair_and_stays_within_its_bound(tmp_path):
    from photogram_ros.io.densify import ImageCache
    paths = _images(tmp_path, 8)
    # Keyframe i's pairs read i and its partners (one along the line, one on the line before).
    uses = [[0], [1, 0], [2, 1], [3, 2, 0], [4, 3, 1], [5, 4, 2], [6, 5, 3], [7, 6, 4]]
    for bound in (4, 3):   # 4: the pairs' working set (i and the three before it); 3: below it
        cache = ImageCache(lambda i: paths[i], uses, max_held=bound)
        for i, used in enumerate(uses):
            for j in used:
                assert int(cache.get(j, i)[0, 0, 0]) == j
                assert len(cache.held) <= bound
            cache.done(i)
            later = {j for u in uses[i + 1:] for j in u}
            assert set(cache.held) <= later, (i, set(cache.held))   # nothing kept that no later pair reads
        assert cache.held == {}
        if bound == 4:
            assert cache.reads == len(paths)   # each image decoded once
        else:
            assert cache.reads < sum(map(len, uses)), cache.reads   # read again past the bound, not at every use


def test_the_image_cache_names_an_unreadable_image(tmp_path):
    from photogram_ros.errors import DataError
    from photogram_ros.io.densify import ImageCache
    cache = ImageCache(lambda i: tmp_path / 'gone.jpg', [[0]])
    with pytest.raises(DataError, match='gone.jpg'):
        cache.get(0, 0)


def test_stored_keyframes_decode_each_image_when_read_and_leave_out_other_sizes(tmp_path):
    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.io.export import StoredKeyframes
    from photogram_ros.io.map_store import MapStore
    store = MapStore(tmp_path / 'map', 0.1, 64)
    store.save_camera(PinholeCamera(40, 30, 50.0, 50.0, 20.0, 15.0))
    for k in range(4):
        size = (40, 30) if k != 2 else (30, 40)   # keyframe 2: another size, left out as before
        img = np.full((size[1], size[0], 3), 10 * k, np.uint8)
        store.save_keyframe_image(k + 1, cv2.imencode('.jpg', img)[1].tobytes())
        store.save_keyframe_pose(k + 1, np.eye(4))
    kfs = StoredKeyframes(store)
    assert len(kfs) == 3
    assert not any(isinstance(v, np.ndarray) and v.ndim == 3 for e in kfs.entries for v in e)   # paths, not pixels
    seen = [int(np.median(kf.image)) for kf in kfs]
    assert seen == pytest.approx([0, 10, 30], abs=2)
    assert all(kf.image.shape == (30, 40, 3) for kf in kfs)
