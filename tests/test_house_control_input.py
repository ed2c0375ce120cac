"""`replay`/`run --gcp`: the control file read once by the command into one typed object
(io/control_file.ControlInput), handed through the graph to the bundle node's adjustment stage, never as a ROS
parameter override; a child process (--processes 2) rebuilds the same object from its values, without the file."""

from __future__ import annotations

import pytest

from photogram_ros.core.control import ControlSet
from photogram_ros.io.control_file import ControlInput
from photogram_ros.nodes.graph import GraphSpec, child_argument, child_spec, make_node, role_values, set_by_command
from test_cli_run_control import _parse, _targets


class _Handed(Exception):
    """Raised by the stand-in of run_replay with what the command handed it."""


def test_replay_hands_the_control_it_read_to_the_graph_not_as_a_parameter(tmp_path, monkeypatch):
    from photogram_ros.commands import replay
    from photogram_ros.nodes import node_main, replay_session, ros_domain

    def fake_run_replay(opts, context=None):
        raise _Handed(opts)
    monkeypatch.setattr(replay_session, 'run_replay', fake_run_replay)
    monkeypatch.setattr(node_main, 'init_ros', lambda: None)
    monkeypatch.setattr(ros_domain, 'use_domain', lambda domain: None)
    monkeypatch.setattr(ros_domain, 'shared_domain', lambda domain: domain)   # no other replay's domain held here
    (tmp_path / 'photos').mkdir()
    f = _targets(tmp_path)
    a = _parse(['replay', str(tmp_path / 'photos'), '--out', str(tmp_path / 'out'), '--gcp', str(f), '--check', 'P4',
                '--gcp-heights', 'ellipsoidal', '--domain', '60', '--quiet'])
    with pytest.raises(_Handed) as got:
        replay.run(a)
    opts = got.value.args[0]
    assert isinstance(opts.control, ControlInput) and isinstance(opts.control.targets, ControlSet)
    assert opts.control.parameters() == {'control_file': str(f.resolve()), 'check_names': 'P4',
                                         'control_heights': 'ellipsoidal'}
    assert opts.control.targets.check_names == ['CHK01', 'P4']
    # Not a ROS parameter override: nothing of the control file in the overrides of any node.
    assert not any(k in v for v in opts.extra.values() for k in ('control_file', 'check_names', 'control_heights'))


def test_the_graph_hands_the_object_to_the_bundle_node(tmp_path, monkeypatch):
    from photogram_ros.nodes import bundle_node
    made = {}

    class FakeBundleNode:
        def __init__(self, overrides=None, control=None, **kwargs):
            made.update(overrides=overrides, control=control)
    monkeypatch.setattr(bundle_node, 'BundleNode', FakeBundleNode)
    control = ControlInput.read(_targets(tmp_path), ['P4'])
    spec = GraphSpec(roles=('tracker', 'bundle'), control=control)
    make_node('bundle', role_values(spec, 'bundle'), spec)
    assert made['control'] is control.targets and 'control_file' not in made['overrides']
    # The tracker's target search and the run's record name the same file, as the bundle node's parameters would.
    assert role_values(spec, 'tracker')['control_file'] == control.file
    assert set_by_command(spec) == {'bundle': control.parameters()}


def test_a_child_process_rebuilds_the_same_control_without_the_file(tmp_path):
    f = _targets(tmp_path)
    control = ControlInput.read(f, ['P4'], 'orthometric')
    spec = GraphSpec(roles=('bundle', 'stereo'), extra={'stereo': {'max_keyframes': 40}}, control=control)
    f.unlink()   # the child does not read the file again
    back = child_spec(child_argument(spec))
    assert back.control == control and back.roles == ('bundle', 'stereo') and back.child_roles == ()
    assert back.extra == {'stereo': {'max_keyframes': 40}}
    a, b = control.targets, back.control.targets
    assert [vars(t) for t in b.targets] == [vars(t) for t in a.targets]
    assert (b.crs, b.source, b.file_heights, b.check_names) == (a.crs, a.source, a.file_heights, a.check_names)
    assert child_spec(child_argument(GraphSpec(roles=('map',)))).control is None


def test_the_stage_takes_the_object_in_place_of_its_parameters(tmp_path):
    from photogram_ros.params import from_dict
    from photogram_ros.stages.adjustment import AdjustmentParams, AdjustmentStage
    control = ControlInput.read(_targets(tmp_path), ['P4'])
    stage = AdjustmentStage(from_dict(AdjustmentParams, {}), control=control.targets)
    assert stage.control is control.targets and stage.live is not None
    # A ROS user's parameter file: the stage reads control_file itself, to the same targets.
    own = AdjustmentStage(from_dict(AdjustmentParams, control.parameters()))
    assert [vars(t) for t in own.control.targets] == [vars(t) for t in control.targets.targets]
