"""Renders docs/parameters.md's "Every parameter" tables from the nodes' parameter dataclasses.

    .venv/bin/python scripts/render_parameters.py          # rewrite docs/parameters.md
    .venv/bin/python scripts/render_parameters.py --check  # exit 1 when the committed page differs

tests/test_parameters_doc.py runs the check, so a parameter added, removed or changed in a dataclass fails
the tests until the page is rendered again.
"""

from __future__ import annotations

import dataclasses
import importlib
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / 'docs' / 'parameters.md'
START = '### camera_node'   # the generated part runs from the first node's heading to the end of the page
STATION = ('photogram_ros.nodes.ground_station', 'GroundStationParams', 'ground_station',
           ' (`photogram-ros ground-station`; its options override these)')


def _cell(text: str) -> str:
    return str(text).replace('|', '\\|').replace('\n', ' ')


def _range(meta: dict) -> str:
    if meta.get('choices'):
        return ', '.join(str(c) for c in meta['choices'])
    lo, hi = meta.get('min'), meta.get('max')
    if lo is None and hi is None:
        return ''
    return f'{"" if lo is None else lo} .. {"" if hi is None else hi}'


def node_table(module: str, cls_name: str, node: str, note: str = '') -> str:
    from photogram_ros.params import fields_of
    cls = getattr(importlib.import_module(module), cls_name)
    rows = [f'### {node}', '', f'`{module}.{cls_name}`{note}', '', '| parameter | default | range | meaning |',
            '|---|---|---|---|']
    for f in fields_of(cls):
        d = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        rows.append(f'| `{f.name}` | `{_cell(repr(d))}` | {_cell(_range(f.metadata))} | '
                    f'{_cell(f.metadata["description"])} |')
    return '\n'.join(rows) + '\n'


def render() -> str:
    from photogram_ros.nodes.graph import NODES, PARAMS
    parts = [node_table(NODES[role][0], cls, NODES[role][2]) for role, cls in PARAMS.items()]
    parts.append(node_table(*STATION))
    head = PAGE.read_text().split(START, 1)[0]
    return head + '\n'.join(parts)


def main(argv: list[str]) -> int:
    text = render()
    if '--check' in argv:
        if PAGE.read_text() != text:
            print('docs/parameters.md differs from the parameter dataclasses: run '
                  '.venv/bin/python scripts/render_parameters.py')
            return 1
        return 0
    PAGE.write_text(text)
    return 0


if __name__ == '__main__':
    sys.path.insert(0, str(ROOT))
    sys.exit(main(sys.argv[1:]))
