"""A stray image never refuses a photo set in `triangulate` (issue 48): a panorama, a thumbnail or a byte-identical
copy of a survey photo among the photos is named and left out (io/photo_block.py), the block made of the others;
the live graph's side is tests/test_faults_odd_photo.py (docs/faults.md)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_data


def _toledo_with_strays(tmp_path: Path, n: int) -> Path:
    """The first `n` toledo photos (2400x1800, DJI FC350) with a 100 MP panorama and a thumbnail (neither with an
    EXIF focal length, as stitching and thumbnail tools write them) and a copy of the second photo downloaded
    twice ('DJI_0064 (1).JPG')."""
    from PIL import Image
    src = sorted(shared_data('photos', 'toledo', 'images').glob('*.JPG'))[:n]
    photos = tmp_path / 'photos'
    photos.mkdir()
    for p in src:
        shutil.copy2(p, photos / p.name)
    Image.fromarray(np.zeros((8400, 12000), np.uint8)).save(photos / 'PANO_0001.JPG', quality=50)
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(photos / 'DJI_0063_thumb.JPG')
    shutil.copy2(src[1], photos / f'{src[1].stem} (1).JPG')
    return photos


def test_strays_are_named_and_left_out_of_the_block(tmp_path, recwarn):
    from photogram_ros.io.photo_block import read_photo_block
    photos = _toledo_with_strays(tmp_path, n=4)
    lines = []
    block = read_photo_block(photos, log=lines.append)
    names = [r.name for r in block.records]
    assert names == ['DJI_0063.JPG', 'DJI_0064.JPG', 'DJI_0065.JPG', 'DJI_0066.JPG']
    assert (block.camera.width, block.camera.height) == (2400, 1800)
    assert block.excluded['DJI_0064 (1).JPG'] == 'identical to DJI_0064.JPG (a duplicate copy)'
    assert '12000x8400' in block.excluded['PANO_0001.JPG'] and 'panorama' in block.excluded['PANO_0001.JPG']
    assert '160x120' in block.excluded['DJI_0063_thumb.JPG']
    said = '\n'.join(lines)
    assert 'DJI_0064 (1).JPG identical to DJI_0064.JPG' in said and 'PANO_0001.JPG (12000x8400)' in said, said
    assert not [w for w in recwarn if 'DecompressionBomb' in type(w.message).__name__]


def test_a_calibration_file_leaves_out_photos_of_another_size(tmp_path):
    """With --camera, a photo of another size than the calibration's is named and left out; when no photo has its
    size the set is refused with the sizes and the option to use (no API hint)."""
    from photogram_ros.errors import CalibrationError
    from photogram_ros.io.photo_block import _camera_and_left_out
    photos = _toledo_with_strays(tmp_path, n=3)
    calib = tmp_path / 'camera.yaml'
    calib.write_text('image_width: 2400\nimage_height: 1800\ncamera_name: fc350\ncamera_matrix:\n  rows: 3\n'
                     '  cols: 3\n  data: [2300, 0, 1200, 0, 2300, 900, 0, 0, 1]\ndistortion_model: plumb_bob\n'
                     'distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0, 0, 0, 0, 0]\n')
    images = sorted(photos.iterdir())
    notes = []
    cam, from_exif, used, why = _camera_and_left_out(photos, images, calib, notes)
    assert not from_exif and cam.width == 2400
    assert sorted(why) == ['DJI_0063_thumb.JPG', 'PANO_0001.JPG'] and len(used) == 4
    assert 'calibration\'s 2400x1800' in why['PANO_0001.JPG']
    small = tmp_path / 'small.yaml'
    small.write_text(calib.read_text().replace('width: 2400', 'width: 1200').replace('height: 1800', 'height: 900')
                     .replace('1200, 0, 2300, 900', '600, 0, 2300, 450'))
    with pytest.raises(CalibrationError) as exc:
        _camera_and_left_out(photos, [p for p in images if p.name.startswith('DJI_006') and '_' not in p.stem[4:]], small, [])
    assert 'but the calibration' in str(exc.value) and '--camera' in str(exc.value)
    assert 'scaled()' not in str(exc.value)
