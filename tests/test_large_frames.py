"""Large frames (12.6 MP, 4096 x 3072) as they come from a survey camera: compressed, decoded by the tracker at
its working size (core/tracker.EncodedImage), keyframe features in full-resolution pixels.

The frames are crops of one real photo (toledo's DJI_0063, upscaled x2.6) at known offsets along x: a
fronto-parallel scene seen by a camera translating parallel to it, so the same ground point moves by exactly
the crop offset between two frames. That offset, in full-resolution pixels, is the oracle: a keyframe table in
the tracker's reduced pixels (1/4 here) would show a quarter of it.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import shared_data
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.tracker import EncodedImage, Tracker, TrackerParams
from photogram_ros.errors import CalibrationError, DataError

W, H = 4096, 3072
STEP_PX = 320          # crop offset between frames, full-resolution px
N_FRAMES = 7


@pytest.fixture(scope='module')
def frames():
    """[(offset_x_px, jpeg bytes, BGR image as the JPEG decodes)] and the camera of the crops."""
    src = cv2.imread(str(shared_data('photos', 'toledo', 'images', 'DJI_0063.JPG')), cv2.IMREAD_COLOR)
    big = cv2.resize(src, None, fx=2.6, fy=2.6, interpolation=cv2.INTER_CUBIC)   # 6240 x 4680
    y0 = (big.shape[0] - H) // 2
    out = []
    for i in range(N_FRAMES):
        x0 = i * STEP_PX
        ok, buf = cv2.imencode('.jpg', big[y0:y0 + H, x0:x0 + W], [cv2.IMWRITE_JPEG_QUALITY, 90])
        assert ok
        out.append((x0, buf.tobytes(), cv2.imdecode(buf, cv2.IMREAD_COLOR)))
    cam = PinholeCamera(W, H, 3500.0, 3500.0, W / 2 - 0.5, H / 2 - 0.5, (0.0, 0.0, 0.0, 0.0, 0.0))
    return out, cam


def test_reduced_decode_is_the_area_reduction_of_the_full_decode(frames):
    seq, _ = frames
    _, jpeg, full = seq[0]
    enc = EncodedImage(jpeg)
    grey = cv2.cvtColor(full, cv2.COLOR_BGR2GRAY)
    for reduce in (2, 4, 8, 16):
        g = enc.reduced_grey(reduce)
        assert g.shape == (-(-H // reduce), -(-W // reduce)) and g.dtype == np.uint8
        area = cv2.resize(grey, (W // reduce, H // reduce), interpolation=cv2.INTER_AREA).astype(float)
        diff = np.abs(g[:H // reduce, :W // reduce].astype(float) - area)
        # Same pixel grid (a shift of one reduced pixel would leave edges differing by tens of DN).
        assert np.median(diff) <= 2.0 and np.percentile(diff, 99) < 12.0, (reduce, np.median(diff))
    assert np.array_equal(enc.full(), full)
    with pytest.raises(DataError):
        EncodedImage(jpeg[:1000] + b'\x00' * 10).full()
    with pytest.raises(DataError):
        EncodedImage(b'not an image').reduced_grey(4)


def test_compressed_large_frames_give_keyframes_in_full_resolution_pixels(frames):
    seq, cam = frames
    tr = Tracker(cam, TrackerParams())
    assert tr._work_cam.width == W // 4        # 4096 px tracked at a quarter (track_max_px 1024)
    kfs = []
    for i, (_, jpeg, _) in enumerate(seq):
        kfs += tr.process(EncodedImage(jpeg), 1_000_000_000 * (i + 1))
    kfs += tr.flush()
    assert len(kfs) >= 2, tr.stats
    offset = {1_000_000_000 * (i + 1): x0 for i, (x0, _, _) in enumerate(seq)}
    shifts = []
    for kf in kfs:
        obs = kf.observations
        assert len(obs) >= 100
        u, v = obs['u'], obs['v']
        assert u.min() >= -0.5 and u.max() <= W - 0.5 and v.min() >= -0.5 and v.max() <= H - 0.5
        assert u.max() > 0.75 * W and v.max() > 0.75 * H           # spread over the full frame, not a quarter
        xn = cam.pixel_to_normalized(np.column_stack([u, v]))
        np.testing.assert_allclose(np.column_stack([obs['xn'], obs['yn']]), xn, atol=1e-9)
        # The image decodes at full size on first read, the same pixels as the JPEG.
        frame = next(f for (x0, _, f) in seq if offset[kf.stamp_ns] == x0)
        assert kf.image.shape == (H, W, 3) and np.array_equal(kf.image, frame)
    for a, b in zip(kfs, kfs[1:]):
        common, ia, ib = np.intersect1d(a.observations['track_id'], b.observations['track_id'], return_indices=True)
        if len(common) < 20:
            continue
        du = b.observations['u'][ib] - a.observations['u'][ia]
        dv = b.observations['v'][ib] - a.observations['v'][ia]
        expected = -(offset[b.stamp_ns] - offset[a.stamp_ns])
        shifts.append((float(np.median(du)), expected, float(np.median(np.abs(du - expected))), float(np.median(dv))))
    print('keyframes', [(k.index, k.frame_index, len(k.observations)) for k in kfs], 'shifts', shifts)
    assert shifts, 'no two consecutive keyframes share 20 tracks'
    for med_du, expected, spread, med_dv in shifts:
        # Measured: medians within 0.001 px, spread 0.01-0.035 px (full-resolution px; 1/4 of that in reduced px).
        assert abs(med_du - expected) < 0.01 and spread < 0.06 and abs(med_dv) < 0.01, shifts


def test_compressed_and_decoded_frames_track_alike(frames):
    """The same frames given decoded (the full image, reduced by the tracker) or compressed (decoded reduced)
    give the same keyframe choice and tracks within a pixel."""
    seq, cam = frames
    out = {}
    for mode in ('decoded', 'compressed'):
        tr = Tracker(cam, TrackerParams())
        kfs = []
        for i, (_, jpeg, img) in enumerate(seq):
            kfs += tr.process(EncodedImage(jpeg) if mode == 'compressed' else img, 1_000_000_000 * (i + 1))
        out[mode] = kfs + tr.flush()
    a, b = out['decoded'], out['compressed']
    assert [k.frame_index for k in a] == [k.frame_index for k in b]
    k0a, k0b = a[0].observations, b[0].observations
    assert abs(len(k0a) - len(k0b)) <= 0.1 * len(k0a)


def test_a_compressed_frame_of_another_size_is_refused(frames):
    seq, cam = frames
    tr = Tracker(cam.scaled(0.5), TrackerParams())
    with pytest.raises(CalibrationError, match='calibration is for 2048x1536'):
        tr.process(EncodedImage(seq[0][1]), 1)
    assert tr.stats.frames == 0


@pytest.mark.ros
def test_photo_folder_through_camera_and_tracker_nodes_stays_compressed(frames, rclpy_context, tmp_path):
    """camera_node publishes the large JPEGs undecoded on camera/image_raw/compressed; tracker_node decodes
    them at its working size and publishes full-size keyframe images with full-resolution features."""
    import threading
    import time

    import yaml
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CompressedImage, Image, PointCloud2

    from photogram_ros import msgs
    from photogram_ros.nodes.camera_node import CameraNode
    from photogram_ros.nodes.tracker_node import TrackerNode

    seq, cam = frames
    folder = tmp_path / 'photos'
    folder.mkdir()
    for i, (_, jpeg, _) in enumerate(seq[:4]):
        (folder / f'IMG_{i:04d}.JPG').write_bytes(jpeg)        # no EXIF time: name order, 1 s apart
    calib = tmp_path / 'camera.yaml'
    calib.write_text(yaml.safe_dump(cam.to_ros_yaml_dict()))
    tracker = TrackerNode(overrides={'reliable_input': True, 'queue_size': 100, 'input_depth': 100,
                                     'calibration_file': str(calib)}, context=rclpy_context)
    listener = Node('large_listener', context=rclpy_context)
    images, features = [], []
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    listener.create_subscription(Image, '/keyframes/image', images.append, qos)
    jpegs = []
    listener.create_subscription(CompressedImage, '/keyframes/image/compressed', jpegs.append, qos)
    listener.create_subscription(PointCloud2, '/keyframes/features', features.append, qos)
    camera = CameraNode(overrides={'source': str(folder), 'calibration_file': str(calib), 'rate': 0.0,
                                   'compressed_above_px': 2000}, context=rclpy_context)
    ex = MultiThreadedExecutor(num_threads=2, context=rclpy_context)
    for n in (tracker, listener, camera):
        ex.add_node(n)
    thread = threading.Thread(target=ex.spin, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and tracker.frames_done < 4:
            time.sleep(0.05)
        assert camera.finished and camera.diag.counts().get('frames_compressed') == 4
        n = tracker.flush(timeout_s=30.0)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and min(len(features), len(jpegs)) < tracker.keyframes_published:
            time.sleep(0.05)
        counts = tracker.diag.counts()
        assert counts.get('frames_decoded_reduced') == 4 and counts.get('frames_tracked') == 4, counts
        assert tracker.keyframes_published >= 2 and len(features) == len(images) == tracker.keyframes_published, n
        first_ns = msgs.ns_from_time(images[0].header.stamp)      # keyframe 0 is photo 0; photos 1 s apart
        assert len(jpegs) == len(images)
        for img_msg, jpeg_msg, feat_msg in zip(images, jpegs, features):
            # keyframes/image at the map cell's resolution (4 x reduced at 4096 x 3072), decoded at that
            # reduction from the camera's JPEG; keyframes/image/compressed the camera's own bytes, full size.
            assert (img_msg.width, img_msg.height) == (W // 4, H // 4)
            i = round((msgs.ns_from_time(img_msg.header.stamp) - first_ns) * 1e-9)
            assert jpeg_msg.header.stamp == img_msg.header.stamp and bytes(jpeg_msg.data) == seq[i][1]
            assert np.array_equal(msgs.image_from_msg(img_msg),
                                  cv2.imdecode(np.frombuffer(seq[i][1], np.uint8),
                                               cv2.IMREAD_REDUCED_COLOR_4 | cv2.IMREAD_IGNORE_ORIENTATION))
            obs = msgs.features_from_keyframe_msg(feat_msg)
            assert obs['u'].max() > 0.75 * W and obs['v'].max() > 0.75 * H
    finally:
        ex.shutdown()
        for n in (camera, tracker, listener):
            n.destroy_node()


def test_camera_node_reads_large_whole_jpegs_undecoded(frames, tmp_path):
    """JpegFile: a whole JPEG above the threshold comes as its bytes and header size; a truncated one, a small
    one or a PNG is left to the usual decode (which names a truncated file's fault)."""
    from photogram_ros.nodes.camera_node import JpegFile
    seq, _ = frames
    jpeg = seq[0][1]
    whole, cut, png = tmp_path / 'a.jpg', tmp_path / 'b.jpg', tmp_path / 'c.png'
    whole.write_bytes(jpeg)
    cut.write_bytes(jpeg[:len(jpeg) // 2])
    cv2.imwrite(str(png), seq[0][2][:600, :800])
    got = JpegFile.read(whole, 2000)
    assert got is not None and got.size == (W, H) and got.data == jpeg
    assert JpegFile.read(whole, W) is None            # not above the threshold
    assert JpegFile.read(cut, 2000) is None
    assert JpegFile.read(png, 100) is None
