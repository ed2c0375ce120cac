"""Keyframe images at the resolution the map's cell needs (core/gsd.keyframe_reduction): the reduction, stereo
on reduced images, the map keeping the full-resolution JPEG, and the targets of a still-compressed keyframe."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import shared_data
from photogram_ros import msgs
from photogram_ros.core import gsd
from photogram_ros.core.control import detect_keyframe_targets, detect_keyframe_targets_encoded
from photogram_ros.core.stereo import StereoParams, stereo_pair
from photogram_ros.errors import ConfigError, DataError
from photogram_ros.params import from_dict
from test_target_detection_fast import paint_markers


def test_reduction_is_one_at_the_simulators_size_and_four_at_20_mp():
    assert gsd.keyframe_reduction(640, 480) == 1
    assert gsd.keyframe_reduction(1920, 1080) == 2
    assert gsd.keyframe_reduction(5472, 3648) == 4
    # the reduced pixel is never coarser than the map cell (in full pixels: CELL_PER_SPACING / downscale)
    for w, h in [(640, 480), (1280, 720), (1920, 1080), (2400, 1800), (4000, 3000), (5472, 3648), (8192, 5460)]:
        r = gsd.keyframe_reduction(w, h)
        assert r <= gsd.CELL_PER_SPACING / gsd.matching_downscale(w, h) < 2 * r or r == gsd.MAX_KEYFRAME_REDUCTION


def test_stereo_params_for_reduced_images_keep_the_matched_resolution():
    p = from_dict(StereoParams, {'downscale': 0.125})
    assert gsd.for_reduced_images(p, 1) is p
    assert gsd.for_reduced_images(p, 4).downscale == 0.5
    with pytest.raises(ConfigError):
        gsd.for_reduced_images(p, 16)
    with pytest.raises(ConfigError):
        gsd.for_reduced_images(StereoParams(), 2)   # AUTO: resolve first


def test_decode_reduced_gives_the_scaled_cameras_size():
    img = np.random.default_rng(0).integers(0, 255, (480, 640, 3), np.uint8)
    ok, buf = cv2.imencode('.jpg', img)
    assert ok
    small = msgs.decode_reduced(buf.tobytes(), 4)
    assert small.shape == (120, 160, 3)
    with pytest.raises(DataError):
        msgs.decode_reduced(b'not a jpeg', 2)
    with pytest.raises(DataError):
        msgs.decode_reduced(buf.tobytes(), 3)


@pytest.fixture(scope='module')
def sim_pair():
    from helpers.sim_world import rendered, world
    cfg, _, terrain, _, _ = world('tiny')
    frames = [(T, img) for _, T, img in rendered((2.0, 3.75))]
    return cfg.camera(), terrain, frames, cfg


def test_stereo_on_half_size_images_matches_the_full_ones(sim_pair):
    """A pair matched at half resolution from full images and from images halved beforehand (the camera scaled,
    the downscale doubled): the same rectified size (to the pixel the image edges round to), and heights as close to the terrain."""
    cam, terrain, ((Ta, ia), (Tb, ib)), cfg = sim_pair
    p = from_dict(StereoParams, {'downscale': 0.5})
    full = stereo_pair(cam, ia, Ta, ib, Tb, p, depth_range_m=(20.0, 55.0))
    half = [cv2.resize(i, (cam.width // 2, cam.height // 2), interpolation=cv2.INTER_AREA) for i in (ia, ib)]
    red = stereo_pair(cam.scaled(0.5), half[0], Ta, half[1], Tb, gsd.for_reduced_images(p, 2),
                      depth_range_m=(20.0, 55.0))
    assert full.ok and red.ok, (full.message, red.message)
    assert abs(red.rect.width - full.rect.width) <= 1 and abs(red.rect.height - full.rect.height) <= 1
    assert red.rect.f_px == pytest.approx(full.rect.f_px)
    dz = [np.median(np.abs(r.cloud['z'] - terrain.height_at(r.cloud['x'], r.cloud['y']))) for r in (full, red)]
    assert dz[1] <= 1.5 * dz[0] + 0.1 * cfg.gsd_m, dz
    assert red.cloud.size >= 0.8 * full.cloud.size


def test_targets_of_a_compressed_keyframe_are_those_of_its_decoded_image():
    bg = cv2.imread(str(shared_data('photos', 'brighton_beach', 'images', 'DJI_0020.JPG')))
    bg = cv2.resize(bg, (4000, 3000), interpolation=cv2.INTER_AREA)
    img, truth = paint_markers(bg, (44, 60, 90, 150), np.random.default_rng(3))
    ok, buf = cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    from photogram_ros.core.camera import PinholeCamera
    cam = PinholeCamera(4000, 3000, 3000.0, 3000.0, 1999.5, 1499.5)
    decoded = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    before = detect_keyframe_targets(decoded, cam)
    after = detect_keyframe_targets_encoded(buf.tobytes(), cam)
    assert len(before) >= 8
    assert sorted(after['marker_id'].tolist()) == sorted(before['marker_id'].tolist())
    by_id = {int(r['marker_id']): (r['u'], r['v']) for r in before}
    for r in after:
        assert np.hypot(r['u'] - by_id[int(r['marker_id'])][0], r['v'] - by_id[int(r['marker_id'])][1]) < 0.1
    with pytest.raises(DataError):
        detect_keyframe_targets_encoded(buf.tobytes(), cam.scaled(0.5))


def test_map_keeps_the_full_jpeg_over_the_reduced_copy(tmp_path):
    from photogram_ros.stages.map import MapParams, MapStage
    stage = MapStage(from_dict(MapParams, {'map_dir': str(tmp_path / 'map'), 'coverage': False}))
    full = np.full((480, 640, 3), 90, np.uint8)
    ok, jpeg = cv2.imencode('.jpg', full)
    stage.add_image(5, np.zeros((240, 320, 3), np.uint8))      # the stereo copy first
    stage.add_image_jpeg(5, jpeg.tobytes())                    # then the full one replaces it
    stage.add_image(7, np.zeros((480, 640, 3), np.uint8))
    stage.add_image_jpeg(6, jpeg.tobytes())
    stage.add_image(6, np.zeros((240, 320, 3), np.uint8))      # a reduced copy after it does not
    sizes = {p.stem: cv2.imread(str(p)).shape[:2] for p in (tmp_path / 'map' / 'keyframes').glob('*.jpg')}
    assert sizes == {'5': (480, 640), '6': (480, 640), '7': (480, 640)}
    assert (tmp_path / 'map' / 'keyframes' / '6.jpg').read_bytes() == jpeg.tobytes()
    assert stage.diag.counts()['keyframes_saved'] == 3
    stage.close()
