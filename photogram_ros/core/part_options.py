"""The adjuster's parts take options of their own: each part declares a frozen dataclass of exactly the
parameters it reads (`param(...)` with description and range, params.py), next to the code that reads them.

`IncrementalOptions` (core/incremental.py), the user-facing container the ROS parameters and CLI flags are made
from, declares its fields with `declared(PartOptions, name)`, so a parameter's description and range are written
once, in the part that uses it; `options_for(PartOptions, container)` makes a part's options from the container's
values (a nested part's options too: `nested(PartOptions)`).
"""

from __future__ import annotations

import dataclasses
from typing import get_type_hints

from photogram_ros.params import fields_of, param, validate


def declared(cls, name: str):
    """A `param(...)` field with the default, description and range that part options `cls` declare for `name`."""
    f = next(f for f in fields_of(cls) if f.name == name)
    default = f.default_factory() if f.default is dataclasses.MISSING else f.default
    m = f.metadata
    return param(default, m['description'], min=m['min'], max=m['max'], choices=m['choices'])


def nested(cls):
    """A field holding the options of a part that this part makes (its own defaults unless `options_for` fills it)."""
    return dataclasses.field(default_factory=cls, metadata={'part': cls})


def options_for(cls, source):
    """Part options `cls` made from the values of the same names in `source` (validated when made)."""
    values = {}
    for f in dataclasses.fields(cls):
        part = f.metadata.get('part')
        values[f.name] = options_for(part, source) if part is not None else getattr(source, f.name)
    return cls(**values)


def check(obj) -> None:
    """Validate frozen part options `obj` (params.py `validate`: ranges, types; ConfigError when out), an int
    given for a float field taken as that float."""
    hints = get_type_hints(type(obj))
    for f in fields_of(type(obj)):
        v = getattr(obj, f.name)
        if hints.get(f.name) is float and isinstance(v, int) and not isinstance(v, bool):
            object.__setattr__(obj, f.name, float(v))
    validate(obj)
