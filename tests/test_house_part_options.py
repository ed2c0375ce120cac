"""The adjuster's parts take options of their own (core/part_options.py): each part holds a frozen, validated
options object of exactly the parameters its module reads, never the whole IncrementalOptions."""

import dataclasses
import inspect
import re

import pytest

from photogram_ros.core import at_block, at_freeze, at_problem, at_register, at_segments, at_two_view
from photogram_ros.core.at_block import BlockOptions
from photogram_ros.core.at_freeze import FreezeOptions
from photogram_ros.core.at_problem import ProblemOptions
from photogram_ros.core.at_register import RegistrationOptions
from photogram_ros.core.at_segments import SegmentOptions
from photogram_ros.core.at_two_view import TwoViewOptions
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core import gnss_datum, gnss_rounds
from photogram_ros.core.gnss_datum import DatumOptions
from photogram_ros.core.gnss_rounds import GnssRoundsOptions
from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions
from photogram_ros.errors import ConfigError
from photogram_ros.params import fields_of

PARTS = {BlockOptions: at_block, FreezeOptions: at_freeze, ProblemOptions: at_problem,
         RegistrationOptions: at_register, TwoViewOptions: at_two_view, SegmentOptions: at_segments,
         DatumOptions: gnss_datum, GnssRoundsOptions: gnss_rounds}


def test_each_part_holds_its_own_options_not_the_container():
    opt = IncrementalOptions(window_size=7, max_reprojection_px=3.5, min_facing=0.4, segments=False, max_thaws=2)
    at = IncrementalAT(PinholeCamera(1000, 800, 900.0, 900.0, 500.0, 400.0), opt)
    held = {'block': (at.block.opt, BlockOptions), 'freezer': (at.block.freezer.opt, FreezeOptions),
            'adjustment': (at.adjustment.opt, ProblemOptions),
            'registration': (at.registration.opt, RegistrationOptions),
            'two view': (at.registration.opt.two_view, TwoViewOptions),
            'segments': (at.segments.opt, SegmentOptions),
            'rounds': (at.rounds.opt, GnssRoundsOptions)}
    for part, (got, want) in held.items():
        assert type(got) is want, f'{part} holds {type(got).__name__}, not {want.__name__}'
        assert not isinstance(got, IncrementalOptions)
        # ... with the container's values.
        for f in fields_of(want):
            assert getattr(got, f.name) == getattr(opt, f.name), (part, f.name)
    assert at.block.freezer.opt.window_size == at.adjustment.opt.window_size == 7
    assert at.registration.opt.two_view.min_facing == 0.4 and not at.segments.opt.segments
    # After a break the block's freezing starts again with the same options.
    at.block.give_up_oriented()
    assert type(at.block.freezer.opt) is FreezeOptions and at.block.freezer.opt.max_thaws == 2


def test_a_part_holds_only_options_its_module_reads():
    for cls, module in PARTS.items():
        src = inspect.getsource(module).replace(inspect.getsource(cls), '')
        for f in dataclasses.fields(cls):
            assert re.search(rf'\.{f.name}\b', src), f'{cls.__name__}.{f.name} is not read in {module.__name__}'


def test_every_part_option_is_the_containers_parameter_declared_once():
    container = {f.name: f for f in fields_of(IncrementalOptions)}
    for cls in PARTS:
        for f in fields_of(cls):
            c = container[f.name]
            assert c.metadata == f.metadata and c.default == f.default, (cls.__name__, f.name)


def test_part_options_are_frozen_and_validated_when_made():
    with pytest.raises(dataclasses.FrozenInstanceError):
        ProblemOptions().window_size = 3
    with pytest.raises(ConfigError, match='window_size'):
        ProblemOptions(window_size=1)
    with pytest.raises(ConfigError, match='min_facing'):
        TwoViewOptions(min_facing=2.0)
    with pytest.raises(ConfigError, match='loss'):
        IncrementalOptions(loss='l3').part(ProblemOptions)
    assert ProblemOptions(loss_scale_px=2).loss_scale_px == 2.0 and type(ProblemOptions(loss_scale_px=2).loss_scale_px) is float


def test_nothing_outside_core_reads_the_adjusters_options():
    from pathlib import Path
    root = Path(__file__).resolve().parents[1] / 'photogram_ros'
    readers = [f'{p.relative_to(root)}:{i}' for p in sorted(root.rglob('*.py')) if p.parts[len(root.parts)] != 'core'
               for i, line in enumerate(p.read_text().splitlines(), 1)
               if re.search(r'\b(at|adjuster|self\.at|self\.adjuster)\.(opt|block\.opt|adjustment\.opt)\b', line)]
    assert readers == []
