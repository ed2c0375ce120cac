"""Drone side and ground station in two processes over DDS: the station receives and merges the maps.

Two drones (namespaces /drone1 and /drone2, each a map node anchored at its own origin 80 m apart)
stream their downsampled maps; the ground station, a separate `photogram-ros ground-station`
process, must place both in one frame: a flat surface at a known ellipsoidal height comes out flat
and continuous across the two drones' areas.
"""

import subprocess
import sys
import time

import numpy as np
import pytest
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import NavSatFix, PointCloud2

from conftest import ROOT
from helpers.clouds import pair_cloud
from photogram_ros import msgs
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.io.export import read_ply

pytestmark = pytest.mark.ros

SURFACE_H_M = 500.0   # ellipsoidal height of the flat field both drones map


def test_ground_station_merges_two_drones(tmp_path, rclpy_context):
    from rclpy.executors import MultiThreadedExecutor

    from photogram_ros.nodes.map_node import MapNode
    origins = {'/drone1': LocalFrame(47.3977, 8.5456, 540.0), '/drone2': LocalFrame(47.3977, 8.54666, 545.0)}
    out = tmp_path / 'gs'
    station = subprocess.Popen([sys.executable, '-m', 'photogram_ros.cli', 'ground-station', '--out', str(out),
                                '--duration', '40', '--save-period', '2'], cwd=ROOT,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    ex = MultiThreadedExecutor(context=rclpy_context)
    nodes, pubs = [], {}
    try:
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        for ns, o in origins.items():
            helper = Node('bundle_node', namespace=ns, context=rclpy_context)   # what publishes a georeference
            nodes.append(helper)
            n = MapNode({'map_dir': str(tmp_path / ns.strip('/')), 'stream_period_s': 0.5, 'cell_m': 0.25,
                         'use_origin_params': True, 'origin_lat_deg': o.lat_deg, 'origin_lon_deg': o.lon_deg,
                         'origin_h_m': o.h_m}, namespace=ns, context=rclpy_context)
            nodes.append(n)
            geo = helper.create_publisher(NavSatFix, f'{ns}/map/georeference', latched)
            geo.publish(msgs.navsatfix_msg(0, o.lat_deg, o.lon_deg, o.h_m, 2, [0, 0, 0], 0, 'map'))
            pubs[ns] = (geo, helper.create_publisher(PointCloud2, f'{ns}/map/dense_cloud',
                                                     QoSProfile(depth=10)))
        for n in nodes:
            ex.add_node(n)
        rng = np.random.default_rng(0)
        deadline = time.monotonic() + 35
        sent = 0
        while time.monotonic() < deadline and station.poll() is None:
            for ns, o in origins.items():
                # The field is flat at SURFACE_H_M ellipsoidal: in this drone's ENU its z is about
                # SURFACE_H_M - origin height (the tangent plane departs by < 1 mm over 40 m).
                cloud = pair_cloud(rng, lambda x, y: np.full_like(x, SURFACE_H_M - o.h_m), 0.0, 0.0, 20.0, 20.0,
                                   4.0, 0.01)
                pubs[ns][1].publish(msgs.pointcloud2_msg(cloud, 0, 'map'))
                sent += 1
            ex.spin_once(timeout_sec=0.2)
            for _ in range(5):
                ex.spin_once(timeout_sec=0.05)
            if sent > 20 and (out / 'merged_cloud.ply').exists() and (out / 'status.json').exists():
                import json
                st = json.loads((out / 'status.json').read_text())
                if all(st['drones'].get(ns, {}).get('points', 0) > 0 for ns in origins):
                    break
    finally:
        for n in nodes:
            n.destroy_node()
        station.terminate()
        log = station.communicate(timeout=30)[0]
    import json
    status = json.loads((out / 'status.json').read_text())
    assert set(origins) <= set(status['drones']), log[-2000:]
    assert all(status['drones'][ns]['points'] > 0 for ns in origins)
    pts, comments = read_ply(out / 'merged_cloud.ply')
    assert any('EPSG:32632' in c for c in comments)
    # Both drones' areas (80 m apart east-west), merged in one flat surface at the right height.
    assert pts['x'].max() - pts['x'].min() > 110
    assert np.percentile(np.abs(pts['z'] - SURFACE_H_M), 95) < 0.05


def test_station_shows_ortho_coverage_gap_and_accuracy(tmp_path, rclpy_context):
    """One drone's map node (coverage and ortho on) and the station in one process: a survey of three
    lines whose outer line misses 50 m; the station receives ortho tiles, the coverage with the gap (area,
    place), the live accuracy, and serves them on its page's routes."""
    import json
    import urllib.request

    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import CameraInfo
    from std_msgs.msg import String

    from photogram_ros.core.rotations import make_T
    from photogram_ros.nodes.ground_station import GroundStationNode
    from photogram_ros.nodes.map_node import MapNode
    from photogram_ros.sim.scenario import preset
    o = LocalFrame(47.3977, 8.5456, 528.0)   # the map origin 40 m above the field at 488 m
    node = MapNode({'map_dir': str(tmp_path / 'map'), 'stream_period_s': 0.3, 'ortho_period_s': 0.3,
                    'coverage_period_s': 0.3, 'cell_m': 0.25, 'use_origin_params': True, 'origin_lat_deg': o.lat_deg,
                    'origin_lon_deg': o.lon_deg, 'origin_h_m': o.h_m}, namespace='/drone1', context=rclpy_context)
    station = GroundStationNode({'out_dir': str(tmp_path / 'gs'), 'drones': '/drone1', 'web': '127.0.0.1:0',
                                 'save_period_s': 1.0}, context=rclpy_context)
    peer = Node('bundle_node', namespace='/drone1', context=rclpy_context)   # stands in for the drone's bundle_node
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pubs = {'geo': peer.create_publisher(NavSatFix, 'map/georeference', latched),
            'info': peer.create_publisher(CameraInfo, 'camera/camera_info', 10),
            'pose': peer.create_publisher(PoseWithCovarianceStamped, 'map/keyframe_pose', QoSProfile(depth=200)),
            'sparse': peer.create_publisher(PointCloud2, 'map/sparse_cloud', 2),
            'cloud': peer.create_publisher(PointCloud2, 'map/dense_cloud', QoSProfile(depth=50)),
            'quality': peer.create_publisher(String, 'map/control_points', latched)}
    ex = SingleThreadedExecutor(context=rclpy_context)
    for n in (node, station, peer):
        ex.add_node(n)
    cam = preset('sample').camera()
    rng = np.random.default_rng(1)
    try:
        pubs['geo'].publish(msgs.georeference_msg(o.lat_deg, o.lon_deg, o.h_m, 0))
        pubs['quality'].publish(msgs.json_msg({'check_rmse': {'horizontal_m': 0.031, 'vertical_m': 0.02, 'count': 4},
                                               'gcp_rmse': None, 'fix_share': {'rtk_fixed': 1.0},
                                               'check_points': [], 'gcps': [], 'gnss_bias_enu_m': None,
                                               'control': {'gcps': 3, 'gcps_full': 2, 'gcps_rejected': 1,
                                                           'faults': ['GCP GCP02 not used: 29.8 m off'],
                                                           'rows': [{'fate': 'outlier'}]},
                                               'block': 'adjusted', 'block_check': {
                                                   'status': 'failed', 'summary': 'FAILED (decided by strips): a '
                                                                                  'strip is tilted 31 deg'}}))
        ground = -40.0
        tie = np.column_stack([rng.uniform(-30, 70, 500), rng.uniform(-20, 110, 500), np.full(500, ground)])
        for _ in range(10):
            ex.spin_once(timeout_sec=0.05)
        pubs['info'].publish(msgs.camera_info_msg(cam, 0))
        pubs['sparse'].publish(msgs.sparse_cloud_msg(tie, 0))
        R = {0: np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]]), 1: np.array([[-1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]])}
        t = 0
        for line in range(3):
            ys = np.arange(0.0, 90.01, 5.0)
            for y in (ys if line % 2 == 0 else ys[::-1]):
                t += 1
                if line == 2 and 15 < y < 65:
                    continue   # the camera stopped
                T = make_T(R[line % 2], np.array([17.2 * line, y, 0.0]))
                pubs['pose'].publish(msgs.pose_with_covariance_from_T(T, 10**18 + t * 10**9, 'map', np.eye(6) * 1e-4))
                pubs['cloud'].publish(msgs.pointcloud2_msg(
                    pair_cloud(rng, lambda x, yy: np.full_like(x, ground), 17.2 * line, y, 10.0, 3.0, 4.0,
                               rgb=0x30A030), 0, 'map'))
                for _ in range(3):
                    ex.spin_once(timeout_sec=0.02)
            t += 10
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
            d = station.status()['drones'].get('drone1', {})
            if (d.get('coverage', {}).get('keyframes', 0) >= 47 and d.get('ortho', {}).get('tiles', 0) >= 2
                    and d['coverage']['gap_list']):
                break
        st = station.status()
        d = st['drones']['drone1']
        gaps = [g for g in d['coverage']['gap_list'] if g['kind'] == 'coverage']
        assert len(gaps) == 1, d['coverage']
        # The outer strip only line 2 sees (east of 17.2 + 26.8 m) over the stop: about 14 m x 11 m.
        assert 80 < gaps[0]['area_m2'] < 400
        gx = o.geodetic_to_enu(gaps[0]['centroid'][1], gaps[0]['centroid'][0], o.h_m - 40)
        assert 44 < gx[0] < 62 and 30 < gx[1] < 50
        assert d['accuracy']['check_rmse_h_m'] == 0.031 and d['accuracy']['check_count'] == 4
        ctl = d['accuracy']['control']     # the bundle node's verdicts on the control, without its rows
        assert ctl['gcps_rejected'] == 1 and ctl['faults'] == ['GCP GCP02 not used: 29.8 m off'] and 'rows' not in ctl
        assert d['go_no_go']['verdict'] == 'NO-GO'
        assert any('largest gap' in r for r in d['go_no_go']['reasons'])
        # The adjuster's check of the block, from its quality document: a folded block after the final adjustment.
        assert any(r.startswith("the adjuster's check of the block: failed: FAILED (decided by strips)")
                   for r in d['go_no_go']['reasons']), d['go_no_go']['reasons']
        z = d['ortho']['zoom']
        key = next(iter(station.drones['/drone1'].tiles))
        url = station.web.url
        with urllib.request.urlopen(f'{url}tiles/drone1/{key[0]}/{key[1]}/{key[2]}.png', timeout=5) as r:
            assert r.read()[:4] == b'\x89PNG' and key[0] == z
        with urllib.request.urlopen(url + 'status.json', timeout=5) as r:
            assert json.loads(r.read())['drones']['drone1']['coverage']['gap_list'][0]['area_m2'] > 0
        with urllib.request.urlopen(url + 'drones/drone1/refly.plan', timeout=5) as r:
            plan = json.loads(r.read())
        assert plan['fileType'] == 'Plan' and len(plan['mission']['items']) >= 4
        station.save()
        assert (tmp_path / 'gs' / 'drone1_gaps.geojson').exists() and (tmp_path / 'gs' / 'drone1_refly.plan').exists()
        assert list((tmp_path / 'gs' / 'tiles' / 'drone1' / str(z)).glob('*/*.png'))
    finally:
        ex.shutdown()
        for n in (peer, station, node):
            n.destroy_node()


def test_low_forward_overlap_is_a_warning_with_its_area():
    """A pair of keyframes below the target forward overlap (the ground between them seen by the neighbouring
    lines: no gap) is a warning with the stretch between them, W x (1 - overlap) x L; the verdict stays."""
    from photogram_ros.core.survey_quality import QualityLimits, go_no_go
    from photogram_ros.nodes.ground_station import low_forward_overlap
    props = {'footprint_width_m': 50.0, 'footprint_length_m': 38.0, 'low_forward_pairs': [[1, 2, 0.22], ['x']]}
    low = low_forward_overlap(props)
    assert low == [{'overlap': 0.22, 'area_m2': round(50.0 * 0.78 * 38.0, 1), 'stamps_ns': [1, 2]}]
    g = go_no_go({'gaps': [], 'coverage_share': 1.0, 'georeference': 'final', 'low_forward_overlap': low,
                  'check_rmse': {'horizontal_m': 0.02, 'vertical_m': 0.02, 'count': 4}}, QualityLimits())
    assert g['verdict'] == 'GO' and g['warnings'] == [
        'forward overlap 22 % between two keyframes of a line, below the target: 1482 m² between them']
    assert low_forward_overlap({'low_forward_pairs': [[1, 2, 0.5]]})[0]['area_m2'] is None


def test_a_drone_node_in_error_holds_the_verdict():
    """bundle_node saying ERROR on /diagnostics (e.g. no georeference after 47 keyframes) is a reason and keeps
    a GO at WAIT; a NO-GO stays NO-GO; WARN and STALE levels do not change it."""
    from photogram_ros.nodes.ground_station import with_node_errors
    go = {'verdict': 'GO', 'reasons': [], 'checks': [], 'warnings': []}
    g = with_node_errors(go, {'/bundle_node': [2, 'no georeference after 47 keyframes'], '/map_node': [0, 'OK']})
    assert g['verdict'] == 'WAIT' and g['reasons'] == ['bundle_node ERROR: no georeference after 47 keyframes']
    assert with_node_errors({**go, 'verdict': 'NO-GO'}, {'/b': [2, 'x']})['verdict'] == 'NO-GO'
    assert with_node_errors(go, {'/tracker_node': [1, 'tracking lost'], '/x': [3, 'stale']}) == go


def test_a_failed_block_check_is_said_once():
    """A failed block check that the go / no-go already reasons on (from the quality document) is not repeated as
    bundle_node's ERROR (the same check on /diagnostics); another bundle_node error still is."""
    from photogram_ros.core.survey_quality import QualityLimits, go_no_go
    from photogram_ros.nodes.ground_station import with_node_errors
    summary = 'FAILED (decided by strips): the block is folded'
    g = go_no_go({'gaps': [], 'coverage_share': 1.0, 'georeference': 'final', 'block': 'adjusted',
                  'block_check': {'status': 'failed', 'summary': summary},
                  'check_rmse': {'horizontal_m': 0.02, 'vertical_m': 0.02, 'count': 4}}, QualityLimits())
    out = with_node_errors(g, {'/bundle_node': [2, f'block check: {summary}']})
    assert out['verdict'] == 'NO-GO' and sum(summary in r for r in out['reasons']) == 1
    other = with_node_errors(g, {'/bundle_node': [2, 'no georeference after 47 keyframes']})
    assert other['reasons'][-1] == 'bundle_node ERROR: no georeference after 47 keyframes'
    # without a failed check in the verdict, the node's block-check error is the only place it is said: kept
    go = {'verdict': 'GO', 'reasons': [], 'checks': [], 'warnings': []}
    assert with_node_errors(go, {'/bundle_node': [2, f'block check: {summary}']})['verdict'] == 'WAIT'
