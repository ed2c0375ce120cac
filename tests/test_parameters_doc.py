"""docs/parameters.md's tables are the parameter dataclasses, rendered (scripts/render_parameters.py)."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _renderer():
    spec = importlib.util.spec_from_file_location('render_parameters', ROOT / 'scripts' / 'render_parameters.py')
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_parameters_page_equals_the_dataclasses():
    r = _renderer()
    assert (ROOT / 'docs' / 'parameters.md').read_text() == r.render(), \
        'docs/parameters.md is stale: run .venv/bin/python scripts/render_parameters.py'


def test_every_node_parameter_has_a_row():
    import importlib
    import dataclasses

    from photogram_ros.nodes.graph import NODES, PARAMS
    page = (ROOT / 'docs' / 'parameters.md').read_text()
    for role, cls_name in PARAMS.items():
        cls = getattr(importlib.import_module(NODES[role][0]), cls_name)
        for f in dataclasses.fields(cls):
            if 'description' in f.metadata:
                assert f'| `{f.name}` |' in page, f'{NODES[role][2]}.{f.name} missing from docs/parameters.md'
