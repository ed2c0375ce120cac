"""Parameter dataclasses: values from the command line take their defaults' types; mistakes are named."""

import pytest

from photogram_ros.core.stereo import StereoParams
from photogram_ros.errors import ConfigError
from photogram_ros.params import fields_of, from_assignments, to_dict


def test_assignments_take_the_default_types():
    p = from_assignments(StereoParams, ['downscale=0.5', 'block_size=7', 'mode=sgbm'])
    assert p.downscale == 0.5 and p.block_size == 7 and p.mode == 'sgbm'


@pytest.mark.parametrize('items, words', [(['downscal=0.5'], 'downscale'), (['downscale=9'], 'downscale'),
                                          (['downscale'], 'name=value')])
def test_assignment_mistakes_are_named(items, words):
    with pytest.raises(ConfigError, match=words):
        from_assignments(StereoParams, items)


def _declared_in(cls) -> dict:
    """{field name: [classes of cls's MRO whose body declares it]}."""
    out = {}
    for c in cls.__mro__:
        for name in vars(c).get('__annotations__', {}):
            out.setdefault(name, []).append(c.__name__)
    return out


def test_node_parameters_are_the_core_sets_plus_the_nodes_own():
    # Each parameter is declared once: the nodes' sets inherit the core ones (stereo, pair planner,
    # fusion) and add only their own, so nothing is copied field by field.
    from photogram_ros.core.fusion import FusionConfig
    from photogram_ros.core.pairs import PairCriteria
    from photogram_ros.nodes.map_node import MapParams
    from photogram_ros.nodes.stereo_node import StereoNodeParams
    assert issubclass(StereoNodeParams, StereoParams) and issubclass(StereoNodeParams, PairCriteria)
    assert issubclass(MapParams, FusionConfig)
    for cls in (StereoNodeParams, MapParams):
        twice = {k: v for k, v in _declared_in(cls).items() if len(v) > 1}
        assert not twice, twice
    own = set(vars(StereoNodeParams)['__annotations__'])
    assert own.isdisjoint(f.name for f in fields_of(StereoParams)) and 'relief_m' not in own
    assert {'ground_height_m', 'settle_keyframes'} <= own


@pytest.mark.parametrize('name', ['replay.yaml', 'onboard_gps.yaml', 'onboard_rtk.yaml', 'ground_station.yaml'])
def test_parameter_files_read_the_same_by_the_nodes_and_offline(name):
    # The node sets accept every name of the shipped files, and the offline products read the core
    # parameters with the same values as the nodes do.
    from conftest import ROOT
    from photogram_ros.commands.products import _core_params
    from photogram_ros.core.fusion import FusionConfig
    from photogram_ros.core.pairs import PairCriteria
    from photogram_ros.nodes.map_node import MapParams
    from photogram_ros.nodes.stereo_node import StereoNodeParams
    from photogram_ros.params import from_dict, load_params_file
    sections = load_params_file(str(ROOT / 'config' / name))
    for node, node_cls, core in (('stereo_node', StereoNodeParams, (StereoParams, PairCriteria)),
                                 ('map_node', MapParams, (FusionConfig,))):
        section = sections.get(node, {})
        full = from_dict(node_cls, section, node)
        for cls in core:
            offline = _core_params(cls, section, node)
            assert to_dict(offline) == {f.name: getattr(full, f.name) for f in fields_of(cls)}


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
