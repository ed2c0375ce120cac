"""The code's shape, read from its syntax: no class over 600 lines and no module over 900 under photogram_ros/, and
nothing outside core/ reaches into the adjuster (core/incremental.py IncrementalAT and its parts): no private
member, no container of its state (`at.kfs`, `at.block.registered`, ...), only the parts' public queries."""

import ast

import numpy as np
import pytest

from conftest import ROOT

MAX_CLASS_LINES = 600
MAX_MODULE_LINES = 900
# The adjuster's parts (attributes of IncrementalAT that are objects of their own, core/incremental.py).
PARTS = ('block', 'datum', 'adjustment', 'rounds', 'registration', 'segments')


def _package_files():
    return sorted((ROOT / 'photogram_ros').rglob('*.py'))


def test_no_class_or_module_too_long():
    files = _package_files()
    assert len(files) >= 100
    long_modules, long_classes = [], []
    for f in files:
        text = f.read_text()
        n = len(text.splitlines())
        if n > MAX_MODULE_LINES:
            long_modules.append(f'{f.relative_to(ROOT)}: {n} lines')
        for node in ast.walk(ast.parse(text, str(f))):
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > MAX_CLASS_LINES:
                long_classes.append(f'{f.relative_to(ROOT)}: {node.name} {node.end_lineno - node.lineno + 1} lines')
    assert not long_modules, long_modules
    assert not long_classes, long_classes


def _adjuster():
    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.core.incremental import IncrementalAT
    return IncrementalAT(PinholeCamera(640, 480, 500, 500, 320, 240, (0, 0, 0, 0, 0)))


def _containers(obj) -> set:
    """Names of `obj`'s attributes (and read-only views) that hold a container of state: a list, dict, set or the
    point store."""
    from photogram_ros.core.at_store import PointStore
    names = set(vars(obj)) | {n for n, v in vars(type(obj)).items() if isinstance(v, property)}
    return {n for n in names if isinstance(getattr(obj, n), (list, dict, set, frozenset, PointStore))}


def forbidden_reads(tree: ast.AST, containers: dict) -> list[str]:
    """`at.x` / `self.at.x` / `<...>.at.x` and `at.<part>.x` where x is private or one of `containers[owner]`
    (owner '' for the adjuster, else the part's name): each as 'line: expression'."""
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        recv = node.value
        owner = None
        if (isinstance(recv, ast.Name) and recv.id == 'at') or (isinstance(recv, ast.Attribute) and recv.attr == 'at'):
            owner = ''
        elif isinstance(recv, ast.Attribute) and recv.attr in PARTS and (
                (isinstance(recv.value, ast.Name) and recv.value.id == 'at')
                or (isinstance(recv.value, ast.Attribute) and recv.value.attr == 'at')):
            owner = recv.attr
        if owner is None:
            continue
        private = node.attr.startswith('_') and not node.attr.startswith('__')
        if private or node.attr in containers[owner]:
            out.append((node.lineno, node.col_offset, f'{node.lineno}: {ast.unparse(node)}'))
    return [r for _, _, r in sorted(out)]


def _adjusters_named_otherwise(tree: ast.AST) -> list[str]:
    """Bindings of an IncrementalAT (a call, or a parameter annotated with it) to a name other than `at` / `.at`:
    the check above follows the adjuster by that name."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call) and \
                ast.unparse(node.value.func).endswith('IncrementalAT'):
            out += [ast.unparse(t) for t in node.targets
                    if not ((isinstance(t, ast.Name) and t.id == 'at') or (isinstance(t, ast.Attribute) and t.attr == 'at'))]
        elif isinstance(node, ast.arg) and node.annotation is not None and \
                'IncrementalAT' in ast.unparse(node.annotation) and node.arg != 'at':
            out.append(node.arg)
        elif isinstance(node, ast.AnnAssign) and 'IncrementalAT' in ast.unparse(node.annotation) and not (
                isinstance(node.target, ast.Attribute) and node.target.attr == 'at'):
            out.append(ast.unparse(node.target))
    return out


@pytest.fixture(scope='module')
def containers():
    at = _adjuster()
    out = {'': _containers(at), **{p: _containers(getattr(at, p)) for p in PARTS}}
    # The block's containers are what the issue names: they must be among those the check forbids.
    assert {'kfs', 'registered', 'points', 'track_kfs'} <= out[''] & out['block']
    assert {'gnss_noise', 'gnss_rejected', 'solves', 'segment_joins'} <= out['']
    return out


def test_nothing_outside_core_reaches_into_the_adjuster(containers):
    files = [f for f in _package_files() if (ROOT / 'photogram_ros' / 'core') not in f.parents]
    assert len(files) >= 60
    bad, named = [], []
    for f in files:
        tree = ast.parse(f.read_text(), str(f))
        bad += [f'{f.relative_to(ROOT)}:{r}' for r in forbidden_reads(tree, containers)]
        named += [f'{f.relative_to(ROOT)}: {n}' for n in _adjusters_named_otherwise(tree)]
    assert not bad, bad
    assert not named, named


def test_the_check_finds_what_it_forbids(containers):
    """Each kind of reach the check forbids, and the public queries it lets through."""
    code = ('def f(at, stage):\n'
            '    a = at.kfs[-1]\n'
            '    b = stage.at.registered\n'
            '    c = at.block.points\n'
            '    d = at._full_adjusted_n\n'
            '    e = at.datum.rejected\n'
            '    ok = at.block.keyframe(-1), at.block.oriented(), at.block.n_points, at.georeferenced\n')
    found = forbidden_reads(ast.parse(code), containers)
    assert [r.split(': ')[1] for r in found] == ['at.kfs', 'stage.at.registered', 'at.block.points',
                                                 'at._full_adjusted_n', 'at.datum.rejected']
    named = _adjusters_named_otherwise(ast.parse('adj = IncrementalAT(cam)\nself.at = IncrementalAT(cam)\n'
                                                 'def g(x: IncrementalAT): pass\n'))
    assert named == ['adj', 'x']


def test_the_public_queries_answer_as_the_containers(containers):
    """The block's queries that readers outside core/ use give what its containers hold."""
    from photogram_ros.core.at_store import Keyframe
    at = _adjuster()
    b = at.block
    for k in range(3):
        kf = Keyframe(k, 10 * k, f'p{k}', np.array([k, k + 1, -1]), np.zeros((3, 2)), np.zeros((3, 2)),
                      np.ones(3, bool), None, None)
        b.add(kf)
        if k:
            kf.map_T_cam = np.eye(4)
            b.enrol(kf)
    b.points.set_many(np.array([1, 2, -1]), np.arange(9.0).reshape(3, 3))
    assert b.n_keyframes == 3 and b.oriented() == [1, 2] and b.oriented(last=1) == [2]
    assert b.keyframe(-1).name == 'p2' and b.last_oriented().name == 'p2'
    assert b.oriented_names() == ['p1', 'p2'] and set(b.poses_by_name()) == {'p1', 'p2'}
    assert b.tie_point_ids().tolist() == [1, 2]
    assert b.tie_point_ids(hot=True).tolist() == [1, 2]     # tracks 1, 2, 3 hot; 3 has no point
    assert b.tie_point_cloud().shape == (2, 3) and b.n_points == 3
    assert b.point_ids() == [1, 2, -1]


# Private names of the standard library that its own documentation tells callers to use.
STDLIB_PRIVATE_OK = {'os._exit', 'argparse._HelpAction', 'argparse._VersionAction'}


def test_nothing_reads_another_objects_private_members():
    """`x._name` only on `self` / `cls`: an object's private members are its own (a public method says what
    another may read or set)."""
    found = []
    for f in _package_files():
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if not (isinstance(node, ast.Attribute) and node.attr.startswith('_') and not node.attr.startswith('__')):
                continue
            if isinstance(node.value, ast.Name) and node.value.id in ('self', 'cls'):
                continue
            if ast.unparse(node) not in STDLIB_PRIVATE_OK:
                found.append(f'{f.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}')
    assert found == []
