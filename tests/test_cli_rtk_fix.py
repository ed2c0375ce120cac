"""camera_node publishes a DJI RTK photo's fix as `triangulate` weighs it: the XMP RtkStd* sigmas and the RtkFlag's
class (io/image_source.dji_rtk_accuracy, one reading for both); photos without the XMP with triangulate's EXIF
sigmas (io/geo_txt.EXIF_SIGMA_H_M / EXIF_SIGMA_V_M)."""

from __future__ import annotations

import time
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest
from PIL import Image

from photogram_ros.core import gnss_fix as gf
from photogram_ros.io.geo_txt import EXIF_SIGMA_H_M, EXIF_SIGMA_V_M
from photogram_ros.sim.photos import dji_rtk_xmp, exif_bytes, insert_xmp

# name -> XMP (RtkFlag, RtkStdLon, RtkStdLat, RtkStdHgt) or None; the sigmas (h, v) and NavSatStatus expected
PHOTOS = {
    'DJI_0001.JPG': ((50, 0.012, 0.010, 0.020), (np.sqrt((0.012 ** 2 + 0.010 ** 2) / 2), 0.020), gf.STATUS_GBAS_FIX),
    'DJI_0002.JPG': ((50, 0.015, 0.018, 0.016), (np.sqrt((0.015 ** 2 + 0.018 ** 2) / 2), 0.016), gf.STATUS_GBAS_FIX),
    'DJI_0003.JPG': ((34, 0.03, 0.03, 0.05), (0.10, 0.20), gf.STATUS_GBAS_FIX),    # float: its class's floor
    'DJI_0004.JPG': ((16, 0.8, 0.8, 1.0), (1.5, 3.0), gf.STATUS_FIX),              # single: its floor
    'DJI_0005.JPG': (None, (EXIF_SIGMA_H_M, EXIF_SIGMA_V_M), gf.STATUS_FIX),      # plain EXIF
}


def _folder(root):
    t0 = datetime(2024, 3, 8, 10, 0, 0, tzinfo=timezone.utc)
    rng = np.random.default_rng(5)
    for k, (name, (xmp, _, _)) in enumerate(PHOTOS.items()):
        p = root / name
        Image.fromarray(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)).save(
            p, quality=90, exif=exif_bytes(46.5 + k * 1e-4, 6.5, 500.0, t0 + timedelta(seconds=2 * k), 4.4, (320, 240)))
        if xmp is not None:
            insert_xmp(p, dji_rtk_xmp(*xmp))
    return root


def test_exif_fix_and_triangulate_position_take_the_same_sigmas(tmp_path):
    from photogram_ros.io.image_source import read_exif_gps
    from photogram_ros.io.photo_block import exif_position
    _folder(tmp_path)
    for name, (_, (sh, sv), status) in PHOTOS.items():
        fix = read_exif_gps(tmp_path / name).gnss_fix(1, EXIF_SIGMA_H_M, EXIF_SIGMA_V_M)
        assert np.sqrt(np.diag(fix.cov_enu_m2)) == pytest.approx([sh, sh, sv], abs=1e-6), name
        assert fix.status == status, name
        assert fix.cov_type == (gf.COV_APPROXIMATED if PHOTOS[name][0] is None else gf.COV_DIAGONAL_KNOWN)
        assert exif_position(tmp_path / name)[3:] == pytest.approx((sh, sv), abs=1e-6), name


def test_camera_node_publishes_each_photos_rtk_sigmas_and_status(tmp_path, rclpy_context):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import NavSatFix

    from photogram_ros import msgs
    from photogram_ros.nodes.camera_node import CameraNode
    _folder(tmp_path)
    cam = CameraNode({'source': str(tmp_path), 'rate': 0.0, 'autostart': False}, context=rclpy_context)
    listener = Node('rtk_fix_listener', context=rclpy_context)
    got = []
    listener.create_subscription(NavSatFix, 'gps/fix', got.append,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(cam)
    ex.add_node(listener)
    try:
        deadline = time.monotonic() + 15
        while cam.pub_fix.get_subscription_count() == 0 and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        while cam.publish_next():
            ex.spin_once(timeout_sec=0.01)
        while len(got) < len(PHOTOS) and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
    finally:
        ex.shutdown()
        listener.destroy_node()
        cam.destroy_node()
    assert len(got) == len(PHOTOS)
    for m, (name, (xmp, (sh, sv), status)) in zip(got, PHOTOS.items()):   # published in shooting order
        fix = msgs.fix_from_navsatfix(m)
        assert np.sqrt(np.diag(fix['covariance_enu_m2'])) == pytest.approx([sh, sh, sv], abs=1e-6), name
        assert m.status.status == status, name
        assert m.position_covariance_type == (NavSatFix.COVARIANCE_TYPE_APPROXIMATED if xmp is None
                                              else NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN), name
