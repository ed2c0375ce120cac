"""Declare a parameter dataclass on an rclpy node, with descriptors and ranges, and read it back."""

from __future__ import annotations

import dataclasses

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

from photogram_ros.errors import ConfigError
from photogram_ros.nodes.qos import is_override
from photogram_ros.params import fields_of, from_dict


def declare(node: Node, cls, overrides: dict | None = None):
    """Declare every field of `cls` on `node` and return the validated dataclass.

    Overrides given to the node (params file, --ros-args -p) that name no field are errors: a
    mistyped parameter must not silently fall back to its default. Every parameter is read-only:
    the node reads them once, so `ros2 param set` is refused with a reason instead of accepted
    and ignored.
    """
    values = {}
    for f in fields_of(cls):
        default = f.default if f.default_factory is dataclasses.MISSING else f.default_factory()
        if overrides and f.name in overrides:
            default = overrides[f.name]
        desc = ParameterDescriptor(description=f.metadata['description'], read_only=True)
        lo, hi = f.metadata['min'], f.metadata['max']
        if isinstance(default, bool) or (lo is None and hi is None):
            pass
        elif isinstance(default, int):
            desc.integer_range = [IntegerRange(from_value=int(lo if lo is not None else -2**31),
                                               to_value=int(hi if hi is not None else 2**31 - 1), step=0)]
        elif isinstance(default, float):
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo if lo is not None else -1e300),
                                                            to_value=float(hi if hi is not None else 1e300),
                                                            step=0.0)]
        try:
            p = node.declare_parameter(f.name, default, desc)
        except Exception as exc:  # rclpy raises several types for bad types/ranges
            raise ConfigError(f'{node.get_name()}: parameter {f.name!r}: {exc}') from exc
        values[f.name] = p.value
    given = set(getattr(node, '_parameter_overrides', {}) or {}) | set(overrides or {})
    # rclpy's QoS overrides (nodes/qos.py) are declared when their publisher or subscription is made.
    unknown = sorted(k for k in given if k not in values and k != 'use_sim_time' and not is_override(k))
    if unknown:
        from_dict(cls, {k: None for k in unknown}, where=node.get_name())  # raises with suggestions
    return from_dict(cls, values, where=node.get_name())
