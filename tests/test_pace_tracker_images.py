"""tracker_node on compressed frames larger than the map's cell needs: keyframe images reduced for stereo
(gsd.keyframe_reduction), the camera's own JPEG at full resolution for the map, targets from the JPEG."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

pytestmark = pytest.mark.ros


def test_compressed_frames_give_reduced_keyframe_images_and_the_full_jpeg(rclpy_context, tmp_path):
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CompressedImage, Image, NavSatFix

    from photogram_ros import msgs
    from photogram_ros.core import gsd
    from photogram_ros.core.camera import save_opencv_yaml
    from photogram_ros.nodes.tracker_node import TrackerNode
    from test_tracker import SimFrames
    from test_tracker_node import _fix_at, _spin

    sim = SimFrames(4.0)
    cam = sim.camera.scaled(1920 / sim.camera.width)   # 1920 px wide: tracked reduced, keyframes reduced 2x for stereo
    r = gsd.keyframe_reduction(cam.width, cam.height)
    assert r == 2
    save_opencv_yaml(cam, tmp_path / 'cam.yaml')
    tracker = TrackerNode(overrides={'calibration_file': str(tmp_path / 'cam.yaml'), 'reliable_input': True,
                                     'queue_size': 100}, context=rclpy_context)
    got = {'image': [], 'jpeg': []}
    peer = Node('pace_peer', context=rclpy_context)
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    peer.create_subscription(Image, '/keyframes/image', got['image'].append, qos)
    peer.create_subscription(CompressedImage, '/keyframes/image/compressed', got['jpeg'].append, qos)
    pub = peer.create_publisher(CompressedImage, 'camera/image_raw/compressed', qos)
    pub_fix = peer.create_publisher(NavSatFix, 'gps/fix', qos)
    ex, _ = _spin([tracker, peer], rclpy_context)
    sent = {}
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and pub.get_subscription_count() == 0:
            time.sleep(0.05)
        for stamp, img, _ in sim.frames:
            big = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_CUBIC)
            ok, buf = cv2.imencode('.jpg', big, [cv2.IMWRITE_JPEG_QUALITY, 92])
            sent[stamp] = buf.tobytes()
            pub_fix.publish(_fix_at(stamp))
            pub.publish(msgs.compressed_msg_from_bytes(sent[stamp], stamp))
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and tracker.frames_done < len(sent):
            time.sleep(0.05)
        tracker.flush(timeout_s=10.0)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and (len(got['image']) < tracker.keyframes_published
                                               or len(got['jpeg']) < tracker.keyframes_published):
            time.sleep(0.05)
    finally:
        ex.shutdown()
    counts = tracker.diag.counts()
    tracker.destroy_node()
    assert tracker.keyframes_published >= 2 and len(got['image']) == tracker.keyframes_published
    for m in got['image']:
        assert (m.width, m.height) == (cam.width // r, cam.height // r)   # never the camera's pixels
    for m in got['jpeg']:
        assert bytes(m.data) == sent[msgs.ns_from_time(m.header.stamp)]   # the camera's bytes, not re-encoded
    assert {msgs.ns_from_time(m.header.stamp) for m in got['jpeg']} == \
        {msgs.ns_from_time(m.header.stamp) for m in got['image']}
    assert counts.get('frames_decoded_reduced', 0) == len(sent) and not counts.get('keyframe_images_reduced_from_full')
    # The reduced image is the photo at half size (libjpeg's DCT scaling: close to an area average).
    m = got['image'][0]
    full = cv2.imdecode(np.frombuffer(sent[msgs.ns_from_time(m.header.stamp)], np.uint8), cv2.IMREAD_COLOR)
    area = cv2.resize(full, (m.width, m.height), interpolation=cv2.INTER_AREA).astype(float)
    assert np.median(np.abs(msgs.image_from_msg(m).astype(float) - area)) <= 2.0
