"""detect_targets on large images (reduced search, full-resolution confirmation) against the whole-image search.

Oracle: markers painted with a known homography (area-sampled 4x4 per pixel, then lens blur and read noise),
so each marker's centre (the image of the board centre) is known exactly. The reference is the whole-image
full-resolution search that detect_targets used on every image before (`full_resolution_detection`).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import SAMPLE_BAG, shared_data
from photogram_ros.core.evaluation import TargetDetection, detect_targets

DICT_4X4_50 = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
CELLS = 6   # 4x4 bits and a one-cell black border; a one-cell white quiet zone around it


def full_resolution_detection(image: np.ndarray, dictionary: int = cv2.aruco.DICT_4X4_50) -> list[TargetDetection]:
    """The whole-image search at full resolution, as detect_targets did on every image before."""
    from photogram_ros.core.evaluation import _diagonal_intersection
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dictionary))
    prm = det.getDetectorParameters()
    prm.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det.setDetectorParameters(prm)
    corners, ids, _ = det.detectMarkers(grey)
    return [TargetDetection(int(i), _diagonal_intersection(c.reshape(4, 2).astype(float)), c.reshape(4, 2))
            for c, i in zip(corners, [] if ids is None else ids.ravel())]


def draw_marker(image: np.ndarray, marker_id: int, corners_uv: np.ndarray, rng: np.random.Generator,
                blur_px: float = 0.6, noise_dn: float = 1.5, supersample: int = 4) -> np.ndarray:
    """Paint a DICT_4X4_50 marker (off-black 25, off-white 230, one-cell white margin) in place so that its
    black square's corners (top-left, clockwise) land on `corners_uv` (pixel centres at integers).
    Returns the true centre pixel (2,): the homography's image of the board centre."""
    bits = cv2.aruco.generateImageMarker(DICT_4X4_50, marker_id, CELLS).astype(np.float64) / 255.0
    square = np.array([[0, 0], [CELLS, 0], [CELLS, CELLS], [0, CELLS]], np.float32)
    H = cv2.getPerspectiveTransform(square, np.asarray(corners_uv, np.float32)).astype(np.float64)
    Hi = np.linalg.inv(H)
    board = cv2.perspectiveTransform(np.array([[[-1, -1], [CELLS + 1, -1], [CELLS + 1, CELLS + 1],
                                                [-1, CELLS + 1]]], np.float64), H)[0]
    h, w = image.shape[:2]
    m = int(np.ceil(3 * blur_px)) + 2
    u0, v0 = max(int(np.floor(board[:, 0].min())) - m, 0), max(int(np.floor(board[:, 1].min())) - m, 0)
    u1 = min(int(np.ceil(board[:, 0].max())) + m + 1, w)
    v1 = min(int(np.ceil(board[:, 1].max())) + m + 1, h)
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    U, V = np.meshgrid((np.arange(u0, u1)[:, None] + sub).ravel(), (np.arange(v0, v1)[:, None] + sub).ravel())
    den = Hi[2, 0] * U + Hi[2, 1] * V + Hi[2, 2]
    x = (Hi[0, 0] * U + Hi[0, 1] * V + Hi[0, 2]) / den
    y = (Hi[1, 0] * U + Hi[1, 1] * V + Hi[1, 2]) / den
    on_board = (x >= -1) & (x < CELLS + 1) & (y >= -1) & (y < CELLS + 1)
    row, col = np.floor(y).astype(int), np.floor(x).astype(int)
    in_code = (row >= 0) & (row < CELLS) & (col >= 0) & (col < CELLS)
    white = np.ones_like(x)
    white[in_code] = bits[row[in_code], col[in_code]]
    shape = (v1 - v0, supersample, u1 - u0, supersample)
    cover = on_board.reshape(shape).mean(axis=(1, 3))
    paint = ((25.0 + 205.0 * white) * on_board).reshape(shape).sum(axis=(1, 3)) / np.maximum(
        on_board.reshape(shape).sum(axis=(1, 3)), 1)
    roi = image[v0:v1, u0:u1].astype(np.float64)
    if roi.ndim == 3:
        cover, paint = cover[..., None], paint[..., None]
    out = roi * (1.0 - cover) + paint * cover
    if blur_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_px)
    out += rng.normal(0.0, noise_dn, out.shape)
    image[v0:v1, u0:u1] = np.clip(np.rint(out), 0, 255).astype(np.uint8)
    return cv2.perspectiveTransform(np.array([[[CELLS / 2, CELLS / 2]]], np.float64), H)[0, 0]


def random_corners(rng: np.random.Generator, centre_uv, side_px: float, perspective: float = 0.06) -> np.ndarray:
    """A marker's 4 corners: a square of `side_px` turned at random, each corner moved by up to
    `perspective` of the side (a tilted view)."""
    th = rng.uniform(0.0, 2.0 * np.pi)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    sq = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]) + rng.uniform(-perspective, perspective,
                                                                                        (4, 2))
    return np.asarray(centre_uv, float) + side_px * sq @ R.T


def paint_markers(background: np.ndarray, sides_px, rng: np.random.Generator, per_side: int = 4,
                  spacing: float = 4.0) -> tuple[np.ndarray, dict]:
    """A copy of `background` with markers of the given sides at random places (ids 0.., apart by
    `spacing` sides); returns (image, {marker_id: true centre})."""
    img = background.copy()
    h, w = img.shape[:2]
    truth, placed = {}, []
    for side in sides_px:
        for _ in range(per_side):
            for _try in range(50):
                c = np.array([rng.uniform(side, w - side), rng.uniform(side, h - side)])
                if all(np.linalg.norm(c - p) > spacing * max(side, s) for p, s in placed):
                    break
            else:
                continue
            k = len(truth)
            if k >= 50:
                return img, truth
            truth[k] = draw_marker(img, k, random_corners(rng, c, side), rng)
            placed.append((c, side))
    return img, truth


def compare(fast: list[TargetDetection], full: list[TargetDetection]) -> float:
    """Largest centre difference between the two searches; they must find the same ids, once each."""
    assert sorted(d.marker_id for d in fast) == sorted(d.marker_id for d in full)
    by_id = {d.marker_id: d for d in full}
    assert len(by_id) == len(full)
    return max((float(np.linalg.norm(d.center_uv - by_id[d.marker_id].center_uv)) for d in fast), default=0.0)


def sample_frames() -> list[np.ndarray]:
    from photogram_ros.io.bag import BagReader, deserialize
    from photogram_ros.msgs import image_from_msg
    with BagReader(SAMPLE_BAG) as bag:
        return [image_from_msg(deserialize(m.msgtype, m.data)) for m in bag.messages(['/camera/image_raw/compressed'])]


@pytest.fixture(scope='module')
def frames() -> list[np.ndarray]:
    return sample_frames()


def test_sample_bag_frames_give_the_full_resolution_result(frames):
    n = 0
    for img in frames:
        fast, full = detect_targets(img), full_resolution_detection(img)
        assert compare(fast, full) == 0.0
        n += len(full)
    assert n >= 90   # the sample's 76 frames show its 9 targets 99 times


def test_sample_bag_frames_upscaled_to_2560_keep_every_marker(frames):
    """Markers 24-30 px in the 640x480 sample become 96-120 px at 2560x1920: searched at half size."""
    n = 0
    for img in frames[::3]:
        big = cv2.resize(img, (2560, 1920), interpolation=cv2.INTER_CUBIC)
        full = full_resolution_detection(big)
        assert compare(detect_targets(big), full) < 0.1
        n += len(full)
    assert n >= 25


@pytest.mark.parametrize('name, size, sides', [
    ('video', (1920, 1080), (18, 20, 24, 30, 40, 60, 100)),   # searched whole
    ('video', (2560, 1440), (30, 36, 44, 60, 80, 130)),
    ('photo', (4000, 2250), (34, 40, 50, 64, 90, 130, 180)),
    ('photo', (4000, 3000), (36, 44, 60, 80, 120, 200)),
])
def test_large_frames_find_what_the_full_search_finds_as_accurately(name, size, sides):
    if name == 'video':
        bg = cv2.imread(str(shared_data('video', 'phantom3_village', 'rgb', '1455008966.000000.jpg')))
    else:
        bg = cv2.imread(str(shared_data('photos', 'brighton_beach', 'images', 'DJI_0020.JPG')))
    bg = cv2.resize(bg, size, interpolation=cv2.INTER_AREA) if bg.shape[1::-1] != size else bg
    rng = np.random.default_rng(sum(size))
    err_fast, err_full = [], []
    for _ in range(2):
        img, truth = paint_markers(bg, sides, rng)
        fast, full = detect_targets(img), full_resolution_detection(img)
        assert compare(fast, full) < 0.1
        for d in fast:
            assert d.marker_id in truth   # no marker that was not painted
            err_fast.append(np.linalg.norm(d.center_uv - truth[d.marker_id]))
        err_full += [np.linalg.norm(d.center_uv - truth[d.marker_id]) for d in full]
        # every painted marker of the larger half of the sizes is found
        big = [k for k in truth if k >= len(truth) // 2]
        assert set(big) <= {d.marker_id for d in fast}
    assert len(err_fast) >= 20
    assert np.max(err_fast) <= np.max(err_full) + 0.01   # the same corners, to float rounding
    assert np.median(err_fast) < 0.1


def test_markers_covering_most_of_a_large_frame_are_all_found():
    """Candidate regions over half the image: the whole image is searched (same result)."""
    rng = np.random.default_rng(5)
    bg = np.full((1440, 2560, 3), 128, np.uint8)
    bg += rng.integers(0, 40, bg.shape, dtype=np.uint8)
    img, truth = paint_markers(bg, [120], rng, per_side=40, spacing=1.6)
    assert len(truth) >= 25
    fast = detect_targets(img)
    assert compare(fast, full_resolution_detection(img)) == 0.0
    assert {d.marker_id for d in fast} == set(truth)


def test_real_photo_without_markers_gives_none():
    img = cv2.imread(str(shared_data('photos', 'brighton_beach', 'images', 'DJI_0018.JPG')))
    assert img.shape[:2] == (2250, 4000)
    assert detect_targets(img) == [] == full_resolution_detection(img)
