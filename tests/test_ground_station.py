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
        helper = Node('drone_side', context=rclpy_context)
        nodes.append(helper)
        for ns, o in origins.items():
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
