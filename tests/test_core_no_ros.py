"""photogram_ros.core must import and work with no ROS package importable; the package's imports, drawn as a graph,
point down the layers only (docs/architecture.md) and go round in no circle."""

import ast
import subprocess
import sys
import textwrap

from conftest import ROOT

BLOCKER = textwrap.dedent('''
    import importlib.abc, sys
    ROS = ('rclpy', 'rosidl', 'rcl_interfaces', 'builtin_interfaces', 'std_msgs', 'sensor_msgs',
           'geometry_msgs', 'nav_msgs', 'diagnostic_msgs', 'stereo_msgs', 'visualization_msgs',
           'rosgraph_msgs', 'lifecycle_msgs', 'rpyutils', 'ament_index_python')
    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split('.')[0] in ROS:
                raise ImportError(f'ROS package {name} imported from core')
    sys.meta_path.insert(0, Block())
    import pkgutil, importlib
    import photogram_ros.core as core
    names = [m.name for m in pkgutil.walk_packages(core.__path__, 'photogram_ros.core.')]
    for n in names:
        importlib.import_module(n)
    loaded = [m for m in sys.modules if m.split('.')[0] in ROS]
    assert not loaded, loaded
    from photogram_ros.core.camera import PinholeCamera
    import numpy as np
    cam = PinholeCamera(640, 480, 500, 500, 320, 240, (0.1, 0, 0, 0, 0))
    uv, ok = cam.project(np.array([[0.1, 0.2, 1.0]]))
    print('OK', len(names))
''')


def test_core_imports_without_ros():
    r = subprocess.run([sys.executable, '-c', BLOCKER], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    n_modules = int(r.stdout.split()[-1])
    assert n_modules >= 4


# The layers from the bottom (docs/architecture.md): a module may import its own layer and those below it only.
# By the module's first name under photogram_ros ('' is the package's own __init__).
LAYERS = [('', 'errors', 'params', 'package_files'), ('core',), ('msgs',), ('io',), ('sim',), ('stages',), ('web',), ('nodes',),
          ('commands',), ('cli',)]
LAYER = {name: i for i, names in enumerate(LAYERS) for name in names}


def _module_name(path) -> str:
    rel = path.relative_to(ROOT).with_suffix('')
    parts = list(rel.parts[:-1] if rel.name == '__init__' else rel.parts)
    return '.'.join(parts)


def import_graph() -> dict:
    """{module: set of the package's modules it imports} over every .py under photogram_ros/, lazy imports inside
    functions too: `from a.b import c` is an arrow to module a.b.c when that is a module, else to a.b; an import of
    a module's own parent package (which Python runs first anyway) is no arrow."""
    files = {_module_name(f): f for f in (ROOT / 'photogram_ros').rglob('*.py')}

    def resolve(name):
        while name and name not in files:
            name = name.rpartition('.')[0]
        return name or None

    graph = {}
    for mod, f in files.items():
        out = set()
        package = mod if f.name == '__init__.py' else mod.rpartition('.')[0]
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ''
                if node.level:
                    up = package.split('.')[:len(package.split('.')) - node.level + 1]
                    base = '.'.join(up + ([base] if base else []))
                names = [f'{base}.{a.name}' if f'{base}.{a.name}' in files else base for a in node.names]
            else:
                continue
            for n in names:
                t = resolve(n) if n.startswith('photogram_ros') else None
                if t is not None and t != mod and not mod.startswith(t + '.'):
                    out.add(t)
        graph[mod] = out
    return graph


def _layer(mod: str) -> int:
    parts = mod.split('.')
    return LAYER[parts[1] if len(parts) > 1 else '']


def _cycles(graph: dict) -> list[set]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = set()
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.add(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(comp)
    return out


def test_every_module_has_a_layer():
    graph = import_graph()
    assert len(graph) >= 100
    unplaced = [m for m in graph if (m.split('.') + [''])[1] not in LAYER]
    assert not unplaced, f'place these in LAYERS (and docs/architecture.md): {unplaced}'


def test_no_import_arrow_points_up_the_layers():
    graph = import_graph()
    up = sorted(f'{m} -> {t}' for m, ts in graph.items() for t in ts if _layer(t) > _layer(m))
    assert not up, up


def test_no_import_cycle():
    cycles = _cycles(import_graph())
    assert not cycles, cycles


def test_the_photo_readers_form_no_circle():
    """io/geo_txt.py is the one geo.txt reader, below io/image_source.py and io/photo_block.py: the photo readers
    import down (photo_block -> camera_events -> image_source -> geo_txt) and never back."""
    graph = import_graph()
    readers = {f'photogram_ros.io.{m}' for m in ('camera_events', 'image_source', 'photo_block', 'geo_txt')}
    assert not [c for c in _cycles(graph) if c & readers]
    assert 'photogram_ros.io.geo_txt' in graph['photogram_ros.io.image_source']
    assert not graph['photogram_ros.io.geo_txt'] & readers


def test_the_trajectory_readers_import_their_base_not_the_registry():
    """io/trajectory_formats.py's registry imports the per-format readers; they import io/trajectory_base.py
    (the reader protocol and shared helpers) and never the registry back."""
    graph = import_graph()
    io = 'photogram_ros.io.'
    readers = {io + m for m in ('rtklib_pos', 'trajectory_csv', 'trajectory_grafnav')}
    assert readers <= graph[io + 'trajectory_formats']
    for r in readers - {io + 'rtklib_pos'}:
        assert io + 'trajectory_base' in graph[r]
    for r in readers | {io + 'trajectory_base'}:
        assert io + 'trajectory_formats' not in graph[r], r


def test_the_graph_sees_what_the_checks_need():
    """The checks above could fail: a lazy arrow up and a circle of two are found."""
    graph = {'photogram_ros.core.a': {'photogram_ros.io.b'}, 'photogram_ros.io.b': {'photogram_ros.core.a'},
             'photogram_ros.io.c': set()}
    assert _cycles(graph) == [{'photogram_ros.core.a', 'photogram_ros.io.b'}]
    assert _layer('photogram_ros.io.b') > _layer('photogram_ros.core.a')
    assert _layer('photogram_ros.cli') > _layer('photogram_ros.commands.run') > _layer('photogram_ros.nodes.graph')
    real = import_graph()
    assert 'photogram_ros.core.incremental' in real['photogram_ros.stages.adjustment']
    assert 'photogram_ros.core.triangulation' in real['photogram_ros.core.bundle']   # a lazy import, in a function
    # `from photogram_ros.core.bundle import losses` is an arrow to the submodule, not to its package.
    assert 'photogram_ros.core.bundle.losses' in real['photogram_ros.core.bundle.solver']
    assert 'photogram_ros.core.bundle' not in real['photogram_ros.core.bundle.solver']
