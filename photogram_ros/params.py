"""Parameters: declared once as dataclass fields with description and range, validated in one place.

A node's parameter set is a dataclass whose fields are made with `param(...)`. The ROS adapter
(`nodes/ros_params.py`) declares exactly these fields as ROS parameters with descriptors; the
command line and YAML files go through `from_dict`, which rejects unknown or mistyped names.
No ROS import here, so the core and tests can use the same dataclasses.
"""

from __future__ import annotations

import dataclasses
import difflib
from typing import Any, get_type_hints

from photogram_ros.errors import ConfigError


def param(default: Any, description: str, *, min: float | None = None, max: float | None = None,
          choices: tuple | None = None):
    """A parameter field: default, what it means (with units), and its valid range or choices."""
    meta = {'description': description, 'min': min, 'max': max, 'choices': choices}
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def fields_of(cls) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if 'description' in f.metadata]


def validate(obj) -> None:
    """Raise ConfigError naming the parameter whose value is out of range or of the wrong type."""
    hints = get_type_hints(type(obj))
    for f in fields_of(type(obj)):
        v = getattr(obj, f.name)
        want = hints.get(f.name)
        if want is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
            setattr(obj, f.name, v)
        if want in (int, float, str, bool) and not (type(v) is want):
            raise ConfigError(f'parameter {f.name!r} must be {want.__name__}, got {v!r}')
        lo, hi, choices = f.metadata['min'], f.metadata['max'], f.metadata['choices']
        if lo is not None and v < lo or hi is not None and v > hi:
            raise ConfigError(f'parameter {f.name!r} = {v} is outside [{lo}, {hi}]: {f.metadata["description"]}')
        if choices is not None and v not in choices:
            raise ConfigError(f'parameter {f.name!r} = {v!r} is not one of {list(choices)}')
    check = getattr(obj, 'check', None)
    if callable(check):
        check()


def from_dict(cls, values: dict, where: str = ''):
    """Build and validate `cls` from a mapping; unknown names are errors with a suggestion."""
    names = [f.name for f in fields_of(cls)]
    unknown = [k for k in values if k not in names]
    if unknown:
        hints = []
        for k in unknown:
            close = difflib.get_close_matches(k, names, n=1)
            hints.append(f'{k!r}' + (f' (did you mean {close[0]!r}?)' if close else ''))
        raise ConfigError(f'unknown parameter {", ".join(hints)}{" in " + where if where else ""}; '
                          f'{cls.__name__} takes {names}')
    obj = cls(**values)
    validate(obj)
    return obj


def from_assignments(cls, items: list[str], where: str = ''):
    """['name=value', ...] (command-line overrides) -> validated `cls`; values take the type of the default."""
    defaults = cls()
    values = {}
    for item in items:
        if '=' not in item:
            raise ConfigError(f'override {item!r} must look like name=value')
        k, v = item.split('=', 1)
        values[k] = type(getattr(defaults, k))(v) if hasattr(defaults, k) else v
    return from_dict(cls, values, where)


def floats(text: str, what: str, n: int) -> tuple:
    """'0.02,0.02,0.03' -> (0.02, 0.02, 0.03): `n` numbers separated by commas (an option's value, named
    `what` in the ConfigError otherwise)."""
    try:
        v = tuple(float(s) for s in text.split(','))
    except ValueError:
        v = ()
    if len(v) != n:
        raise ConfigError(f'{what} takes {n} numbers separated by commas, got {text!r}')
    return v


def to_dict(obj) -> dict:
    return {f.name: getattr(obj, f.name) for f in fields_of(type(obj))}


def load_params_file(path: str) -> dict:
    """ROS 2 params file (`node: {ros__parameters: {...}}`, wildcards allowed) -> {node: {name: value}}."""
    import yaml
    try:
        with open(path) as f:
            doc = yaml.safe_load(f) or {}
    except OSError as exc:
        raise ConfigError(f'cannot read parameter file {path}: {exc}') from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f'parameter file {path} is not valid YAML: {exc}') from exc
    out = {}
    for node, body in doc.items():
        if not isinstance(body, dict) or 'ros__parameters' not in body:
            raise ConfigError(f'{path}: section {node!r} needs a ros__parameters mapping')
        out[str(node).strip('/')] = dict(body['ros__parameters'] or {})
    return out
