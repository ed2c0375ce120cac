"""Chessboard calibration of the pinhole + Brown-Conrady camera with OpenCV.

Corners are found with `findChessboardCorners`, refined with `cornerSubPix`, and `calibrateCamera`
fits the 5-term model. Views whose own reprojection RMS is far above the others (a blurred board,
a mis-ordered corner grid) are rejected one at a time and the fit is repeated, so one bad photo
cannot bend the calibration. Too few usable views is an expected outcome, returned with a status.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.errors import CalibrationError, DataError

OK = 'ok'
TOO_FEW_VIEWS = 'too_few_views'


@dataclass
class CalibrationResult:
    status: str
    camera: PinholeCamera | None = None
    rms_px: float = float('nan')                          # over the views kept
    view_rms_px: dict = field(default_factory=dict)       # name -> RMS of that view, px (kept views)
    rejected: dict = field(default_factory=dict)          # name -> why
    used: list = field(default_factory=list)
    message: str = ''

    @property
    def ok(self) -> bool:
        return self.status == OK


def parse_board(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6): inner corners per row and per column."""
    try:
        cols, rows = (int(v) for v in text.lower().split('x'))
    except ValueError as exc:
        raise DataError(f'board size {text!r} must look like COLSxROWS of inner corners, e.g. 9x6') from exc
    if cols < 2 or rows < 2:
        raise DataError(f'board {text!r} needs at least 2x2 inner corners')
    return cols, rows


def board_points(board: tuple[int, int], square: float) -> np.ndarray:
    """(cols*rows, 3) corner coordinates on the board plane, in the order OpenCV reports them."""
    cols, rows = board
    g = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(np.float32)
    return np.column_stack([g * float(square), np.zeros(len(g), np.float32)])


def find_corners(gray: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners (N, 1, 2) float32, or None when the whole board is not visible."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, board, flags=flags)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    return cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), criteria)


def _view_rms(obj, img_pts, rvecs, tvecs, K, D) -> np.ndarray:
    out = []
    for o, p, r, t in zip(obj, img_pts, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, D)
        out.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - p.reshape(-1, 2)) ** 2, axis=1)))))
    return np.array(out)


def calibrate(views: list[tuple[str, np.ndarray]], board: tuple[int, int], square: float = 1.0,
              min_views: int = 5, reject_factor: float = 3.0, reject_floor_px: float = 1.0) -> CalibrationResult:
    """Calibrate from (name, grayscale image) pairs.

    A view is rejected when its RMS exceeds both `reject_floor_px` and `reject_factor` times the
    median view RMS; the worst such view goes first and the fit is repeated.
    """
    if not views:
        raise DataError('no images given to calibrate: pass the chessboard photos')
    if square <= 0:
        raise DataError(f'square size {square} must be positive (any unit; it scales the board only)')
    size = None
    obj_pts, img_pts, names, rejected = [], [], [], {}
    template = board_points(board, square)
    for name, img in views:
        gray = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        hw = gray.shape[:2]
        if size is None:
            size = hw
        elif hw != size:
            rejected[name] = f'size {hw[1]}x{hw[0]} differs from the first image {size[1]}x{size[0]}'
            continue
        corners = find_corners(gray, board)
        if corners is None:
            rejected[name] = f'no complete {board[0]}x{board[1]} board found'
            continue
        obj_pts.append(template)
        img_pts.append(corners)
        names.append(name)
    res = CalibrationResult(TOO_FEW_VIEWS, rejected=rejected)
    while True:
        if len(names) < min_views:
            res.message = f'only {len(names)} usable views, need {min_views}: take more photos of the whole board'
            return res
        h, w = size
        rms, K, D, rvecs, tvecs = cv2.calibrateCamera(obj_pts, img_pts, (w, h), None, None)
        per_view = _view_rms(obj_pts, img_pts, rvecs, tvecs, K, D)
        limit = max(reject_floor_px, reject_factor * float(np.median(per_view)))
        worst = int(np.argmax(per_view))
        if per_view[worst] <= limit:
            break
        rejected[names[worst]] = f'reprojection RMS {per_view[worst]:.2f} px > {limit:.2f} px'
        del obj_pts[worst], img_pts[worst], names[worst]
    try:
        camera = PinholeCamera(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(D.ravel()[:5]))
    except CalibrationError as exc:
        res.message = f'calibration is not physical: {exc}'
        res.status = 'failed'
        return res
    return CalibrationResult(OK, camera, float(rms), dict(zip(names, per_view.tolist())), rejected, names,
                             f'{len(names)} views, RMS {rms:.3f} px')
