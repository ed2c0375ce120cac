"""The figures gates compare with: lines of the result files in bench/results, which the benches wrote.
A gate names its result file beside it and holds the figure within 1.5x (common rule)."""

from __future__ import annotations

import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / 'bench' / 'results'


def figure(result_file: str, **where) -> dict:
    """The last line of bench/results/`result_file` whose keys equal `where` (dotted keys reach into dicts)."""
    found = None
    for line in (RESULTS / result_file).read_text().splitlines():
        if not line.strip():
            continue
        row = json.loads(line)
        ok = True
        for k, v in where.items():
            x = row
            for part in k.split('.'):
                x = x.get(part) if isinstance(x, dict) else None
            ok = ok and x == v
        if ok:
            found = row
    if found is None:
        raise LookupError(f'no line with {where} in bench/results/{result_file}')
    return found


def newest_figure(pattern: str, **where) -> tuple[str, dict]:
    """(file name, line): the line bench/render_figures.py renders for a figure of the result files matching
    `pattern` (a glob under bench/results, e.g. 'real_surveys*.jsonl') and `where`: of the files holding such a
    line, the one measured at the latest commit (git's commit time), its last such line. A gate that reads its
    figure here moves with the newest result file committed, and names that file."""
    import sys
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from bench.render_figures import Figure, newest
    src = newest(Figure(('gate',), pattern, dict(where)))
    if src is None:
        raise LookupError(f'no line with {where} in bench/results/{pattern}')
    return src.path.name, src.line
