"""The camera model: pinhole with Brown-Conrady distortion (k1, k2, p1, p2, k3).

Identical to OpenCV's 5-term model and to sensor_msgs/CameraInfo's `plumb_bob`, so calibrations
move between the three without conversion. Pixel coordinates have their origin at the centre of
the top-left pixel (OpenCV and ROS). Points in the camera frame use the optical convention
(x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from photogram_ros.errors import CalibrationError

DISTORTION_MODEL = 'plumb_bob'


@dataclass(frozen=True)
class PinholeCamera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))  # k1, k2, p1, p2, k3

    def __post_init__(self):
        d = tuple(float(v) for v in np.asarray(self.dist, dtype=float).ravel())
        if len(d) < 5:
            d = d + (0.0,) * (5 - len(d))
        object.__setattr__(self, 'dist', d[:5])
        self.validate()

    def validate(self) -> None:
        """Raise CalibrationError when the numbers cannot describe a real camera."""
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CalibrationError(f'image size {self.width}x{self.height} must be positive')
        vals = [self.fx, self.fy, self.cx, self.cy, *self.dist]
        if not all(np.isfinite(v) for v in vals):
            raise CalibrationError('camera calibration contains NaN or infinite values')
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(f'focal length fx={self.fx}, fy={self.fy} px must be positive: '
                                   'the calibration is missing or was not filled in')
        if not (0 < self.cx < self.width and 0 < self.cy < self.height):
            raise CalibrationError(f'principal point ({self.cx:.1f}, {self.cy:.1f}) lies outside the '
                                   f'{self.width}x{self.height} image: wrong image size or calibration')

    def check_image_size(self, width: int, height: int) -> None:
        if (int(width), int(height)) != (self.width, self.height):
            raise CalibrationError(
                f'images are {width}x{height} but the calibration is for {self.width}x{self.height}: '
                'use the calibration of this camera mode, or scale it with PinholeCamera.scaled()')

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=float)

    def scaled(self, factor: float) -> 'PinholeCamera':
        """The same camera for images resized by `factor` (e.g. 0.5 for half resolution)."""
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        # Pixel centres: u' + 0.5 = factor * (u + 0.5)
        return replace(self, width=w, height=h, fx=self.fx * factor, fy=self.fy * factor,
                       cx=(self.cx + 0.5) * factor - 0.5, cy=(self.cy + 0.5) * factor - 0.5)

    # --- distortion in normalized coordinates -------------------------------------------------

    def distort(self, xy_n: np.ndarray) -> np.ndarray:
        """Undistorted normalized (N, 2) -> distorted normalized (N, 2)."""
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy_n[..., 0], xy_n[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def _distort_jacobian(self, x, y):
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dr = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r2 * r2
        j11 = radial + 2.0 * dr * x * x + 2.0 * p1 * y + 6.0 * p2 * x
        j12 = 2.0 * dr * x * y + 2.0 * p1 * x + 2.0 * p2 * y
        j22 = radial + 2.0 * dr * y * y + 6.0 * p1 * y + 2.0 * p2 * x
        return j11, j12, j12, j22

    def undistort_normalized(self, xy_d: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Distorted normalized (N, 2) -> undistorted normalized (N, 2) by Newton's method.

        Converges to 1e-12 within the calibrated field of view; OpenCV's fixed-point iteration
        stops at ~1e-3 px for strong distortion, which is too coarse for rendering truth.
        """
        xy_d = np.asarray(xy_d, dtype=float)
        if not any(self.dist) or not xy_d.size:   # (no points: a keyframe that saw none)
            return xy_d.copy()
        xy = xy_d.copy()
        for _ in range(iterations):
            err = self.distort(xy) - xy_d
            j11, j12, j21, j22 = self._distort_jacobian(xy[..., 0], xy[..., 1])
            det = j11 * j22 - j12 * j21
            dx = (j22 * err[..., 0] - j12 * err[..., 1]) / det
            dy = (-j21 * err[..., 0] + j11 * err[..., 1]) / det
            xy[..., 0] -= dx
            xy[..., 1] -= dy
            if np.max(np.abs(err)) < 1e-13:
                break
        return xy

    # --- pixels ----------------------------------------------------------------------------------

    def normalized_to_pixel(self, xy_n: np.ndarray) -> np.ndarray:
        """Undistorted normalized -> distorted pixels."""
        xd = self.distort(np.asarray(xy_n, dtype=float))
        return np.stack([self.fx * xd[..., 0] + self.cx, self.fy * xd[..., 1] + self.cy], axis=-1)

    def pixel_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels -> undistorted normalized coordinates (x/z, y/z)."""
        uv = np.asarray(uv, dtype=float)
        xd = np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], axis=-1)
        return self.undistort_normalized(xd)

    def max_radius_n(self) -> float:
        """The undistorted normalized radius (tan of the angle off the optical axis) up to which the radial
        distortion keeps the image radius growing, r (1 + k1 r^2 + k2 r^4 + k3 r^6); inf when it always does.
        Beyond it the polynomial folds back: a direction far outside the field of view would land inside the
        image (a strong barrel lens, k1 < 0, folds at about 1.5-2.5)."""
        k1, k2, _, _, k3 = self.dist
        # d/dr of r (1 + k1 r^2 + k2 r^4 + k3 r^6) = 1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3 with s = r^2.
        coeffs = np.trim_zeros(np.array([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0]), 'f')
        roots = np.roots(coeffs) if len(coeffs) > 1 else np.array([])
        s = roots[(np.abs(roots.imag) < 1e-12) & (roots.real > 0)].real
        return float(np.sqrt(s.min())) if len(s) else float('inf')

    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) points in the optical camera frame -> (N, 2) pixels and a mask of the points the camera can
        image: in front (z > 0) and within max_radius_n of the optical axis (beyond it the distortion folds
        back into the image; such a point's pixel is meaningless)."""
        p = np.asarray(points_cam, dtype=float)
        z = p[..., 2]
        in_front = z > 1e-9
        zs = np.where(in_front, z, 1.0)
        xy = p[..., :2] / zs[..., None]
        uv = self.normalized_to_pixel(xy)
        r_max = self.max_radius_n()
        if np.isfinite(r_max):
            in_front = in_front & (np.sum(xy * xy, axis=-1) < r_max * r_max)
        return uv, in_front

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> unit ray directions (N, 3) in the optical camera frame."""
        xy = self.pixel_to_normalized(uv)
        rays = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def in_image(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        u, v = uv[..., 0], uv[..., 1]
        return ((u >= -0.5 + margin_px) & (u <= self.width - 0.5 - margin_px)
                & (v >= -0.5 + margin_px) & (v <= self.height - 0.5 - margin_px))

    # --- ROS / file formats ----------------------------------------------------------------------

    def to_camera_info_fields(self) -> dict:
        """Fields of sensor_msgs/CameraInfo (lower-case names as in the message)."""
        K = self.K
        P = np.zeros((3, 4))
        P[:3, :3] = K
        return {'width': self.width, 'height': self.height, 'distortion_model': DISTORTION_MODEL,
                'd': list(self.dist), 'k': K.ravel().tolist(), 'r': np.eye(3).ravel().tolist(),
                'p': P.ravel().tolist()}

    @classmethod
    def from_camera_info_fields(cls, width, height, distortion_model, d, k) -> 'PinholeCamera':
        if distortion_model not in (DISTORTION_MODEL, 'rational_polynomial', '') and len(d):
            raise CalibrationError(f'distortion model {distortion_model!r} is not supported; '
                                   f'calibrate with the {DISTORTION_MODEL!r} (OpenCV 5-term) model')
        k = np.asarray(k, dtype=float).reshape(-1)
        if k.size != 9:
            raise CalibrationError(f'camera matrix K needs 9 values, got {k.size}')
        d = np.asarray(d, dtype=float).ravel()
        if d.size > 5 and np.any(d[5:] != 0):
            raise CalibrationError('only the 5-term plumb_bob distortion is supported '
                                   f'(got {d.size} non-zero terms)')
        return cls(int(width), int(height), k[0], k[4], k[2], k[5], tuple(d[:5]))

    def to_ros_yaml_dict(self, camera_name: str = 'camera') -> dict:
        """The camera_calibration_parsers YAML layout written by ROS's camera_calibration."""
        f = self.to_camera_info_fields()
        return {'image_width': self.width, 'image_height': self.height, 'camera_name': camera_name,
                'camera_matrix': {'rows': 3, 'cols': 3, 'data': f['k']},
                'distortion_model': DISTORTION_MODEL,
                'distortion_coefficients': {'rows': 1, 'cols': 5, 'data': f['d']},
                'rectification_matrix': {'rows': 3, 'cols': 3, 'data': f['r']},
                'projection_matrix': {'rows': 3, 'cols': 4, 'data': f['p']}}

    @classmethod
    def from_ros_yaml_dict(cls, d: dict) -> 'PinholeCamera':
        try:
            return cls.from_camera_info_fields(
                d['image_width'], d['image_height'], d.get('distortion_model', DISTORTION_MODEL),
                d['distortion_coefficients']['data'], d['camera_matrix']['data'])
        except (KeyError, TypeError) as exc:
            raise CalibrationError(f'calibration YAML lacks the field {exc}: expected the ROS '
                                   'camera_calibration layout (image_width, camera_matrix, ...)') from exc


# --- calibration files (appended: OpenCV FileStorage YAML, and a loader for both layouts) -------------


def save_opencv_yaml(camera: PinholeCamera, path, extra: dict | None = None) -> None:
    """Write `camera` as OpenCV FileStorage YAML (image_width, image_height, camera_matrix,
    distortion_coefficients), readable by cv2.FileStorage and by `load_calibration`."""
    import cv2
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise CalibrationError(f'cannot write the calibration file {path}')
    try:
        fs.write('image_width', int(camera.width))
        fs.write('image_height', int(camera.height))
        fs.write('camera_matrix', camera.K)
        fs.write('distortion_coefficients', camera.dist_array.reshape(1, 5))
        for key, value in (extra or {}).items():
            fs.write(key, value)
    finally:
        fs.release()


def load_opencv_yaml(path) -> PinholeCamera:
    import cv2
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise CalibrationError(f'cannot read {path} as OpenCV FileStorage YAML/XML')
    try:
        K = fs.getNode('camera_matrix').mat()
        D = fs.getNode('distortion_coefficients').mat()
        w = fs.getNode('image_width').real()
        h = fs.getNode('image_height').real()
    except cv2.error as exc:
        raise CalibrationError(f'{path} is not an OpenCV calibration file: {exc.err}') from exc
    finally:
        fs.release()
    if K is None or K.size != 9 or D is None:
        raise CalibrationError(f'{path} lacks camera_matrix (3x3) or distortion_coefficients: '
                               'expected the OpenCV calibration layout')
    if not w or not h:
        raise CalibrationError(f'{path} lacks image_width/image_height: the calibration must state the '
                               'image size it was made for')
    return PinholeCamera.from_camera_info_fields(int(w), int(h), DISTORTION_MODEL, D.ravel().tolist(),
                                                 K.ravel().tolist())


def load_calibration(path) -> PinholeCamera:
    """Read a calibration file in either the ROS camera_calibration YAML or OpenCV FileStorage layout."""
    from pathlib import Path
    p = Path(path)
    try:
        text = p.read_text(errors='replace')
    except OSError as exc:
        raise CalibrationError(f'cannot read the calibration file {path}: {exc}') from exc
    if text.lstrip().startswith('%YAML') or text.lstrip().startswith('<?xml'):
        return load_opencv_yaml(p)
    import yaml
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CalibrationError(f'{path} is not valid YAML: {exc}') from exc
    if not isinstance(doc, dict):
        raise CalibrationError(f'{path} is not a calibration file (expected a YAML mapping)')
    return PinholeCamera.from_ros_yaml_dict(doc)
