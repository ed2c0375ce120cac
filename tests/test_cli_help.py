"""`photogram-ros COMMAND --help` of every command shows the options' defaults (cli.HelpFormatter)."""

import re
import subprocess
import sys

import pytest

from conftest import ROOT
from photogram_ros import cli


def _help(capsys, *argv) -> str:
    with pytest.raises(SystemExit) as exc:
        cli.main([*argv, '--help'])
    assert exc.value.code == 0
    return ' '.join(capsys.readouterr().out.split())   # argparse's line wrapping undone


@pytest.mark.parametrize('command', sorted(cli.COMMANDS))
def test_every_command_has_help_without_noise(capsys, command):
    text = _help(capsys, command)
    assert text.startswith(f'usage: photogram-ros {command}')
    # Nothing to show is not shown: no "(default: None)", "(default: False)" or "(default: )".
    assert not re.search(r'\(default: (None|False|)\)', text), text


def test_known_defaults_are_shown(capsys):
    replay = _help(capsys, 'replay')
    assert re.search(r'--rate RATE bag time speed; 0 = as fast as the mapper keeps up \(default: 0\.0\)', replay)
    assert '--out OUT output folder (default: output/replay)' in replay
    assert '--min-pairs MIN_PAIRS export only cells confirmed by this many stereo pairs (1 keeps everything) ' \
           '(default: 2)' in replay
    assert '(default: bundle,stereo,map)' in replay
    tri = _help(capsys, 'triangulate')
    assert '(default 1: in this process, no Dask)' in tri              # --workers says its own default
    assert 'photos: SIFT features per photo (default: 4000)' in tri
    assert 'GCP sigma E,N,U in metres (default: 0.02,0.02,0.03)' in tri
    export = _help(capsys, 'export')
    assert 'DSM cell size in metres (default: 2 fusion cells, about 2 GSD)' in export
    assert 'orthomosaic cell size in metres (default: one fusion cell, about 1 GSD)' in export
    assert '(default: las,laz,ply,dsm,dtm,ortho)' in export
    # An option whose help says its default is not told twice.
    assert 'WGS84 ellipsoidal (default) or orthometric' in export and 'default: ellipsoidal' not in export


def test_help_from_the_installed_command():
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'play', '--help'], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert '(default: ' in r.stdout
