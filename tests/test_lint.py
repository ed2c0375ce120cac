"""The linter (ruff, configured in ruff.toml) finds nothing in the package, its tests and benchmarks."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing():
    ruff = Path(sys.executable).with_name('ruff')
    if not ruff.exists():
        pytest.skip('ruff is not installed in this environment (requirements.txt pins it)')
    out = subprocess.run([str(ruff), 'check', '--no-cache', 'photogram_ros', 'tests', 'bench', 'launch', 'setup.py'],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
