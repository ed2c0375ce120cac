"""A target's intersection says how well its rays fix it (core.evaluation.intersection_dop), and one fixed too weakly
is not counted as a check point (intersect_targets' `weak`): its residual would be its own intersection's noise."""

from __future__ import annotations

import numpy as np
import pytest

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.evaluation import MAX_INTERSECTION_DOP, intersect_targets, intersection_dop

CAM = PinholeCamera(1280, 960, 1000.0, 1000.0, 640.0, 480.0)


def _nadir(x_m: float, y_m: float, height_m: float) -> np.ndarray:
    """A camera looking straight down from (x, y, height), image x east, y south (camera to map)."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [x_m, y_m, height_m]
    return T


def _project(Ts, X):
    out = []
    for T in Ts:
        pc = T[:3, :3].T @ (X - T[:3, 3])
        out.append(CAM.normalized_to_pixel((pc[:2] / pc[2])[None])[0])
    return np.array(out)


@pytest.mark.parametrize('base_m', [4.0, 8.0, 20.0])
def test_the_dop_of_a_normal_stereo_pair_is_the_textbook_one(base_m):
    """Two nadir cameras H above the ground, B apart, the point below their midpoint: the normal case gives
    sigma_Z = sqrt(2) (H / B) (H / f) sigma_px, and sigma_X = sigma_Y = (H / f) sigma_px / sqrt(2), so the DOP is
    sqrt(2) H / B vertically and 1 horizontally (2D), in ground pixels H / f per pixel of detection noise."""
    H = 40.0
    Ts = np.array([_nadir(0.0, 0.0, H), _nadir(base_m, 0.0, H)])
    X = np.array([base_m / 2, 0.0, 0.0])
    dop_h, dop_v = intersection_dop(CAM, Ts, _project(Ts, X), X)
    assert dop_v == pytest.approx(np.sqrt(2) * H / base_m, rel=1e-3)
    assert dop_h == pytest.approx(1.0, rel=1e-3)


def test_a_point_on_the_baseline_of_parallel_rays_is_not_fixed():
    """Two cameras at one place: the rays coincide, the depth is not fixed at all."""
    Ts = np.array([_nadir(0.0, 0.0, 40.0), _nadir(0.0, 0.0, 40.0)])
    X = np.array([1.0, 2.0, 0.0])
    dop_h, dop_v = intersection_dop(CAM, Ts, _project(Ts, X), X)
    assert not np.isfinite(dop_v) or dop_v > 1e4


def test_a_check_point_seen_from_two_neighbouring_images_is_weak_and_one_seen_across_lines_counts():
    """Check A seen from two images 6 m apart along a line 40 m up (vertical DOP 9.4), check B from three lines:
    A is listed as weak (not in the residuals, not missing), B counts; both 5 cm off in height."""
    rng = np.random.default_rng(3)
    H = 40.0
    line = [_nadir(x, 0.0, H) for x in (-6.0, 0.0, 6.0)]
    across = [_nadir(x, y, H) for x in (-6.0, 0.0, 6.0) for y in (-15.0, 0.0, 15.0)]
    Ts = np.array(line[:2] + across)
    A, B = np.array([-3.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    obs = {'A': [(j, uv) for j, uv in enumerate(_project(Ts[:2], A) + rng.normal(0, 0.2, (2, 2)))],
           'B': [(2 + j, uv) for j, uv in enumerate(_project(Ts[2:], B) + rng.normal(0, 0.2, (9, 2)))]}
    surveyed = {'A': ('A', A + [0, 0, 0.05]), 'B': ('B', B + [0, 0, 0.05])}
    got = intersect_targets(CAM, Ts, obs, surveyed)
    print(got.names, got.residuals, got.weak)
    assert got.names == ['B'] and not got.missing
    assert [w['name'] for w in got.weak] == ['A'] and got.weak[0]['views'] == 2
    assert got.weak[0]['dop_v'] == pytest.approx(np.sqrt(2) * H / 6.0, rel=0.02)
    assert got.weak[0]['dop_v'] > MAX_INTERSECTION_DOP
    assert abs(got.residuals[0][2] + 0.05) <= 0.02
    # With the limit raised the weak one counts, and its residual is its intersection's noise.
    loose = intersect_targets(CAM, Ts, obs, surveyed, max_dop=100.0)
    assert loose.names == ['A', 'B'] and not loose.weak
