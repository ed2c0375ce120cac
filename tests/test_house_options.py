"""triangulate's options: one TriangulateOptions, validated when it is made and handed down whole."""

import pickle

import pytest

from photogram_ros.core.incremental import IncrementalOptions
from photogram_ros.core.photo_matching import MatchingOptions
from photogram_ros.errors import ConfigError
from photogram_ros.io.aerial_triangulation import TriangulateOptions


def test_bad_options_are_refused_when_made():
    with pytest.raises(ConfigError, match='--takeoff-altitude-m'):
        TriangulateOptions(exif_altitude='relative')
    with pytest.raises(ConfigError, match='only used with --exif-altitude relative'):
        TriangulateOptions(takeoff_h_m=12.0)
    with pytest.raises(ConfigError, match='window_size'):
        TriangulateOptions(window=0)
    with pytest.raises(ConfigError, match='neighbours'):
        TriangulateOptions(neighbours=-1)


def test_the_stages_options_are_made_once_from_the_fields():
    opt = TriangulateOptions(window=7, lever_arm_cam_m=[0.1, 0.0, -0.2], neighbours=12,
                             matching=MatchingOptions(max_features=900), self_calibrate=['k1'])
    assert isinstance(opt.adjustment, IncrementalOptions)
    assert opt.adjustment.window_size == 7 and tuple(opt.adjustment.lever_arm_cam_m) == (0.1, 0.0, -0.2)
    assert opt.adjustment == IncrementalOptions(window_size=7, lever_arm_cam_m=(0.1, 0.0, -0.2))   # else defaults
    assert opt.matching.neighbours == opt.neighbours == 12 and opt.matching.max_features == 900
    assert opt.lever_arm_cam_m == (0.1, 0.0, -0.2) and opt.self_calibrate == ('k1',)
    assert opt.refine(None, 0, []) == ('k1',)          # asked for: no automatic choice is made
    # Without --neighbours the matching options' own count stands.
    assert TriangulateOptions(matching=MatchingOptions(neighbours=5)).neighbours == 5
    # Sent whole to a Dask worker (split-merge's sub-blocks): the copy is the same options.
    back = pickle.loads(pickle.dumps(opt))
    assert back == opt and back.adjustment == opt.adjustment
