"""Dense-cloud completeness counts measured cells only, over the flown area."""

from types import SimpleNamespace

import numpy as np

from photogram_ros.io.flight_report import _cloud_completeness


def _truth_over(lo, hi):
    frames = []
    for x, y in ((lo, lo), (hi, hi)):
        T = np.eye(4)
        T[:3, 3] = (x, y, 40.0)
        frames.append(SimpleNamespace(map_T_cam=T))
    return SimpleNamespace(frames=frames)


def test_half_covered_area_is_half_complete():
    truth = _truth_over(0.0, 10.0)
    xs, ys = np.meshgrid(np.arange(0.05, 5.0, 0.1), np.arange(0.05, 10.0, 0.1))  # left half, every 0.1 m
    enu = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    assert abs(_cloud_completeness(enu, truth, 0.5) - 0.5) < 1e-9


def test_points_outside_the_flown_area_do_not_count():
    truth = _truth_over(0.0, 10.0)
    enu = np.array([[-3.0, 5.0, 0.0], [12.0, 5.0, 0.0], [5.0, 5.0, 0.0]])
    assert abs(_cloud_completeness(enu, truth, 1.0) - 1 / 100) < 1e-9
