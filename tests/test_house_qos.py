"""nodes/qos.py: the project's QoS profiles, and a topic's QoS overridden from the node's parameters (rclpy's
qos_overrides, as ros2/demos' quality_of_service_demo does it)."""

import pytest


def test_the_profiles_are_what_the_nodes_used():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    from photogram_ros.nodes import qos
    assert qos.reliable(100) == QoSProfile(depth=100)                 # rclpy's default: reliable, keep last, volatile
    assert qos.diagnostics() == qos.clock() == QoSProfile(depth=10)   # what a bare depth 10 gives
    assert qos.sensor_data().reliability == ReliabilityPolicy.BEST_EFFORT and qos.sensor_data().depth == 5
    assert qos.best_effort(100).depth == 100
    assert qos.latched().durability == DurabilityPolicy.TRANSIENT_LOCAL and qos.latched().depth == 1
    assert qos.keep_all().history == HistoryPolicy.KEEP_ALL
    assert qos.keyframes().depth == 20 and qos.keyframes().reliability == ReliabilityPolicy.RELIABLE
    assert qos.reliable(7) is not qos.reliable(7)                     # an override changes its own copy only


def test_a_topic_qos_is_overridden_from_the_parameters(rclpy_context):
    from rclpy.parameter import Parameter
    from rclpy.qos import ReliabilityPolicy

    from photogram_ros.nodes.mavlink_node import MavlinkNode
    overrides = [Parameter('qos_overrides./gps/fix.publisher.reliability', value='best_effort'),
                 Parameter('qos_overrides./gps/fix.publisher.depth', value=7)]
    node = MavlinkNode(context=rclpy_context, parameter_overrides=overrides)
    try:
        (fix,) = node.get_publishers_info_by_topic('/gps/fix')            # as the graph sees it
        assert fix.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
        assert node.pub_fix.qos_profile.depth == 7                       # (discovery carries no depth)
        (att,) = node.get_publishers_info_by_topic('/mavlink/attitude')    # the others as they were
        assert att.qos_profile.reliability == ReliabilityPolicy.RELIABLE and node.pub_att.qos_profile.depth == 100
        assert node.get_parameter('qos_overrides./mavlink/attitude.publisher.depth').value == 100
    finally:
        node.destroy_node()


def test_a_mistyped_parameter_is_still_refused_beside_the_overrides(rclpy_context):
    from rclpy.parameter import Parameter

    from photogram_ros.errors import ConfigError
    from photogram_ros.nodes.mavlink_node import MavlinkNode
    overrides = [Parameter('qos_overrides./gps/fix.publisher.depth', value=7),
                 Parameter('max_fix_age_sec', value=2.0)]
    with pytest.raises(ConfigError, match='max_fix_age_sec'):
        MavlinkNode(context=rclpy_context, parameter_overrides=overrides)


def test_no_qos_profile_is_built_outside_the_qos_module():
    """Every node takes its profiles from nodes/qos.py (one place to read and override them)."""
    import re

    from conftest import ROOT
    hand_built = [f'{p.relative_to(ROOT)}:{n}' for p in sorted((ROOT / 'photogram_ros').rglob('*.py'))
                  if p.name != 'qos.py'
                  for n, line in enumerate(p.read_text().splitlines(), 1) if re.search(r'\bQoSProfile\(', line)]
    assert hand_built == []
    from photogram_ros.nodes import qos
    assert qos.tf_static() == qos.latched() and qos.tf().depth == 100
