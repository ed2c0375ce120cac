"""`photogram-ros run`: the parameter files start every node; mistakes in them stop the start, by name."""

import signal
import subprocess
import sys
import time

import pytest

from conftest import ROOT
from helpers.processes import reaped
from photogram_ros.params import load_params_file

pytestmark = pytest.mark.ros

CONFIGS = sorted((ROOT / 'config').glob('*.yaml'))


def test_every_config_file_names_real_parameters():
    """Each shipped parameter file is valid against the nodes' declared parameters."""
    from photogram_ros.nodes.ground_station import GroundStationParams
    from photogram_ros.nodes.graph import NODES, node_class
    from photogram_ros.params import from_dict
    import importlib
    params_classes = {'ground_station': GroundStationParams}
    for role, (module, _cls, script) in NODES.items():
        mod = importlib.import_module(module)
        cls = [v for k, v in vars(mod).items() if k.endswith('Params') and isinstance(v, type)
               and v.__module__ == module]
        params_classes[script] = cls[-1]
        assert node_class(role)
    assert len(CONFIGS) >= 4
    for path in CONFIGS:
        for section, values in load_params_file(str(path)).items():
            assert section in params_classes, f'{path.name}: section {section}'
            from_dict(params_classes[section], values, where=f'{path.name}:{section}')


def test_mistyped_parameter_stops_the_start_with_its_name(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('tracker_node:\n  ros__parameters:\n    keyframe_overlapp: 0.7\n')
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'run', '--params', str(bad)], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "keyframe_overlapp" in r.stderr and 'keyframe_overlap' in r.stderr.replace('keyframe_overlapp', '')
    wrong = tmp_path / 'range.yaml'
    wrong.write_text('stereo_node:\n  ros__parameters:\n    downscale: 7.0\n')
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'run', '--params', str(wrong)], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and 'downscale' in r.stderr


def test_run_starts_all_nodes_and_sigint_flushes_the_map(tmp_path, sample_bag):
    cfg = tmp_path / 'onboard.yaml'
    text = (ROOT / 'config' / 'onboard_rtk.yaml').read_text()
    text = text.replace('url: udpin:0.0.0.0:14550', f'url: {sample_bag / "flight.tlog"}')
    text = text.replace('map_dir: maps/current', f'map_dir: {tmp_path / "map"}')
    cfg.write_text(text)
    proc = subprocess.Popen([sys.executable, '-m', 'photogram_ros.cli', 'run', '--params', str(cfg),
                             '--out', str(tmp_path / 'products')], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    with reaped(proc):
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (tmp_path / 'map' / 'map.json').exists():
            time.sleep(0.5)
        time.sleep(3.0)
        proc.send_signal(signal.SIGINT)
        out = proc.communicate(timeout=60)[0]
    assert proc.returncode == 5, out[-3000:]   # no camera: nothing mapped, MAPPING FAILED exits 5
    assert 'photogram_ros running: mavlink, tracker, bundle, stereo, map' in out
    assert (tmp_path / 'map' / 'map.json').exists()
    # No camera here, so no keyframes: the stop says there is nothing to export, and still writes the report.
    assert 'no georeferenced keyframes' in out and (tmp_path / 'products' / 'report.md').exists()


def test_replay_file_serves_graphs_without_some_nodes():
    """A bag without MAVLink runs the graph without mavlink_node; the replay file's section is not an error."""
    from photogram_ros.nodes.graph import GraphSpec, _sections
    sections = _sections(GraphSpec(roles=('tracker', 'bundle'), params_file=str(ROOT / 'config' / 'replay.yaml')))
    assert 'mavlink_node' in sections and 'tracker_node' in sections


def test_replay_of_a_bag_without_images_is_a_clear_error(tmp_path):
    from conftest import shared_data
    bag = shared_data('bags', 'husky_gps_imu_sqlite3')
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(bag), '--out', str(tmp_path / 'o'),
                        '--quiet'], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and 'no camera images' in r.stderr and '/fix' in r.stderr


def test_run_with_a_photo_folder_ends_by_itself_at_its_end(tmp_path):
    """camera_node on a folder (no device, no loop): `run` ends the flight once the tracker has the last photo."""
    from test_replay_unmappable import write_white_wall
    photos = write_white_wall(tmp_path / 'wall', n=4)
    cfg = tmp_path / 'photos.yaml'
    cfg.write_text(f'camera_node:\n  ros__parameters:\n    source: {photos}\n    rate: 0.0\n'
                   f'map_node:\n  ros__parameters:\n    map_dir: {tmp_path / "map"}\n')
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'run', '--params', str(cfg), '--nodes',
                        'camera,tracker,bundle,stereo,map', '--out', str(tmp_path / 'products')], cwd=ROOT,
                       capture_output=True, text=True, timeout=180)
    out = r.stdout + r.stderr
    assert r.returncode == 5, out[-3000:]   # MAPPING FAILED exits 5
    assert 'end of the camera source: ending the flight' in out
    assert r.stdout.strip().splitlines()[-1].startswith('MAPPING FAILED: ')   # a white wall maps nothing
    assert (tmp_path / 'products' / 'report.md').exists()


def test_an_executor_error_does_not_stop_the_graph_spinning(capsys):
    """rclpy's executor raises (InvalidHandle) when an entity is destroyed while it waits on it; the
    graph's spinning thread prints it and spins on instead of leaving every node deaf."""
    from types import SimpleNamespace

    from photogram_ros.nodes.graph import Graph

    calls = []

    def spin():
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError('cannot use Destroyable because destruction was requested')
    ok = SimpleNamespace(ok=lambda: True)
    Graph._spin(SimpleNamespace(executor=SimpleNamespace(spin=spin, context=ok)))
    assert len(calls) == 2 and 'executor error, spinning on' in capsys.readouterr().err
    calls.clear()
    down = SimpleNamespace(ok=lambda: False)     # after shutdown an error ends the thread
    Graph._spin(SimpleNamespace(executor=SimpleNamespace(spin=spin, context=down)))
    assert len(calls) == 1
