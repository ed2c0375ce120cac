"""How many GNSS position types the code defines, and where (issue #46: one fix type across the readers).

Read from the source, nothing run: every class under photogram_ros/ whose own fields (annotations, or attributes
set in __init__) hold both `lat_deg` and `lon_deg`, or a `cov_enu_m2` / `var_enu_m2` beside a height, is a type
that carries a GNSS position; per module, those classes, and which modules import core/gnss_fix.py. One JSON line
for the tree given (`--tree`, default this checkout; give an exported older commit to compare):
    .venv/bin/python bench/ppk_fix_types.py [--tree DIR] [--label LABEL] [--out bench/results/ppk_fix_types_<commit>.jsonl]
Position records that are not fixes are listed apart (`not_a_fix`: a camera placed at an exposure, a surveyed
target, a local frame's origin): the names are this bench's reading, given in NOT_A_FIX. core/exposure_positions.py
AntennaTrack counts as a fix type: a trajectory's fixes in columns.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

# Classes with a position that are other things than a GNSS fix: counted apart.
NOT_A_FIX = {'PlacedExposure', 'SurveyedTarget', 'LocalFrame'}


def _fields(cls: ast.ClassDef) -> set[str]:
    names = set()
    for node in cls.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        if isinstance(node, ast.FunctionDef) and node.name == '__init__':
            for sub in ast.walk(node):
                targets = sub.targets if isinstance(sub, ast.Assign) else [sub.target] if isinstance(
                    sub, ast.AnnAssign) else []
                for t in targets:
                    for el in (t.elts if isinstance(t, ast.Tuple) else [t]):
                        if isinstance(el, ast.Attribute) and isinstance(el.value, ast.Name) and el.value.id == 'self':
                            names.add(el.attr)
    return names


def position_types(tree: Path) -> dict:
    pkg = tree / 'photogram_ros'
    fixes, others, importers = {}, {}, []
    for path in sorted(pkg.rglob('*.py')):
        rel = str(path.relative_to(tree))
        try:
            mod = ast.parse(path.read_text())
        except (SyntaxError, UnicodeDecodeError):
            continue
        for node in ast.walk(mod):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [a.name for a in node.names]
                src = getattr(node, 'module', None) or ''
                if 'gnss_fix' in src or any('gnss_fix' in n for n in names):
                    importers.append(rel)
            if not isinstance(node, ast.ClassDef):
                continue
            f = _fields(node)
            has_pos = {'lat_deg', 'lon_deg'} <= f or (bool(f & {'cov_enu_m2', 'var_enu_m2'}) and bool(
                f & {'h_m', 'ecef_m'}))
            if has_pos:
                (others if node.name in NOT_A_FIX else fixes).setdefault(rel, []).append(node.name)
    return {'fix_types': {k: sorted(v) for k, v in fixes.items()},
            'n_fix_types': sum(len(v) for v in fixes.values()), 'n_modules_defining': len(fixes),
            'not_a_fix': {k: sorted(v) for k, v in others.items()},
            'modules_importing_gnss_fix': sorted(set(importers)),
            'n_modules_importing_gnss_fix': len(set(importers))}


def main(argv=None) -> int:
    from bench.machine import ResultWriter, tree_state
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--tree', default=str(HERE.parent), help='the checkout to read (default: this one)')
    ap.add_argument('--label', default='', help='what the tree is (e.g. "before: 6030be7")')
    ap.add_argument('--out', help='JSON lines file (default bench/results/ppk_fix_types_<commit>.jsonl)')
    ap.add_argument('--append', action='store_true', help='add to the file instead of starting it afresh')
    a = ap.parse_args(argv)
    commit = tree_state()['commit']
    out = a.out or str(HERE / 'results' / f'ppk_fix_types_{commit[:7]}.jsonl')
    w = ResultWriter(out, 'ppk_fix_types', ['photogram_ros'], fresh=not a.append, echo=True)
    w.write({'tree': a.label or a.tree, **position_types(Path(a.tree))})
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
