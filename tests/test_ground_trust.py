"""The ground station trusts only its drones, and stops cleanly.

- In one process: a drone /drone1 (stand-ins named as its bundle_node and map_node) whose check points are
  far beyond the limit (NO-GO); then plain rclpy nodes publish a perfect map/control_points on the drone's
  topic (from another namespace, and from another node name in the drone's namespace), a fake /diagnostics
  and a drone outside the allow-list. The verdict and its figures do not move; the page's status names the
  unknown publishers and the unknown drone; /diagnostics carries the same figures as status.json.
- The command: SIGINT and SIGTERM save and exit 0 without a traceback; 0.0.0.0 prints a token and says
  whether ROS 2 security is available; a base map that cannot be read is refused at the start (exit 2).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import String

from conftest import ROOT
from photogram_ros import msgs

pytestmark = pytest.mark.ros
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _quality(h_m: float) -> dict:
    return {'stamp_ns': 1, 'keyframes': 40, 'fix_share': {'rtk_fixed': 1.0}, 'block': 'in_flight',
            'check_rmse': {'horizontal_m': h_m, 'vertical_m': 0.02, 'count': 4},
            'gcp_rmse': {'horizontal_m': None, 'vertical_m': None, 'count': 0}, 'gnss_bias_enu_m': None,
            'check_points': [{'name': 'CHK01', 'marker_id': 5, 'lat_deg': 47.3977, 'lon_deg': 8.5456, 'h_m': 490.0,
                              'residual_enu_m': [h_m, 0.0, 0.02], 'images': 6, 'rms_px': 0.3, 'use': 'check'}],
            'gcps': []}


def _diag(name: str, georef: str) -> DiagnosticArray:
    return DiagnosticArray(status=[DiagnosticStatus(level=DiagnosticStatus.OK, name=name, message='OK',
                                                    values=[KeyValue(key='georeferenced', value=georef)])])


def _spinner(context, listener, *nodes):
    """An executor over the nodes and the listener; the dict the station's /diagnostics values fill (as the
    listener hears them); spin(seconds, until) runs the executor."""
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=context)
    for n in (*nodes, listener):
        ex.add_node(n)
    heard = {}
    listener.create_subscription(DiagnosticArray, '/diagnostics', lambda m: heard.update(
        {kv.key: kv.value for st in m.status if st.name == '/ground_station' for kv in st.values}), 50)

    def spin(seconds, until=lambda: False):
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds and not until():
            ex.spin_once(timeout_sec=0.05)
    return ex, heard, spin


def test_fake_publishers_change_no_verdict(tmp_path, rclpy_context):
    from photogram_ros.nodes.ground_station import GroundStationNode
    station = GroundStationNode({'out_dir': str(tmp_path / 'gs'), 'drones': '/drone1', 'web': '127.0.0.1:0',
                                 'save_period_s': 1.0}, context=rclpy_context)
    bundle = Node('bundle_node', namespace='/drone1', context=rclpy_context)
    mapper = Node('map_node', namespace='/drone1', context=rclpy_context)
    fake = Node('fake', context=rclpy_context)                                  # a plain node, root namespace
    impostor = Node('impostor', namespace='/drone1', context=rclpy_context)     # in the drone's namespace
    stranger = Node('map_node', namespace='/drone9', context=rclpy_context)     # a drone not on the list
    listener = Node('diag_listener', context=rclpy_context)
    ex, station_diag, spin = _spinner(rclpy_context, listener, station, bundle, mapper, fake, impostor, stranger)

    def drone():
        return station.status()['drones'].get('drone1', {})

    try:
        bundle.create_publisher(String, 'map/control_points', LATCHED).publish(msgs.json_msg(_quality(0.20)))
        mapper.create_publisher(String, 'map/coverage', LATCHED).publish(msgs.json_msg(
            {'type': 'FeatureCollection', 'features': [], 'properties': {'coverage_share': 1.0, 'largest_gap_m2': 0.0}}))
        bundle_diag = bundle.create_publisher(DiagnosticArray, '/diagnostics', 10)
        for _ in range(40):
            bundle_diag.publish(_diag('/drone1/bundle_node', 'True'))
            spin(0.1)
            if drone().get('go_no_go', {}).get('verdict') == 'NO-GO':
                break
        before = drone()
        assert before['go_no_go']['verdict'] == 'NO-GO', before['go_no_go']
        assert before['accuracy']['check_rmse_h_m'] == 0.20 and before['accuracy']['georeference'] == 'final'
        # The bundle node's figures came from its in-flight block: the reason says so.
        assert 'in-flight block, before its final adjustment' in before['go_no_go']['reasons'][0]
        assert not before['unknown_publishers']

        tiles_before, cov_before = station.status()['drones']['drone1']['ortho'], before.get('coverage')
        perfect = msgs.json_msg(_quality(0.001))
        fake_cp = fake.create_publisher(String, '/drone1/map/control_points', LATCHED)
        # A fake ortho tile and a fake full coverage in the drone's topics, from nodes that are not its map_node.
        fake_tiles = fake.create_publisher(CompressedImage, '/drone1/map/ortho_tiles', 10)
        tile = msgs.ortho_tile_msg(19, 274589, 183553, b'\x89PNG\r\n\x1a\n' + b'0' * 64, 1)
        imp_cov = impostor.create_publisher(String, 'map/coverage', LATCHED)
        imp_cov.publish(msgs.json_msg({'type': 'FeatureCollection', 'features': [], 'properties': {
            'coverage_share': 1.0, 'largest_gap_m2': 0.0, 'fake': True}}))
        imp_cp = impostor.create_publisher(String, 'map/control_points', LATCHED)
        fake_diag = fake.create_publisher(DiagnosticArray, '/diagnostics', 10)
        stranger.create_publisher(String, 'map/control_points', LATCHED).publish(perfect)
        stranger_cloud = stranger.create_publisher(String, 'map/cloud_downsampled', 5)   # a topic of that name
        for _ in range(3):
            fake_cp.publish(perfect)
            imp_cp.publish(perfect)
            fake_diag.publish(_diag('/drone1/bundle_node', 'provisional'))
            stranger_cloud.publish(String(data='x'))
            fake_tiles.publish(tile)
            spin(1.0)
        spin(1.5)
        after = drone()
        st = station.status()
        with urllib.request.urlopen(station.web.url + 'status.json', timeout=5) as r:
            page = json.loads(r.read())
    finally:
        ex.shutdown()
        for n in (listener, stranger, impostor, fake, mapper, bundle, station):
            n.destroy_node()
    print('after the fakes:', json.dumps({'verdict': after['go_no_go']['verdict'],
                                          'unknown_publishers': after['unknown_publishers'],
                                          'not_counted': after['not_counted'], 'unknown_drones': st['unknown_drones'],
                                          'diagnostics_unknown': st['diagnostics_unknown_publishers']}))
    assert after['go_no_go']['verdict'] == 'NO-GO'
    assert after['ortho'] == tiles_before and after.get('coverage') == cov_before   # no fake tile, no fake coverage
    assert '/fake' in after['unknown_publishers']['/map/ortho_tiles']
    assert '/drone1/impostor' in after['unknown_publishers']['/map/coverage']
    assert after['accuracy']['check_rmse_h_m'] == 0.20 and after['accuracy']['georeference'] == 'final'
    assert set(after['unknown_publishers']['/map/control_points']) == {'/fake', '/drone1/impostor'}
    assert after['not_counted']['/map/control_points'] >= 1
    assert '/drone9' in st['unknown_drones'] and 'drone9' not in st['drones']
    assert '/fake' in st['diagnostics_unknown_publishers']
    # The page's status.json: the same figures and the same unknown publishers.
    d = page['drones']['drone1']
    assert d['go_no_go']['verdict'] == 'NO-GO' and d['accuracy']['check_rmse_h_m'] == 0.20
    assert set(d['unknown_publishers']['/map/control_points']) == {'/fake', '/drone1/impostor'}
    # /diagnostics of the station: the same verdict and figure (until the fake /diagnostics came, it was heard).
    assert station_diag.get('drone1_verdict') == 'NO-GO', station_diag
    assert float(station_diag['drone1_check_points_horizontal_RMSE']) == 0.20
    assert 'unknown_drones' in station_diag and '/drone9' in station_diag['unknown_drones']
    assert not st['security']['enabled'] and st['security']['summary']



def test_a_second_node_of_the_drones_name_is_not_counted_and_diagnostics_equal_status(tmp_path, rclpy_context):
    """A plain rclpy node that takes the drone's node name (/bundle_node in the root namespace, the drone '/')
    while the drone's own bundle_node publishes: the topic has two publishers of that name, so neither is
    counted and the verdict keeps its last trusted value. The station's /diagnostics carries every figure of
    status.json (check points H / V and count, GCP residuals, georeference, GNSS bias, gaps) with the same value."""
    from photogram_ros.nodes.ground_station import GroundStationNode, diagnostic_figures, diagnostic_text
    station = GroundStationNode({'out_dir': str(tmp_path / 'gs'), 'drones': '/', 'save_period_s': 1.0},
                                context=rclpy_context)
    bundle = Node('bundle_node', context=rclpy_context)
    mapper = Node('map_node', context=rclpy_context)
    listener = Node('diag_listener2', context=rclpy_context)
    ex, heard, spin = _spinner(rclpy_context, listener, station, bundle, mapper)

    q = _quality(0.03)
    q.update(georeference='final', gnss_bias_enu_m=[0.001, -0.025, 0.004],
             gcp_rmse={'horizontal_m': 0.0305, 'vertical_m': 0.0262, 'count': 5})
    twin = None
    try:
        cp = bundle.create_publisher(String, 'map/control_points', LATCHED)
        cp.publish(msgs.json_msg(q))
        mapper.create_publisher(String, 'map/coverage', LATCHED).publish(msgs.json_msg({
            'type': 'FeatureCollection', 'properties': {'coverage_share': 1.0}, 'features': [
                {'type': 'Feature', 'geometry': None, 'properties': {'role': 'gap', 'kind': 'forward_overlap',
                                                                     'area_m2': 3.5, 'min_views': 2}}]}))
        spin(10, lambda: station.status()['drones'].get('default', {}).get('go_no_go', {}).get('verdict') == 'GO')
        good = station.status()['drones']['default']
        spin(3, lambda: heard.get('default_gcp_rmse_h_m') == '0.0305')
        twin = Node('bundle_node', context=rclpy_context)       # the same name, another process's node
        ex.add_node(twin)
        twin_cp = twin.create_publisher(String, 'map/control_points', LATCHED)
        for _ in range(3):
            twin_cp.publish(msgs.json_msg(_quality(0.50)))
            cp.publish(msgs.json_msg(_quality(0.50)))
            spin(1.0)
        after = station.status()['drones']['default']
    finally:
        ex.shutdown()
        for n in (twin, listener, mapper, bundle, station):
            if n is not None:
                n.destroy_node()
    print('diagnostics:', {k: v for k, v in heard.items() if k.startswith('default_')})
    assert good['go_no_go']['verdict'] == 'GO' and good['accuracy']['check_rmse_h_m'] == 0.03
    assert after['accuracy']['check_rmse_h_m'] == 0.03 and after['go_no_go']['verdict'] == 'GO'
    assert any('2 nodes of that name' in w for w in after['unknown_publishers']['/map/control_points'])
    for name, value in diagnostic_figures(good).items():
        if name != 'updated_unix_s':
            assert heard[f'default_{name}'] == diagnostic_text(value), name
    assert heard['default_georeference'] == 'final' and heard['default_gcp_rmse_h_m'] == '0.0305'
    assert heard['default_gnss_bias_enu_m'] == '[0.001, -0.025, 0.004]'


def _station(tmp_path, *extra, env=None, **kw):
    return subprocess.Popen([sys.executable, '-m', 'photogram_ros.cli', 'ground-station', '--out',
                             str(tmp_path / 'gs'), '--save-period', '1', *extra], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env or {**os.environ, 'PYTHONUNBUFFERED': '1'}, **kw)


def _wait_for(proc, text, timeout_s=60):
    lines = []
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        line = proc.stdout.readline()
        if not line and proc.poll() is not None:
            break
        lines.append(line)
        if text in line:
            return ''.join(lines)
    raise AssertionError(f'{text!r} not printed: {"".join(lines)[-2000:]}')


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_signal_saves_and_exits_0_without_traceback(tmp_path, sig):
    proc = _station(tmp_path, '--web', '0.0.0.0:0')
    try:
        head = _wait_for(proc, 'map page on')
        time.sleep(1.5)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    out = head + out
    assert proc.returncode == 0, err[-2000:]
    assert 'Traceback' not in err and 'Traceback' not in out
    assert f'stopped by {sig.name}' in out and 'saved in' in out
    assert (tmp_path / 'gs' / 'status.json').exists()
    assert '?token=' in out and 'other machines need this token' in out        # 0.0.0.0: a token, printed
    assert 'ROS 2 security: ' in out


def test_unreadable_base_map_is_refused_at_the_start(tmp_path):
    bad = tmp_path / 'nothing.mbtiles'
    bad.write_bytes(b'not sqlite')
    proc = _station(tmp_path, '--web', '127.0.0.1:0', '--basemap', str(bad))
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and 'Traceback' not in err
    assert 'not a readable MBTiles file' in err


def test_a_crash_says_where_the_files_are(tmp_path):
    """The output folder replaced by a file mid-run (a disk unmounted, say): the next save fails; the station
    stops with exit 1 and names the folder where the earlier saves are."""
    import shutil
    proc = _station(tmp_path)
    try:
        head = _wait_for(proc, 'merged cells')
        t0 = time.monotonic()
        while not (tmp_path / 'gs' / 'status.json').exists() and time.monotonic() - t0 < 20:
            time.sleep(0.2)
        assert (tmp_path / 'gs' / 'status.json').exists()
        shutil.rmtree(tmp_path / 'gs')
        (tmp_path / 'gs').write_text('not a folder')
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    del head
    assert proc.returncode == 1
    assert 'stopped by an error' in err and str((tmp_path / 'gs').resolve()) in err and 'status.json' in err


def test_the_commands_page_closes_idle_connections_and_refuses_remote_requests(tmp_path):
    """`ground-station --web 0.0.0.0:PORT` with its defaults: a connection that sends half a request line and
    one that sends nothing are closed by the server within 60 s; a request naming another host, or from
    another address without the token, is refused (403); with the token it is served."""
    import re
    import socket

    from test_ground_page import _lan_address, _served
    proc = _station(tmp_path, '--web', '0.0.0.0:0')
    try:
        head = _wait_for(proc, 'map page on')
        url = re.search(r'map page on (http://\S+)', head).group(1)
        token = url.split('?token=')[1].split()[0]
        port = int(url.split('/')[2].rsplit(':', 1)[1])
        half, idle = socket.create_connection(('127.0.0.1', port)), socket.create_connection(('127.0.0.1', port))
        half.sendall(b'GET /status.json HT')
        for s in (half, idle):
            s.settimeout(60)
            try:
                assert s.recv(100) == b''          # closed by the server, not by the 60 s timeout here
            except ConnectionResetError:
                pass
            s.close()
        local = f'http://127.0.0.1:{port}/status.json'
        assert _served(None, local) == 200
        assert _served(None, local, {'Host': 'station.example:80'}) == 403
        lan = _lan_address()
        if lan is not None:
            assert _served(None, f'http://{lan}:{port}/status.json') == 403
            wrong = token[:-1] + ('y' if token.endswith('x') else 'x')
            assert _served(None, f'http://{lan}:{port}/status.json?token={wrong}') == 403
            assert _served(None, f'http://{lan}:{port}/status.json', {'Authorization': f'Bearer {token}'}) == 200
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0 and 'Traceback' not in err
    assert 'DDS traffic NOT authenticated, NOT encrypted' in head or 'DDS traffic authenticated' in head


def test_security_asked_for_without_the_plugins_is_refused_at_the_start(tmp_path):
    """ROS_SECURITY_ENABLE=true with the PyPI wheels (Fast DDS without the security plugins): rcl could not
    create the node; the station says why and what to do, exit 2, no traceback."""
    from photogram_ros.nodes.ground_station import security_status
    if security_status()['dds_security_plugins'] is not False:
        pytest.skip('this Fast DDS has the security plugins')
    ks = tmp_path / 'keystore' / 'enclaves' / 'gs'
    ks.mkdir(parents=True)
    proc = _station(tmp_path, env={**os.environ, 'PYTHONUNBUFFERED': '1', 'ROS_SECURITY_ENABLE': 'true',
                                   'ROS_SECURITY_KEYSTORE': str(tmp_path / 'keystore'), 'ROS_SECURITY_ENCLAVE': '/gs'})
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and 'Traceback' not in err
    assert 'no DDS security plugins' in err and 'ROS_SECURITY_ENABLE' in err
