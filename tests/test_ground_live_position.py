"""The ground station shows each drone's live position and GNSS track: <ns>/gps/fix of the drone's own node
(mavlink_node, camera_node, px4_adapter) is its position on the page (status and live.geojson); a fix from a
node of another name is not counted; the page's server serves live.geojson."""

from __future__ import annotations

import json
import time
import urllib.request

import numpy as np
import pytest
from rclpy.node import Node
from sensor_msgs.msg import NavSatFix, NavSatStatus

from photogram_ros import msgs

pytestmark = pytest.mark.ros

LAT0, LON0 = 47.3977, 8.5456


def _fix(k: int, status: int = NavSatStatus.STATUS_GBAS_FIX) -> NavSatFix:
    # 4 m a step east, then the step north: a track of corners
    return msgs.navsatfix_msg(1_000_000_000 * k, LAT0 + (k // 10) * 2e-5, LON0 + k * 5.3e-5, 540.0 + k, status,
                              [0.01, 0.01, 0.04], NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN, 'gps')


def _spin_until(ex, cond, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        ex.spin_once(timeout_sec=0.05)
        if cond():
            return True
    return False


def test_station_shows_each_drones_live_position_and_track(tmp_path, rclpy_context):
    from rclpy.executors import SingleThreadedExecutor
    from photogram_ros.nodes.ground_station import GroundStationNode
    station = GroundStationNode({'out_dir': str(tmp_path / 'gs'), 'drones': '/drone1,/drone2', 'web': '127.0.0.1:0'},
                                context=rclpy_context)
    mav = Node('mavlink_node', namespace='/drone1', context=rclpy_context)
    px4 = Node('px4_adapter', namespace='/drone2', context=rclpy_context)
    intruder = Node('spoofer', namespace='/drone2', context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    for n in (station, mav, px4):
        ex.add_node(n)
    try:
        pub1 = mav.create_publisher(NavSatFix, '/drone1/gps/fix', 10)
        pub2 = px4.create_publisher(NavSatFix, '/drone2/gps/fix', 10)
        assert _spin_until(ex, lambda: pub1.get_subscription_count() and pub2.get_subscription_count(), 20)
        for k in range(25):      # one at a time: the station's subscription is best effort (the newest fix counts)
            pub1.publish(_fix(k))
            pub2.publish(_fix(k, NavSatStatus.STATUS_FIX))
            _spin_until(ex, lambda: min(d.versions['live'] for d in station.drones.values()) > k, 5)
        pub1.publish(_fix(25, NavSatStatus.STATUS_NO_FIX))    # no fix: not a position
        st = {}

        def got():
            st.update(station.status()['drones'])
            return all(st.get(k, {}).get('position', {}).get('track_points', 0) >= 25 for k in ('drone1', 'drone2'))
        assert _spin_until(ex, got, 20), {k: (v.get("position"), v["not_counted"], v["unknown_publishers"]) for k, v in st.items()}
        p1 = st['drone1']['position']
        assert p1['lat_deg'] == pytest.approx(LAT0 + 2 * 2e-5) and p1['lon_deg'] == pytest.approx(LON0 + 24 * 5.3e-5)
        assert p1['h_m'] == pytest.approx(564.0) and p1['status'] == NavSatStatus.STATUS_GBAS_FIX
        live = station.geojson('drone1', 'live')
        kinds = {f['properties']['role']: f for f in live['features']}
        assert kinds['position']['geometry']['coordinates'] == pytest.approx([p1['lon_deg'], p1['lat_deg']])
        line = np.array(kinds['track']['geometry']['coordinates'])
        assert len(line) == 25 and np.all(np.diff(line[:, 0]) > 0)
        # The page's server gives the same document.
        with urllib.request.urlopen(station.web.url + 'drones/drone1/live.geojson', timeout=10) as r:
            assert json.loads(r.read())['features'][-1]['properties']['role'] == 'position'
        # Another node of drone2's namespace publishing its gps/fix: its fixes are not counted.
        ex.add_node(intruder)
        bad = intruder.create_publisher(NavSatFix, '/drone2/gps/fix', 10)
        before = station.status()['drones']['drone2']['position']['track_points']
        end = time.monotonic() + 15
        while time.monotonic() < end and not station.status()['drones']['drone2']['not_counted'].get('/gps/fix'):
            bad.publish(_fix(99))
            pub2.publish(_fix(60))
            ex.spin_once(timeout_sec=0.05)
        st2 = station.status()['drones']['drone2']
        assert st2['not_counted'].get('/gps/fix') and '/drone2/spoofer' in st2['unknown_publishers']['/gps/fix']
        assert st2['position']['track_points'] <= before + 1
    finally:
        for n in (intruder, px4, mav, station):
            n.destroy_node()
