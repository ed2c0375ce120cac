"""A folder holding photos of two cameras (io/photo_block.py `_camera`): split by camera, the largest group is
used and the other photos are named as not used, with their camera; a zoom within 5 % stays one camera."""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
from PIL import Image

from photogram_ros.io.image_source import exif_intrinsics
from photogram_ros.io.photo_block import _camera
from photogram_ros.sim.photos import PIXEL_PITCH_MM, exif_bytes


def _photo(folder, name, size, focal_mm):
    when = datetime(2026, 5, 28, 12, 0, 0, tzinfo=timezone.utc)
    img = Image.fromarray(np.full((size[1], size[0], 3), 128, np.uint8))
    img.save(folder / name, quality=90, exif=exif_bytes(47.4, 8.5, 500.0, when, focal_mm, size))
    return folder / name


def test_photos_of_a_second_camera_are_split_off_and_named(tmp_path):
    src = tmp_path / 'photos'
    src.mkdir()
    main = [_photo(src, f'A_{k}.JPG', (640, 480), 520 * PIXEL_PITCH_MM) for k in range(5)]
    zoom = _photo(src, 'A_zoom.JPG', (640, 480), 530 * PIXEL_PITCH_MM)          # 1.9 % longer: the same camera
    second = [_photo(src, f'B_{k}.JPG', (800, 600), 700 * PIXEL_PITCH_MM) for k in range(3)]
    tele = _photo(src, 'C_0.JPG', (640, 480), 900 * PIXEL_PITCH_MM)            # same size, 73 % longer focal
    images = sorted(main + [zoom] + second + [tele])
    notes = []
    cam, from_exif, used = _camera(src, images, None, notes)
    assert from_exif and (cam.width, cam.height) == (640, 480)
    assert abs(cam.fx - exif_intrinsics(main[0]).camera.fx) < 1e-6
    assert sorted(p.name for p in used) == sorted(p.name for p in main + [zoom])
    other = [n for n in notes if 'photos of another camera not used' in n]
    assert len(other) == 2
    assert any('3 photos' in n and '800x600' in n and all(p.name in n for p in second) for n in other)
    assert any('1 photos' in n and 'C_0.JPG' in n for n in other)
    assert any('another focal length' in n and 'A_zoom.JPG' in n for n in notes)


def test_one_camera_keeps_every_photo(tmp_path):
    src = tmp_path / 'photos'
    src.mkdir()
    images = [_photo(src, f'A_{k}.JPG', (640, 480), 1.56) for k in range(3)]
    notes = []
    _, _, used = _camera(src, images, None, notes)
    assert used == images and not any('not used' in n for n in notes)
