"""Parameter dataclasses: values from the command line take their defaults' types; mistakes are named."""

import pytest

from photogram_ros.core.stereo import StereoParams
from photogram_ros.errors import ConfigError
from photogram_ros.params import from_assignments


def test_assignments_take_the_default_types():
    p = from_assignments(StereoParams, ['downscale=0.5', 'block_size=7', 'mode=sgbm'])
    assert p.downscale == 0.5 and p.block_size == 7 and p.mode == 'sgbm'


@pytest.mark.parametrize('items, words', [(['downscal=0.5'], 'downscale'), (['downscale=9'], 'downscale'),
                                          (['downscale'], 'name=value')])
def test_assignment_mistakes_are_named(items, words):
    with pytest.raises(ConfigError, match=words):
        from_assignments(StereoParams, items)
