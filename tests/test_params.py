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


def test_runtime_parameter_changes_are_refused_with_a_reason(rclpy_context):
    # `ros2 param set` goes through set_parameters: the nodes read their parameters once, so a change
    # must be refused (and the user told), not accepted and silently ignored.
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from photogram_ros.core.tracker import TrackerParams
    from photogram_ros.nodes.ros_params import declare
    node = Node('read_only_check', context=rclpy_context)
    try:
        p = declare(node, TrackerParams, {'max_features': 300})
        assert p.max_features == 300                                  # overrides still apply at start
        res = node.set_parameters([Parameter('max_features', value=500), Parameter('normalize', value='none')])
        assert [r.successful for r in res] == [False, False]
        assert all('read-only' in r.reason for r in res)
        assert node.get_parameter('max_features').value == 300
        assert node.describe_parameter('max_features').read_only
    finally:
        node.destroy_node()
