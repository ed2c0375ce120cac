"""The heights' noise about the flight's plane (core/incremental.flight_plane_sigma), which `gnss_tighten`
weights consumer geotag heights by: a level (or tilted) flight's heights give their noise; a flight that
follows relief gives its relief."""

import numpy as np
import pytest

from photogram_ros.core.incremental import IncrementalOptions, flight_plane_sigma


def _grid(n=6):
    e, nn = np.meshgrid(np.linspace(-40, 40, n), np.linspace(-40, 40, n))
    return e.ravel(), nn.ravel()


def test_plane_sigma_is_the_heights_noise_about_a_tilted_flight():
    rng = np.random.default_rng(3)
    e, n = _grid()
    h = 198.5 + 0.004 * e - 0.003 * n + rng.normal(0, 0.05, e.size)
    assert flight_plane_sigma(np.column_stack([e, n, h])) == pytest.approx(0.05, rel=0.35)


def test_plane_sigma_keeps_relief_the_flight_followed():
    e, n = _grid()
    h = 198.5 + 2.0 * np.sin(e / 15.0)   # a terrain-following flight: metres of relief, no noise
    assert flight_plane_sigma(np.column_stack([e, n, h])) > 0.5


def test_gnss_tighten_is_off_by_default():
    assert IncrementalOptions().gnss_tighten is False
    assert IncrementalOptions().gnss_tighten_floor_m == pytest.approx(0.05)
