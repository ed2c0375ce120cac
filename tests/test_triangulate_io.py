"""The readers and writers behind `photogram-ros triangulate`: ODM gcp_list.txt and geo.txt, raw MAVLink
in a bag, the pose tables (poses.csv, trajectory.csv), and the flight report on an open MapStore."""

import csv
import math
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from photogram_ros.core.geodesy import LocalFrame, geodetic_to_crs
from photogram_ros.errors import DataError

LAT, LON, H = 47.3977, 8.5456, 488.0


def _utm(lat, lon, h=0.0):
    x, y, _ = geodetic_to_crs(lat, lon, h, 'EPSG:32632')
    return float(x), float(y)


# --- OpenDroneMap files --------------------------------------------------------------------------

def test_gcp_list_points_observations_and_check_names(tmp_path):
    from photogram_ros.io.control_file import read_gcp_list
    x, y = _utm(LAT, LON)
    p = tmp_path / 'gcp_list.txt'
    p.write_text(f'WGS84 UTM 32N\n# x y z px py image name\n'
                 f'{x:.4f} {y:.4f} 490.25 100.5 200.25 IMG_1.JPG GCP01\n'
                 f'{x:.4f} {y:.4f} 490.25 300.0 210.0 IMG_2.JPG GCP01\n'
                 f'{x + 30:.4f} {y:.4f} 491.0 50.0 60.0 IMG_2.JPG CHK07\n'
                 f'{x:.4f} {y + 40:.4f} 489.5 10.0 20.0 IMG_1.JPG P4\n'
                 f'{x + 5:.4f} {y + 5:.4f} 489.0 1.0 2.0 IMG_3.JPG\n')
    g = read_gcp_list(p, check_names=['P4'])
    assert g.crs == 'EPSG:32632'
    unnamed = f'{x + 5:.4f}_{y + 5:.4f}'
    assert list(g.points) == ['GCP01', 'CHK07', 'P4', unnamed]
    assert g.roles == {'GCP01': 'gcp', 'CHK07': 'check', 'P4': 'check', unnamed: 'gcp'}
    lat, lon, h = g.points['GCP01']
    assert abs(lat - LAT) < 1e-8 and abs(lon - LON) < 1e-8 and h == pytest.approx(490.25)
    assert set(g.image_uv) == {'IMG_1.JPG', 'IMG_2.JPG', 'IMG_3.JPG'}
    assert np.array_equal(g.image_uv['IMG_2.JPG']['GCP01'], [300.0, 210.0])
    assert sorted(g.image_uv['IMG_1.JPG']) == ['GCP01', 'P4']
    origin = LocalFrame(LAT, LON, 480.0)
    cps = g.in_map(origin, (0.02, 0.02, 0.03))
    assert [c.name for c in cps] == list(g.points) and [c.role for c in cps] == list(g.roles.values())
    # The CHK07 board is 30 m east of GCP01 in UTM: about that far east in the map (grid convergence
    # near the zone's central meridian is a fraction of a degree).
    d = cps[1].map_xyz - cps[0].map_xyz
    assert abs(np.hypot(d[0], d[1]) - 30.0) < 0.05 and abs(d[1]) < 0.5 and d[2] == pytest.approx(0.75, abs=0.01)
    assert np.allclose(cps[0].map_xyz, [0.0, 0.0, 10.25], atol=1e-3) and np.array_equal(cps[0].sigma_m,
                                                                                         [0.02, 0.02, 0.03])


@pytest.mark.parametrize('text, match', [
    ('', 'empty'),
    ('EPSG:32632\n465000 5249000 490 1 2\n', 'x y z px py image'),
    ('EPSG:32632\n465000 north 490 1 2 IMG.JPG\n', 'not a number'),
    ('NOT A CRS\n465000 5249000 490 1 2 IMG.JPG\n', 'coordinate reference system'),
])
def test_bad_gcp_lists_are_data_errors(tmp_path, text, match):
    from photogram_ros.io.control_file import read_gcp_list
    p = tmp_path / 'gcp_list.txt'
    p.write_text(text)
    with pytest.raises(DataError, match=match):
        read_gcp_list(p)


def test_geo_txt_projected_and_geographic(tmp_path):
    from photogram_ros.io.photo_block import EXIF_SIGMA_H_M, EXIF_SIGMA_V_M, read_geo_txt
    x, y = _utm(LAT, LON)
    (tmp_path / 'a.txt').write_text(f'EPSG:32632\nIMG_1.JPG {x:.4f} {y:.4f} 530.5 0 0 0 0.02 0.04\n'
                                    f'IMG_2.JPG {x:.4f} {y:.4f} 531.0\n')
    (tmp_path / 'b.txt').write_text(f'EPSG:4326\n# image lon lat h\nIMG_1.JPG {LON} {LAT} 530.5 1 2 3 0 0\n')
    a, b = read_geo_txt(tmp_path / 'a.txt'), read_geo_txt(tmp_path / 'b.txt')
    lat, lon, h, h_acc, v_acc = a['IMG_1.JPG']
    assert abs(lat - LAT) < 1e-8 and abs(lon - LON) < 1e-8 and h == pytest.approx(530.5)
    # Without accuracies: the EXIF geotag sigmas (5 m horizontal, 2 m vertical since 5df030e).
    assert (h_acc, v_acc) == (0.02, 0.04) and a['IMG_2.JPG'][3:] == (EXIF_SIGMA_H_M, EXIF_SIGMA_V_M) == (5.0, 2.0)
    assert b['IMG_1.JPG'] == (LAT, LON, 530.5, 1e-3, 1e-3)      # zero accuracies floored
    (tmp_path / 'c.txt').write_text('EPSG:4326\nIMG_1.JPG 8.5 47.3\n')
    with pytest.raises(DataError, match='image x y z'):
        read_geo_txt(tmp_path / 'c.txt')


# --- raw MAVLink in a bag --------------------------------------------------------------------------

@pytest.fixture(scope='module')
def mavlink_only_bag(sample_bag, tmp_path_factory):
    """The sample bag without /gps/fix: positions must come from its raw MAVLink."""
    from photogram_ros.io.bag import BagReader, BagWriter
    out = tmp_path_factory.mktemp('mav') / 'bag'
    with BagReader(sample_bag) as r, BagWriter(out) as w:
        for m in r.messages():
            if m.topic != '/gps/fix':
                w.add_topic(m.topic, m.msgtype)
                w.write_raw(m.topic, m.stamp_ns, m.data)
    return out


def test_messages_from_bag_are_the_tlog_messages(sample_bag):
    """The bag's /mavlink/from_fcu carries the same packets as the flight's .tlog."""
    from photogram_ros.io.bag import BagReader, messages_from_bag
    from photogram_ros.io.mavlink import read_tlog
    with BagReader(sample_bag) as bag:
        got = list(messages_from_bag(bag))
    ref, _ = read_tlog(sample_bag / 'flight.tlog')
    assert len(got) == len(ref) > 1000
    assert [m.get_msgbuf() for m, _ in got] == [m.get_msgbuf() for m, _ in ref]
    stamps = np.array([t for _, t in got if t is not None])
    assert np.all(np.diff(stamps) >= 0) and len(stamps) == len(got)


def test_fixes_from_raw_mavlink_match_the_gps_fix_topic(sample_bag, mavlink_only_bag):
    from photogram_ros.io.bag import BagReader
    from photogram_ros.io.bag_keyframes import bag_fixes
    with BagReader(sample_bag) as bag:
        topic, where_topic = bag_fixes(bag)
    with BagReader(mavlink_only_bag) as bag:
        raw, where_raw = bag_fixes(bag)
    assert '/gps/fix' in where_topic and 'raw MAVLink' in where_raw
    assert len(raw) == len(topic) > 300
    for a, b in zip(topic, raw):
        # MAVLink carries 1e-7 degrees, millimetres and a millisecond clock.
        assert abs(a.stamp_ns - b.stamp_ns) < 1_000_000
        assert abs(a.lat_deg - b.lat_deg) < 1e-7 and abs(a.lon_deg - b.lon_deg) < 1e-7 and abs(a.h_m - b.h_m) < 1e-3
        assert b.cov_enu_m2.shape == (3, 3) and np.allclose(b.cov_enu_m2, a.cov_enu_m2,
                                                                   rtol=0.15)
        assert b.status == a.status


@pytest.mark.slow
def test_triangulate_bag_with_raw_mavlink_only(mavlink_only_bag, sample_bag, tmp_path):
    """Without /gps/fix the fixes decoded from raw MAVLink georeference the block as well (measured 3.7 cm,
    as with /gps/fix)."""
    from photogram_ros.sim.truth import GroundTruth
    out = tmp_path / 'at'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'triangulate', str(mavlink_only_bag),
                        '--out', str(out), '--lever-arm=0,-0.05,-0.20'], cwd=ROOT, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    truth = GroundTruth.load(sample_bag)
    err = [truth.origin.geodetic_to_enu(float(row['lat_deg']), float(row['lon_deg']), float(row['h_m']))
           - truth.frame_by_stamp(int(row['image']), 5_000_000).map_T_cam[:3, 3]
           for row in csv.DictReader(open(out / 'poses.csv'))]
    assert len(err) >= 40 and np.sqrt(np.mean(np.sum(np.square(err), axis=1))) < 0.05
    assert 'raw MAVLink' in (out / 'report.md').read_text()


# --- pose tables -----------------------------------------------------------------------------------

def _poses(origin):
    """A nadir camera 40 m up (omega = phi = kappa = 0) and one yawed: kappa 30 degrees."""
    T0 = np.eye(4)
    T0[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T0[:3, 3] = [10.0, -20.0, 40.0]
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    T1 = T0.copy()
    T1[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ T0[:3, :3]
    return np.array([T0, T1])


def test_pose_tables_have_their_columns_and_the_same_values(tmp_path):
    from photogram_ros.io.trajectory import POSES_COLUMNS, TRAJECTORY_COLUMNS, write_trajectory_csv
    origin = LocalFrame(LAT, LON, H)
    T = _poses(origin)
    write_trajectory_csv(tmp_path / 'poses.csv', POSES_COLUMNS, ['a,1.jpg', 'b.jpg'], T, origin, 'EPSG:32632')
    write_trajectory_csv(tmp_path / 'trajectory.csv', TRAJECTORY_COLUMNS, ['1.jpg', '2.jpg'], T, origin,
                         'EPSG:32632', [1, 2])
    p = list(csv.DictReader(open(tmp_path / 'poses.csv')))
    t = list(csv.DictReader(open(tmp_path / 'trajectory.csv')))
    assert list(p[0]) == ['image', 'x', 'y', 'z', 'crs', 'lat_deg', 'lon_deg', 'h_m', 'omega_deg', 'phi_deg',
                          'kappa_deg']
    assert list(t[0]) == ['image', 'stamp_ns', 'easting_m', 'northing_m', 'h_ellipsoid_m', 'lat_deg', 'lon_deg',
                          'omega_deg', 'phi_deg', 'kappa_deg']
    assert p[0]['image'] == 'a,1.jpg' and p[0]['crs'] == 'EPSG:32632' and t[1]['stamp_ns'] == '2'
    # Oracle for WGS84: the ENU offset (10, -20, 40) m over the meridian and prime-vertical radii of
    # curvature (second-order terms are below 0.1 mm here); the CRS columns are those positions in UTM.
    a, e2 = 6378137.0, 6.69437999014e-3
    w = 1 - e2 * math.sin(math.radians(LAT)) ** 2
    m_radius, n_radius = a * (1 - e2) / w ** 1.5, a / math.sqrt(w)
    lat = LAT + math.degrees(-20.0 / (m_radius + H))
    lon = LON + math.degrees(10.0 / ((n_radius + H) * math.cos(math.radians(LAT))))
    x, y = _utm(lat, lon)
    for rp, rt in zip(p, t):
        assert float(rp['lat_deg']) == pytest.approx(lat, abs=2e-9)
        assert float(rp['lon_deg']) == pytest.approx(lon, abs=2e-9)
        assert rp['lat_deg'] == rt['lat_deg'] and rp['lon_deg'] == rt['lon_deg']
        assert float(rp['x']) == pytest.approx(x, abs=1e-3) and rp['x'] == rt['easting_m']
        assert float(rp['y']) == pytest.approx(y, abs=1e-3) and rp['y'] == rt['northing_m']
        assert float(rp['z']) == float(rp['h_m']) == float(rt['h_ellipsoid_m']) == pytest.approx(H + 40.0, abs=1e-3)
    assert [float(p[0][k]) for k in ('omega_deg', 'phi_deg', 'kappa_deg')] == pytest.approx([0, 0, 0], abs=1e-9)
    assert abs(float(p[1]['kappa_deg'])) == pytest.approx(30.0, abs=1e-5) and float(t[1]['kappa_deg']) == \
        pytest.approx(float(p[1]['kappa_deg']), abs=1e-4)
    assert len(p[1]['kappa_deg'].split('.')[1]) == 5 and len(t[1]['kappa_deg'].split('.')[1]) == 4


def test_flight_report_takes_an_open_map_store(tmp_path, sample_bag):
    import cv2

    from photogram_ros.io.flight_report import build_report
    from photogram_ros.io.map_store import MapStore
    from photogram_ros.sim.truth import GroundTruth
    origin = LocalFrame(LAT, LON, H)
    store = MapStore(tmp_path / 'map', 0.1, 64)
    store.set_origin(origin)
    store.save_camera(GroundTruth.load(sample_bag).camera)
    for k, T in enumerate(_poses(origin)):
        store.save_keyframe_image(100 + k, cv2.imencode('.jpg', np.zeros((8, 8, 3), np.uint8))[1].tobytes())
        store.save_keyframe_pose(100 + k, T)
    for d in ('a', 'b'):
        (tmp_path / d).mkdir()
    fig_store = build_report(tmp_path / 'a', store, 'EPSG:32632', {})
    fig_path = build_report(tmp_path / 'b', tmp_path / 'map', 'EPSG:32632', {})
    assert fig_store['keyframes'] == fig_path['keyframes'] == 2
    a, b = ((tmp_path / d / 'trajectory.csv').read_text() for d in ('a', 'b'))
    assert a == b and a.splitlines()[1].startswith('100.jpg,100,')
