"""Camera ingest: simulator survey photos (EXIF time + GPS) and a video file onto the camera topics."""

from __future__ import annotations

import shutil
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import cv2
import numpy as np
import pytest

from photogram_ros.errors import ConfigError
from photogram_ros.io.image_source import FolderSource, VideoSource, open_source, read_exif_time_ns


@pytest.fixture(scope='module')
def survey(tmp_path_factory):
    """Simulated tiny survey with geotagged photos, its truth and the calibration YAML the simulator
    writes beside them (about 25 s)."""
    from photogram_ros.io.keyframe_block import camera_from_yaml
    from photogram_ros.sim.scenario import preset, simulate
    out = tmp_path_factory.mktemp('cam') / 'tiny'
    truth = simulate(preset('tiny', photos=True, fps=1.0, line_length_m=30.0), out)
    calib = out / 'photos' / 'camera.yaml'
    assert camera_from_yaml(calib) == truth.camera
    geo = {}
    for ln in (out / 'photos' / 'geo.txt').read_text().splitlines()[1:]:
        f = ln.split()
        geo[f[0]] = (float(f[2]), float(f[1]), float(f[3]))   # lat, lon, h ellipsoidal
    return out / 'photos', truth, calib, geo


def _frame_index(path) -> int:
    return int(Path(path).stem.split('_')[-1])


def test_folder_yields_photos_in_time_order_with_truth_stamps_and_exif_gps(survey, tmp_path):
    photos, truth, _, geo = survey
    # The photos alone, without the geo.txt the simulator writes beside them (it would replace the EXIF GPS).
    for p in photos.glob('*.JPG'):
        (tmp_path / p.name).symlink_to(p)
    src = FolderSource(tmp_path)
    frames = list(src)
    assert len(frames) == len(geo) >= 5
    assert src.notes == [] and src.skipped == []   # zone and sub-seconds present, nothing unreadable
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(stamps)
    for f in frames:
        assert f.stamp_ns == truth.frames[_frame_index(f.path)].stamp_ns
        lat, lon, h = geo[Path(f.path).name]
        assert f.gps is not None
        assert abs(f.gps.lat_deg - lat) < 1e-7 and abs(f.gps.lon_deg - lon) < 1e-7
        fix = f.gps.gnss_fix(f.stamp_ns, 5.0, 10.0)
        assert abs(fix.h_m - h) < 0.01                    # MSL -> ellipsoidal through the geoid
        assert abs(fix.h_m - f.gps.alt_msl_m) > 20.0     # the geoid undulation near Zurich is ~48 m
        assert fix.stamp_ns == f.stamp_ns and np.array_equal(np.diag(fix.cov_enu_m2), [25.0, 25.0, 100.0])
        assert f.image.shape == (truth.camera.height, truth.camera.width, 3) and f.image.dtype == np.uint8


def test_folder_order_comes_from_exif_not_names(survey, tmp_path):
    photos, truth, _, _ = survey
    names = sorted(p.name for p in photos.glob('*.JPG'))
    for i, n in enumerate(names):   # reversed names: name order would be backwards in time
        shutil.copy(photos / n, tmp_path / f'P{len(names) - i:03d}_{n}')
    frames = list(FolderSource(tmp_path))
    assert [Path(f.path).name.split('_', 1)[1] for f in frames] == names


def test_corrupt_files_are_skipped_and_counted(survey, tmp_path):
    photos, _, _, geo = survey
    for p in photos.glob('*.JPG'):
        shutil.copy(p, tmp_path / p.name)
    (tmp_path / 'IMG_0001.JPG').write_bytes(b'\xff\xd8\xff garbage, not a JPEG' * 10)
    whole = (photos / 'IMG_0002.JPG').read_bytes()
    (tmp_path / 'IMG_0003.JPG').write_bytes(whole[:len(whole) // 2])   # EXIF intact, pixels truncated
    src = FolderSource(tmp_path)
    frames = list(src)
    assert sorted(Path(p).name for p, _ in src.skipped) == ['IMG_0001.JPG', 'IMG_0003.JPG']
    assert sorted(Path(f.path).name for f in frames) == sorted(geo)
    assert src.notes == []   # the unreadable file did not force file-name order


def test_subsecond_and_zone_round_trip(tmp_path):
    from PIL import Image

    from photogram_ros.sim.photos import exif_bytes
    when = datetime(2026, 5, 28, 20, 26, 41, 375000, tzinfo=timezone.utc)
    img = Image.fromarray(np.zeros((8, 8, 3), np.uint8))
    img.save(tmp_path / 'a.jpg', exif=exif_bytes(47.0, 8.0, 400.0, when, 4.0))
    ns, zoned, sub = read_exif_time_ns(tmp_path / 'a.jpg', utc_offset_s=7200.0)
    assert zoned and sub
    assert ns == int(when.timestamp()) * 10**9 + 375_000_000   # the zone in the file wins over the guess
    # Same wall time written as local time two hours ahead of UTC, without zone tags.
    local = when + timedelta(hours=2)
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0x9003] = local.strftime('%Y:%m:%d %H:%M:%S')
    img.save(tmp_path / 'b.jpg', exif=exif.tobytes())
    ns_b, zoned_b, sub_b = read_exif_time_ns(tmp_path / 'b.jpg', utc_offset_s=7200.0)
    assert not zoned_b and not sub_b and ns_b == int(when.timestamp()) * 10**9


def test_folder_without_exif_times_falls_back_to_name_order(tmp_path):
    for i, name in enumerate(['c.png', 'a.png', 'b.png']):
        cv2.imwrite(str(tmp_path / name), np.full((8, 8, 3), i, np.uint8))
    src = FolderSource(tmp_path, fallback_period_s=0.5)
    frames = list(src)
    assert [Path(f.path).name for f in frames] == ['a.png', 'b.png', 'c.png']
    assert np.diff([f.stamp_ns for f in frames]).tolist() == [500_000_000] * 2
    assert any('file-name order' in n for n in src.notes)


def test_video_file_frame_count_and_stamps(tmp_path):
    path = tmp_path / 'clip.avi'
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*'MJPG'), 10.0, (64, 48))
    assert w.isOpened()
    for i in range(23):
        w.write(np.full((48, 64, 3), 10 * i, np.uint8))
    w.release()
    src = open_source(str(path))
    assert isinstance(src, VideoSource) and not src.is_device
    frames = list(src)
    assert len(frames) == 23
    dt_ms = np.diff([f.stamp_ns for f in frames]) / 1e6
    assert np.allclose(dt_ms, 100.0, atol=1.0)
    assert abs(frames[5].image.mean() - 50) < 3   # frames come out in order


def test_bad_sources_and_missing_calibration_are_config_errors(survey, rclpy_context, tmp_path):
    from photogram_ros.nodes.camera_node import CameraNode
    photos, _, calib, _ = survey
    with pytest.raises(ConfigError, match='source'):
        open_source(str(tmp_path / 'nowhere'))
    # Photos without any focal length in their EXIF, and no calibration file: say which parameter to set.
    for i in range(3):
        cv2.imwrite(str(tmp_path / f'p{i}.png'), np.full((8, 8, 3), i, np.uint8))
    with pytest.raises(ConfigError, match='calibration_file.*no usable focal length'):
        CameraNode({'source': str(tmp_path)}, context=rclpy_context)
    with pytest.raises(ConfigError, match='calibration_file'):
        CameraNode({'source': str(photos), 'calibration_file': str(tmp_path / 'missing.yaml')},
                   context=rclpy_context)


def _listener(ctx):
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image, NavSatFix
    node = Node('camera_listener', context=ctx)
    got = {'image': [], 'info': [], 'fix': [], 'image_wall_s': []}

    def on_image(m):
        got['image'].append(m)
        got['image_wall_s'].append(time.monotonic())

    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Image, 'camera/image_raw', on_image, qos)
    node.create_subscription(CameraInfo, 'camera/camera_info', got['info'].append, qos)
    node.create_subscription(NavSatFix, 'gps/fix', got['fix'].append, qos)
    return node, got


def _spin_until(executor, cond, timeout_s=15.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not cond():
        executor.spin_once(timeout_sec=0.05)
    return cond()


def test_node_publishes_image_info_and_exif_fix(survey, rclpy_context, tmp_path):
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import NavSatFix

    from photogram_ros import msgs
    from photogram_ros.nodes.camera_node import CameraNode
    photos, truth, calib, geo = survey
    for p in photos.glob('*.JPG'):
        shutil.copy(p, tmp_path / p.name)
    (tmp_path / 'IMG_0001.JPG').write_bytes(b'not an image')
    n = len(geo)
    cam = CameraNode({'source': str(tmp_path), 'calibration_file': str(calib), 'rate': 0.0, 'autostart': False,
                      'exif_sigma_m': 3.0}, context=rclpy_context)
    listener, got = _listener(rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(cam)
    ex.add_node(listener)
    try:
        assert _spin_until(ex, lambda: cam.pub_image.get_subscription_count() > 0)
        while cam.publish_next():
            ex.spin_once(timeout_sec=0.01)
        assert cam.finished
        assert _spin_until(ex, lambda: len(got['image']) == n and len(got['fix']) == n and len(got['info']) == n)
    finally:
        ex.shutdown()
        listener.destroy_node()
        cam.destroy_node()
    stamps = [msgs.ns_from_time(m.header.stamp) for m in got['image']]
    assert stamps == sorted(truth.frames[_frame_index(p)].stamp_ns for p in geo)
    assert [msgs.ns_from_time(m.header.stamp) for m in got['fix']] == stamps
    img = msgs.image_from_msg(got['image'][0])
    assert got['image'][0].encoding == 'bgr8' and img.shape == (truth.camera.height, truth.camera.width, 3)
    assert msgs.camera_from_info(got['info'][0]).fx == pytest.approx(truth.camera.fx)
    first = sorted(geo, key=lambda k: truth.frames[_frame_index(k)].stamp_ns)[0]
    fix = msgs.fix_from_navsatfix(got['fix'][0])
    assert abs(fix['lat_deg'] - geo[first][0]) < 1e-7 and abs(fix['h_m'] - geo[first][2]) < 0.01
    assert fix['covariance_type'] == NavSatFix.COVARIANCE_TYPE_APPROXIMATED
    assert np.allclose(np.diag(fix['covariance_enu_m2']), [9.0, 9.0, 4.0])   # vertical: exif_sigma_v_m, 2 m
    c = cam.diag.counts()
    assert c['frames'] == n and c['fixes'] == n and c['skipped_unreadable'] == 1


def test_node_timer_plays_folder_at_scaled_exif_timing(survey, rclpy_context):
    from rclpy.executors import SingleThreadedExecutor

    from photogram_ros import msgs
    from photogram_ros.nodes.camera_node import CameraNode
    photos, truth, calib, geo = survey
    rate = 20.0
    listener, got = _listener(rclpy_context)
    cam = CameraNode({'source': str(photos), 'calibration_file': str(calib), 'rate': rate,
                      'publish_exif_fix': False}, context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(cam)
    ex.add_node(listener)
    try:
        assert _spin_until(ex, lambda: cam.finished and len(got['image']) == len(geo))
    finally:
        ex.shutdown()
        listener.destroy_node()
        cam.destroy_node()
    assert got['fix'] == []
    stamps = np.array([msgs.ns_from_time(m.header.stamp) for m in got['image']])
    span_s = (stamps[-1] - stamps[0]) * 1e-9
    assert span_s > 10.0
    # Published in EXIF-time order, each stamped with its own EXIF time (the pacing in wall time at `rate` is a
    # bench's measure: a wall-clock bound fails on a loaded machine).
    assert np.all(np.diff(stamps) > 0) and np.all(np.diff(got['image_wall_s']) >= 0)
    print(f"{span_s:.1f} s of photos at rate {rate:g} in {got['image_wall_s'][-1] - got['image_wall_s'][0]:.2f} s wall")


def test_simulated_photos_carry_exif_intrinsics(survey):
    """The simulator's EXIF as a real camera's: FocalLength x FocalPlaneXResolution gives its focal length
    to the rationals' rounding (measured 5.2e-5 px of 520 px), FocalLengthIn35mmFilm alone (an integer
    number of mm) within 0.45 %."""
    from photogram_ros.core.exif_intrinsics import intrinsics_from_exif
    from photogram_ros.io.image_source import exif_intrinsics, read_exif_camera
    photos, truth, _, _ = survey
    first = sorted(photos.glob('*.JPG'))[0]
    est = exif_intrinsics(first)
    assert est.source == 'focal_plane' and (est.camera.width, est.camera.height) == (truth.camera.width,
                                                                                     truth.camera.height)
    tags = read_exif_camera(first)
    only35 = intrinsics_from_exif(type(tags)(tags.width_px, tags.height_px, focal_35mm=tags.focal_35mm))
    print(f'simulator photos: focal plane {est.camera.fx:.5f} px, 35 mm {only35.camera.fx:.2f} px, '
          f'truth {truth.camera.fx:.2f} px')
    assert abs(est.camera.fx - truth.camera.fx) < 1.5 * MEASURED_FOCAL_PLANE_PX and est.camera.fy == est.camera.fx
    assert only35.source == '35mm' and abs(only35.camera.fx / truth.camera.fx - 1) < 1.5 * MEASURED_35MM_REL


MEASURED_FOCAL_PLANE_PX = 5.2e-5
MEASURED_35MM_REL = 0.0045


def test_node_without_calibration_file_takes_the_exif_camera(survey, rclpy_context):
    from photogram_ros.nodes.camera_node import CameraNode
    photos, truth, _, _ = survey
    cam = CameraNode({'source': str(photos), 'autostart': False}, context=rclpy_context)
    try:
        assert abs(cam.camera.fx / truth.camera.fx - 1) < 0.03
        assert cam.camera.dist == (0.0,) * 5 and cam.camera.width == truth.camera.width
    finally:
        cam.destroy_node()


def test_a_photo_without_exif_time_is_skipped_not_the_folder_timing(survey, tmp_path):
    """Issue 15.8: one PNG without DateTimeOriginal among timed JPEGs kept the folder in name order,
    1 s apart; now the PNG is skipped and named, the others keep their EXIF times."""
    photos, truth, _, geo = survey
    for p in photos.glob('*.JPG'):
        shutil.copy(p, tmp_path / p.name)
    cv2.imwrite(str(tmp_path / 'AAA_screenshot.png'), np.full((48, 64, 3), 7, np.uint8))
    (tmp_path / 'IMG_9999.JPG').write_bytes(b'')            # and an empty file
    src = FolderSource(tmp_path)
    frames = list(src)
    assert [Path(f.path).name for f in frames] == sorted(geo, key=lambda k: truth.frames[_frame_index(k)].stamp_ns)
    assert all(f.stamp_ns == truth.frames[_frame_index(f.path)].stamp_ns for f in frames)
    why = {Path(p).name: w for p, w in src.skipped}
    assert set(why) == {'AAA_screenshot.png', 'IMG_9999.JPG'}
    assert 'no EXIF DateTimeOriginal' in why['AAA_screenshot.png'] and 'empty file' in why['IMG_9999.JPG']
    assert not any('file-name order' in n for n in src.notes)


def test_photo_block_reads_exif_positions(survey):
    from photogram_ros.io.photo_block import exif_position as _read_exif
    photos, _, _, geo = survey
    name = sorted(geo)[1]
    lat, lon, h, h_acc, v_acc = _read_exif(photos / name)
    assert abs(lat - geo[name][0]) < 1e-7 and abs(lon - geo[name][1]) < 1e-7 and abs(h - geo[name][2]) < 0.01
    assert (h_acc, v_acc) == (5.0, 2.0)
    assert _read_exif(photos / 'geo.txt') is None
