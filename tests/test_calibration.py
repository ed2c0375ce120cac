"""Chessboard calibration on OpenCV's real sample images (9x6 inner corners, 640x480)."""

import cv2
import numpy as np
import pytest

from conftest import shared_data
from photogram_ros.core.calibration import OK, TOO_FEW_VIEWS, calibrate, parse_board
from photogram_ros.core.camera import PinholeCamera, load_calibration, save_opencv_yaml
from photogram_ros.errors import CalibrationError, DataError


@pytest.fixture(scope='module')
def views():
    paths = sorted(shared_data('chessboard').glob('left*.jpg'))
    return [(p.name, cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)) for p in paths]


def test_calibration_without_rejection_matches_opencv_reference(views):
    # reject_floor_px=inf keeps every view: the same fit as OpenCV's own sample (RMS ~0.41 px, fx ~536).
    res = calibrate(views, (9, 6), 1.0, reject_floor_px=np.inf)
    print(f'all {len(res.used)} views: RMS {res.rms_px:.3f} px, fx {res.camera.fx:.1f} fy {res.camera.fy:.1f} '
          f'cx {res.camera.cx:.1f} cy {res.camera.cy:.1f}')
    assert res.status == OK and len(res.used) == 13
    assert 0.30 < res.rms_px < 0.50
    assert abs(res.camera.fx - 536) < 6 and abs(res.camera.fy - 536) < 6
    assert abs(res.camera.cx - 342) < 6 and abs(res.camera.cy - 236) < 6


def test_bad_view_rejected_and_rms_improves(views):
    full = calibrate(views, (9, 6), 1.0, reject_floor_px=np.inf)
    res = calibrate(views, (9, 6), 1.0)
    print(f'kept {len(res.used)} views, rejected {res.rejected}: RMS {res.rms_px:.3f} px')
    assert res.ok
    assert res.rejected, 'left02 is a known poor view (RMS > 1 px) and should be rejected'
    assert res.rms_px < full.rms_px
    assert max(res.view_rms_px.values()) <= 1.0
    # The same lens either way: the rejected view only perturbed the fit.
    assert abs(res.camera.fx / full.camera.fx - 1) < 0.01
    assert abs(res.camera.cx - full.camera.cx) < 3 and abs(res.camera.cy - full.camera.cy) < 3


def test_unreadable_views_are_reported_not_fatal(views):
    blank = np.full((480, 640), 128, np.uint8)
    res = calibrate(views[:4] + [('blank', blank)], (9, 6), 1.0)
    assert res.status == TOO_FEW_VIEWS and 'blank' in res.rejected and res.camera is None


def test_board_and_input_errors():
    assert parse_board('9x6') == (9, 6)
    with pytest.raises(DataError):
        parse_board('nine by six')
    with pytest.raises(DataError):
        calibrate([], (9, 6))


def test_calibration_files_round_trip(tmp_path):
    cam = PinholeCamera(640, 480, 534.1, 534.2, 342.8, 233.7, (-0.27, 0.005, 0.001, 0.0, 0.18))
    save_opencv_yaml(cam, tmp_path / 'cv.yaml')
    back = load_calibration(tmp_path / 'cv.yaml')
    assert back == cam
    # OpenCV itself reads what we wrote.
    fs = cv2.FileStorage(str(tmp_path / 'cv.yaml'), cv2.FILE_STORAGE_READ)
    assert np.allclose(fs.getNode('camera_matrix').mat(), cam.K)
    fs.release()
    import yaml
    (tmp_path / 'ros.yaml').write_text(yaml.safe_dump(cam.to_ros_yaml_dict()))
    assert load_calibration(tmp_path / 'ros.yaml') == cam
    (tmp_path / 'bad.yaml').write_text('%YAML:1.0\n---\ncamera_matrix: 3\n')
    with pytest.raises(CalibrationError):
        load_calibration(tmp_path / 'bad.yaml')


def test_calibrate_command_writes_yaml(tmp_path):
    from photogram_ros.cli import main
    imgs = [str(p) for p in sorted(shared_data('chessboard').glob('left*.jpg'))]
    out = tmp_path / 'cal.yaml'
    assert main(['calibrate', *imgs, '--board', '9x6', '--square', '1.0', '--out', str(out)]) == 0
    cam = load_calibration(out)
    assert abs(cam.fx - 536) < 6 and (cam.width, cam.height) == (640, 480)
