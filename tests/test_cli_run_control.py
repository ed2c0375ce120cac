"""`run --gcp/--check/--gcp-heights`: the live graph's control file given on the command line, as `replay` takes it
(commands/common_args.add_live_control: one definition), read once before any node starts (live_control), handed to
the bundle node's stage and to the report's check points (commands/run.flight_control); without --gcp the parameter
file's."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import ROOT
from photogram_ros.core.geodesy import geodetic_to_crs

LAT, LON = 47.3977, 8.5456


def _targets(tmp_path, name='targets.txt'):
    x, y, _ = geodetic_to_crs(LAT, LON, 0.0, 'EPSG:32632')
    p = tmp_path / name
    p.write_text(f'EPSG:32632\nGCP01 0 {x:.3f} {y:.3f} 490.0\nCHK01 7 {x + 10:.3f} {y + 10:.3f} 489.0\n'
                 f'P4 9 {x - 20:.3f} {y:.3f} 488.0\n')
    return p


def _parse(argv):
    from photogram_ros.cli import build_parser
    return build_parser().parse_args(argv)


def _help_of(command: str, flag: str) -> str:
    from photogram_ros.cli import build_parser
    sub = next(a for a in build_parser()._actions if a.dest == 'command')
    return next(a.help for a in sub.choices[command]._actions if flag in a.option_strings)


def test_run_and_replay_take_the_control_file_alike():
    for flag in ('--gcp', '--check', '--gcp-heights'):
        assert _help_of('run', flag) == _help_of('replay', flag)
    a = _parse(['run', '--gcp', 'targets.txt', '--check', 'P4', '--gcp-heights', 'ellipsoidal'])
    assert (a.gcp, a.check, a.gcp_heights) == ('targets.txt', 'P4', 'ellipsoidal')
    assert _parse(['run']).gcp == ''


def test_the_stage_and_the_report_control_come_from_one_reading(tmp_path):
    from photogram_ros.commands.common_args import live_control
    from photogram_ros.commands.run import flight_control
    f = _targets(tmp_path)
    a = _parse(['run', '--gcp', str(f), '--check', 'P4'])
    control = live_control(a)
    assert control.parameters() == {'control_file': str(f.resolve()), 'check_names': 'P4', 'control_heights': 'auto'}
    assert control.targets.gcp_names == ['GCP01'] and control.targets.check_names == ['CHK01', 'P4']
    assert flight_control(a, control) is control.targets
    # Without --gcp: the parameter file's bundle_node control file, as the bundle node reads it.
    params = tmp_path / 'p.yaml'
    params.write_text(f'bundle_node:\n  ros__parameters:\n    control_file: {f}\n    check_names: "P4"\n')
    assert flight_control(_parse(['run', '--params', str(params)])).check_names == ['CHK01', 'P4']
    params.write_text('bundle_node:\n  ros__parameters:\n    max_window: 12\n')
    assert flight_control(_parse(['run', '--params', str(params)])) is None
    assert live_control(_parse(['run'])) is None


@pytest.mark.parametrize('case', ['missing', 'bad_row'])
def test_a_bad_control_file_stops_run_before_any_node_starts(tmp_path, case):
    f = tmp_path / 'targets.txt'
    if case == 'bad_row':
        f.write_text('EPSG:32632\nGCP01 0 500000 5250000\n')
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'run', '--gcp', str(f), '--out',
                        str(tmp_path / 'products')], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stdout[-2000:] + r.stderr[-2000:]
    assert 'targets.txt' in r.stderr and 'photogram_ros running' not in r.stdout
    assert not (tmp_path / 'products').exists()


@pytest.mark.ros
def test_run_hands_the_control_file_to_the_bundle_node_and_the_report(tmp_path):
    """A photo folder through `run --gcp`: the bundle node starts with the file (a bad one would stop it) and the
    report names it as the source of its check points."""
    from test_replay_unmappable import write_white_wall
    photos = write_white_wall(tmp_path / 'wall', n=4)
    f = _targets(tmp_path)
    cfg = tmp_path / 'photos.yaml'
    cfg.write_text(f'camera_node:\n  ros__parameters:\n    source: {photos}\n    rate: 0.0\n'
                   f'map_node:\n  ros__parameters:\n    map_dir: {tmp_path / "map"}\n')
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'run', '--params', str(cfg), '--nodes',
                        'camera,tracker,bundle,stereo,map', '--gcp', str(f), '--out', str(tmp_path / 'products')],
                       cwd=ROOT, capture_output=True, text=True, timeout=180)
    out = r.stdout + r.stderr
    assert r.returncode == 5, out[-3000:]   # a white wall maps nothing: MAPPING FAILED, with its report
    report = (tmp_path / 'products' / 'report.json').read_text()
    assert 'targets.txt' in report, report[:2000]
