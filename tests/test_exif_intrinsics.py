"""Camera intrinsics from EXIF: a real DJI FC300S photo, the simulator's JPEGs, and the rules between sources."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from PIL import Image

from conftest import shared_data
from photogram_ros.core.exif_intrinsics import ExifCameraTags, intrinsics_from_exif
from photogram_ros.errors import CalibrationError, DataError
from photogram_ros.io.image_source import exif_intrinsics, image_file_problem, read_dji_xmp, read_exif_camera

# The FC300S (DJI Phantom 3 Professional): FocalLength 3.61 mm on a sensor 6.16 mm wide, the width
# OpenSfM's sensor database gives (opensfm/data/sensor_data.json, "DJI FC300S": 6.16), spanning the
# 4000 px of the 16:9 frame cut from the 4:3 sensor: 3.61 / 6.16 * 4000 = 2344.2 px.
FC300S_FOCAL_PX = 3.61 / 6.16 * 4000


def _dji_photo():
    return shared_data('photos', 'brighton_beach', 'images', 'DJI_0018.JPG')


def test_fc300s_focal_from_exif_within_3_percent_by_table_and_by_35mm_equivalent():
    tags = read_exif_camera(_dji_photo())
    assert (tags.width_px, tags.height_px, tags.make, tags.model) == (4000, 2250, 'DJI', 'FC300S')
    assert tags.focal_mm == pytest.approx(3.61) and tags.focal_35mm == 20
    est = intrinsics_from_exif(tags)
    assert est.source == 'sensor_table' and abs(est.camera.fx / FC300S_FOCAL_PX - 1) < 0.03
    assert est.camera.cx == pytest.approx(1999.5) and est.camera.cy == pytest.approx(1124.5)
    assert est.camera.dist == (0.0,) * 5 and 'distortion zero' in est.note
    # Without the table (an unknown model) the 35 mm equivalent, stated for the full 4:3 frame, gives it
    # within 1.5 %: 20 / 43.27 * 5000 px (the diagonal of the 4000 x 3000 frame) = 2311 px.
    unknown = dataclasses.replace(tags, model='FC999')
    est35 = intrinsics_from_exif(unknown)
    assert est35.source == '35mm' and 'crop' in est35.note
    print(f'FC300S: table {est.camera.fx:.1f} px, 35 mm {est35.camera.fx:.1f} px, truth {FC300S_FOCAL_PX:.1f} px')
    assert abs(est35.camera.fx / FC300S_FOCAL_PX - 1) < 0.03
    # Taking the 16:9 frame's own diagonal instead would be 9 % short: the crop rule matters.
    assert abs(20 / 43.27 * np.hypot(4000, 2250) / FC300S_FOCAL_PX - 1) > 0.05


def test_dji_xmp_fields_are_read():
    xmp = read_dji_xmp(_dji_photo())
    assert float(xmp['GimbalYawDegree']) == pytest.approx(45.0) and float(xmp['RelativeAltitude']) == pytest.approx(39.8)
    assert float(xmp['GimbalPitchDegree']) == pytest.approx(-89.9)


def test_source_priority_and_sanity_rules():
    base = ExifCameraTags(4000, 3000, 'DJI', 'FC300S', focal_mm=3.61, focal_35mm=20)
    # A DJI XMP calibrated focal (pixels) wins, with its principal point.
    xmp = intrinsics_from_exif(dataclasses.replace(base, xmp_focal_px=2300.5, xmp_cx_px=2010.0, xmp_cy_px=1490.0))
    assert xmp.source == 'xmp' and (xmp.camera.fx, xmp.camera.cx, xmp.camera.cy) == (2300.5, 2010.0, 1490.0)
    # The focal-plane resolution agrees with the table (6.16 mm for 4000 px): used.
    fp = intrinsics_from_exif(dataclasses.replace(base, focal_plane_px_per_mm=4000 / 6.2))
    assert fp.source == 'focal_plane' and fp.camera.fx == pytest.approx(3.61 * 4000 / 6.2)
    # Stated for the full-resolution sensor of a downsized image (sensor 12 mm): the table instead.
    assert intrinsics_from_exif(dataclasses.replace(base, focal_plane_px_per_mm=4000 / 12.0)).source == 'sensor_table'
    # Implausible sensor (0.1 mm) on an unknown camera: not used; nothing else -> a calibration error.
    odd = ExifCameraTags(640, 480, 'x', 'y', focal_mm=1.5, focal_plane_px_per_mm=6400.0)
    with pytest.raises(CalibrationError, match='no usable focal length'):
        intrinsics_from_exif(odd)
    # A 4:3 frame: the 35 mm equivalent by its own diagonal.
    e = intrinsics_from_exif(ExifCameraTags(4000, 3000, 'x', 'y', focal_35mm=24))
    assert e.camera.fx == pytest.approx(24 / 43.27 * 5000)


def test_unusable_files_are_named(tmp_path):
    good = tmp_path / 'a.jpg'
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(good, quality=90)
    assert image_file_problem(good) is None
    (tmp_path / 'empty.jpg').write_bytes(b'')
    assert image_file_problem(tmp_path / 'empty.jpg') == 'empty file (0 bytes)'
    (tmp_path / 'text.jpg').write_bytes(b'not an image at all' * 10)
    assert image_file_problem(tmp_path / 'text.jpg').startswith('not an image')
    data = good.read_bytes()
    (tmp_path / 'cut.jpg').write_bytes(data[:len(data) // 2])
    assert image_file_problem(tmp_path / 'cut.jpg').startswith('truncated or corrupt JPEG')
    with pytest.raises(DataError, match='text.jpg'):
        exif_intrinsics(tmp_path / 'text.jpg')
    with pytest.raises(CalibrationError, match='a.jpg'):
        exif_intrinsics(good)           # no focal length in its EXIF: the file is named
