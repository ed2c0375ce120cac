"""A pip install that installs: the package metadata declares requirements.txt's runtime pins (the ROS 2
wheels as the `ros` extra, pytest and ruff as `test`), and `pip install .` into an empty virtualenv gives a
working `photogram-ros` (--version, replay --help) that finds its parameter files from the package, not
from the current directory."""

from __future__ import annotations

import os
import re
import runpy
import shutil
import subprocess
import sys

import pytest

from conftest import ROOT


def _setup_kwargs(monkeypatch) -> dict:
    import setuptools
    captured = {}
    monkeypatch.setattr(setuptools, 'setup', lambda **kw: captured.update(kw))
    runpy.run_path(str(ROOT / 'setup.py'), run_name='__main__')
    return captured


def _pins(path) -> list[str]:
    return [line.split('#', 1)[0].strip() for line in path.read_text().splitlines() if line.split('#', 1)[0].strip()]


def test_metadata_declares_every_pin_of_requirements(monkeypatch, tmp_path):
    from photogram_ros import __version__
    monkeypatch.chdir(tmp_path)        # setup.py reads its files from its own folder
    kw = _setup_kwargs(monkeypatch)
    pins = _pins(ROOT / 'requirements.txt')
    ros = [p for p in pins if p.startswith('ros-')]
    test = [p for p in pins if p.split('==')[0] in ('pytest', 'ruff')]
    assert ros and kw['extras_require']['ros'] == ros
    assert kw['extras_require']['test'] == [p.split('==')[0] for p in test] == ['pytest', 'ruff']
    runtime = [p for p in pins if p not in ros and p not in test]
    assert kw['install_requires'] == ['setuptools'] + runtime
    assert any(p.startswith('numpy==') for p in runtime) and any(p.startswith('rasterio==') for p in runtime)
    assert kw['version'] == __version__
    # package.xml states the same version (colcon and rosdep read it)
    assert re.search(r'<version>([^<]+)</version>', (ROOT / 'package.xml').read_text()).group(1) == __version__


def test_version_option():
    from photogram_ros import __version__
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', '--version'], capture_output=True, text=True,
                       cwd=ROOT, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == f'photogram-ros {__version__}'


def test_config_files_are_found_from_the_package(tmp_path, monkeypatch):
    from photogram_ros.package_files import config_file
    monkeypatch.chdir(tmp_path)
    found = config_file('replay.yaml')
    assert found is not None and found.read_bytes() == (ROOT / 'config' / 'replay.yaml').read_bytes()
    assert config_file('no_such.yaml') is None


def _source_copy(dest):
    """The files a clone holds for the build (no .venv, .git, tests, bench or bags)."""
    skip = {'.venv', '.git', 'tests', 'bench', 'bags', 'build', 'install', 'log', 'output', '.pytest_cache'}
    shutil.copytree(ROOT, dest, ignore=lambda d, names: [n for n in names if n in skip or n.endswith('.egg-info')
                                                         or n == '__pycache__'])
    return dest


@pytest.mark.slow
def test_pip_install_into_an_empty_venv(tmp_path):
    """`pip install .` (dependencies from the package metadata; the local wheel mirror or PyPI), then the
    command runs from an unrelated folder with no PYTHONPATH."""
    src = _source_copy(tmp_path / 'src')
    venv = tmp_path / 'venv'
    subprocess.run([sys.executable, '-m', 'venv', str(venv)], check=True, timeout=300)
    env = {k: v for k, v in os.environ.items() if k not in ('PYTHONPATH', 'VIRTUAL_ENV')}
    r = subprocess.run([str(venv / 'bin' / 'python'), '-m', 'pip', 'install', '--quiet', str(src)],
                       capture_output=True, text=True, timeout=1800, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    elsewhere = tmp_path / 'elsewhere'
    elsewhere.mkdir()
    exe = venv / 'bin' / 'photogram-ros'
    from photogram_ros import __version__
    r = subprocess.run([str(exe), '--version'], capture_output=True, text=True, timeout=300, env=env, cwd=elsewhere)
    assert r.returncode == 0 and r.stdout.strip() == f'photogram-ros {__version__}', r.stderr
    r = subprocess.run([str(exe), 'replay', '--help'], capture_output=True, text=True, timeout=300, env=env,
                       cwd=elsewhere)
    assert r.returncode == 0 and '--params' in r.stdout, r.stderr[-2000:]
    code = ('import numpy, scipy, cv2, rasterio, laspy, pyproj, yaml, rosbags, matplotlib, jinja2; '
            'import photogram_ros.io.export, photogram_ros.io.flight_report; '
            'from photogram_ros.package_files import config_file; print(config_file("replay.yaml"))')
    r = subprocess.run([str(venv / 'bin' / 'python'), '-c', code], capture_output=True, text=True, timeout=300,
                       env=env, cwd=elsewhere)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == str(venv / 'share' / 'photogram_ros' / 'config' / 'replay.yaml')
    r = subprocess.run([str(venv / 'bin' / 'python'), '-m', 'pip', 'check'], capture_output=True, text=True,
                       timeout=300, env=env)
    assert r.returncode == 0, r.stdout
