"""A photo folder with a geo.txt beside it (a PPK `geotag`) replays on those positions: the camera node's
source (io/image_source.FolderSource) gives each photo its geo.txt position and accuracies instead of its
EXIF GPS."""

import cv2
import numpy as np

from photogram_ros.core import gnss_fix as gf
from photogram_ros.io.image_source import FolderSource


def test_geo_txt_positions_replace_the_exif_gps(tmp_path):
    for k in range(3):
        cv2.imwrite(str(tmp_path / f'IMG_{k}.jpg'), np.full((32, 48, 3), 40 * k, np.uint8))
    (tmp_path / 'geo.txt').write_text('EPSG:4326\n'
                                      'IMG_0.jpg 8.5000000 47.3000000 512.25 0 0 0 0.02 0.04\n'
                                      'IMG_1.jpg 8.5001000 47.3000500 512.40 0 0 0 0.03 0.05\n')
    src = FolderSource(tmp_path)
    frames = list(src)
    assert [type(f.gps) for f in frames] == [gf.GnssFix, gf.GnssFix, type(None)]
    assert [f.gps.source for f in frames[:2]] == ['geo.txt', 'geo.txt']
    assert any('from geo.txt' in n for n in src.notes)
    fix = frames[1].gps.gnss_fix(123, 5.0, 10.0)     # the EXIF sigmas given are not used
    assert (fix.lat_deg, fix.lon_deg, fix.h_m) == (47.30005, 8.5001, 512.40)
    assert np.allclose(np.diag(fix.cov_enu_m2), [0.03 ** 2, 0.03 ** 2, 0.05 ** 2])
    assert fix.cov_type == gf.COV_DIAGONAL_KNOWN and fix.stamp_ns == 123
