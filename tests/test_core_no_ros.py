"""photogram_ros.core must import and work with no ROS package importable, and never import photogram_ros.io."""

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


def _imports(path):
    """Every module an import statement of the file names (module level or inside a function)."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            yield node.module
            yield from (f'{node.module}.{a.name}' for a in node.names)


def test_core_imports_nothing_from_io(tmp_path):
    """core is the numerics under io (files, reports) and nodes: an import the other way round is a cycle
    in the layering, even a lazy one inside a function."""
    files = sorted((ROOT / 'photogram_ros' / 'core').rglob('*.py'))
    assert len(files) >= 20
    bad = [f'{f.relative_to(ROOT)}: {m}' for f in files for m in _imports(f)
           if m == 'photogram_ros.io' or m.startswith('photogram_ros.io.')]
    assert not bad, bad
    lazy = tmp_path / 'lazy.py'   # the check sees a lazy import and `from photogram_ros import io`
    lazy.write_text('def f():\n    from photogram_ros.io.report import Section\n    from photogram_ros import io\n')
    assert {'photogram_ros.io.report', 'photogram_ros.io'} <= set(_imports(lazy))
