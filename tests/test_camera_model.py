import cv2
import numpy as np
import pytest

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.errors import CalibrationError

CAM = PinholeCamera(640, 480, 520.0, 521.0, 320.2, 238.7, (-0.12, 0.05, 0.0005, -0.0003, -0.01))
RNG = np.random.default_rng(3)


def _points():
    xy = RNG.uniform(-0.6, 0.6, (400, 2))
    z = RNG.uniform(2, 50, 400)
    return np.column_stack([xy * z[:, None], z])


def test_project_matches_opencv():
    P = _points()
    uv, ok = CAM.project(P)
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), CAM.K, CAM.dist_array)
    assert ok.all()
    assert np.max(np.abs(uv - ref.reshape(-1, 2))) < 1e-9


def test_unproject_inverts_project():
    P = _points()
    uv, _ = CAM.project(P)
    rays = CAM.unproject(uv)
    assert np.max(np.abs(rays - P / np.linalg.norm(P, axis=1, keepdims=True))) < 1e-10


def test_undistort_agrees_with_opencv_iterative():
    uv = RNG.uniform([0, 0], [640, 480], (300, 2))
    ours = CAM.pixel_to_normalized(uv)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), CAM.K, CAM.dist_array, None, None, None,
                              (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)).reshape(-1, 2)
    assert np.max(np.abs(ours - ref)) < 1e-7


def test_points_behind_camera_are_flagged():
    uv, ok = CAM.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]))
    assert list(ok) == [False, True]


def test_directions_beyond_the_fold_of_the_distortion_are_flagged():
    # The radial polynomial r (1 + k1 r^2 + k2 r^4 + k3 r^6) of this barrel lens stops growing at the radius
    # where its slope, found here by a dense scan (the oracle), reaches zero: a direction beyond it would land
    # back inside the image. A ground point 2.35 off the axis (67 degrees) projects to a pixel in the image
    # (406, 430): flagged, as the camera cannot see it; every direction inside the image is kept.
    r = np.linspace(0.0, 4.0, 400001)
    k1, k2, _, _, k3 = CAM.dist
    rd = r * (1 + k1 * r ** 2 + k2 * r ** 4 + k3 * r ** 6)
    fold = r[np.argmax(np.diff(rd) <= 0)]
    assert CAM.max_radius_n() == pytest.approx(fold, abs=1e-4) and 1.5 < fold < 2.5
    far = np.array([[0.98, 2.14, 1.0]])
    uv, ok = CAM.project(far)
    assert CAM.in_image(uv)[0] and not ok[0]
    corners = CAM.unproject(np.array([[0.0, 0.0], [639.0, 479.0], [0.0, 479.0], [639.0, 0.0]]))
    assert CAM.project(corners * 30.0)[1].all()
    # No fold without distortion, or with a pincushion lens (k1 > 0): nothing beyond the image is flagged.
    for dist in ((0.0,) * 5, (0.1, 0.0, 0.0, 0.0, 0.0)):
        cam = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0, dist)
        assert cam.max_radius_n() == float('inf') and cam.project(far)[1][0]


def test_camera_info_and_yaml_round_trip():
    f = CAM.to_camera_info_fields()
    assert PinholeCamera.from_camera_info_fields(f['width'], f['height'], f['distortion_model'], f['d'], f['k']) == CAM
    assert PinholeCamera.from_ros_yaml_dict(CAM.to_ros_yaml_dict()) == CAM


def test_scaled_camera_projects_consistently():
    half = CAM.scaled(0.5)
    P = _points()
    uv, _ = CAM.project(P)
    uv2, _ = half.project(P)
    assert np.max(np.abs((uv + 0.5) * 0.5 - 0.5 - uv2)) < 1e-9


@pytest.mark.parametrize('kwargs, words', [
    (dict(fx=0.0), 'focal length'),
    (dict(cx=900.0), 'principal point'),
    (dict(width=0), 'image size'),
    (dict(fy=float('nan')), 'NaN'),
])
def test_bad_calibration_is_a_clear_error(kwargs, words):
    args = dict(width=640, height=480, fx=500.0, fy=500.0, cx=320.0, cy=240.0)
    args.update(kwargs)
    with pytest.raises(CalibrationError, match=words):
        PinholeCamera(**args)


def test_image_size_mismatch_is_reported():
    with pytest.raises(CalibrationError, match='1280x960'):
        CAM.check_image_size(1280, 960)


def test_no_points_undistort_to_no_points_with_a_distorted_lens():
    """A keyframe that saw no point: its empty pixel array goes through a lens with distortion (triangulate of
    seneca_part crashed on it once the in-flight pass had refined k1)."""
    from photogram_ros.core.camera import PinholeCamera
    cam = PinholeCamera(1600, 1200, 1000.0, 1000.0, 800.0, 600.0, dist=(-0.03, 0.02, 0.0, 0.0, 0.0))
    assert cam.pixel_to_normalized(np.zeros((0, 2))).shape == (0, 2)
