"""EXIF GPSAltitude readings (MSL, ellipsoidal, above the take-off point) and the relative-altitude rule."""

import numpy as np
import pytest

from photogram_ros.errors import ConfigError
from photogram_ros.io.image_source import exif_altitude_to_ellipsoidal_m, exif_altitudes_look_relative

# Published EGM2008 geoid height at 0 N 0 E: 17.16 m (NGA calculator, tide-free); the oracle is
# independent of the grid interpolation the code uses.
N_0_0_M = 17.16


def test_exif_altitude_msl_and_ellipsoidal():
    assert exif_altitude_to_ellipsoidal_m(0.0, 0.0, 100.0) == pytest.approx(100.0 + N_0_0_M, abs=0.15)
    h = exif_altitude_to_ellipsoidal_m(0.0, 0.0, np.array([100.0, -5.0]), 'ellipsoidal')
    assert np.array_equal(h, [100.0, -5.0])


def test_exif_altitude_relative_to_a_takeoff_height():
    # Take-off 20 m MSL, photo 80 m above it: 100 m MSL, then through the geoid.
    h = exif_altitude_to_ellipsoidal_m(0.0, 0.0, 80.0, 'relative', 20.0)
    assert h == pytest.approx(100.0 + N_0_0_M, abs=0.15)
    # Take-off given as an ellipsoidal height: no geoid at all.
    assert exif_altitude_to_ellipsoidal_m(0.0, 0.0, 80.0, 'relative', 137.16, 'ellipsoidal') == pytest.approx(217.16)
    # Below the take-off point (a valley survey): negative relative altitudes.
    assert exif_altitude_to_ellipsoidal_m(0.0, 0.0, -30.0, 'relative', 20.0, 'ellipsoidal') == pytest.approx(-10.0)


def test_relative_exif_altitude_gives_the_msl_reading_back():
    # Photos 300 m from a take-off near Zurich (geoid ~47.7 m): a relative altitude plus the take-off
    # MSL height is the MSL altitude, and the ellipsoidal take-off route agrees to the geoid's slope.
    lat, lon = np.array([47.3977, 47.4004]), np.array([8.5456, 8.5456])
    takeoff_msl_m, alt_msl_m = 440.28, np.array([480.42, 481.10])
    from_msl = exif_altitude_to_ellipsoidal_m(lat, lon, alt_msl_m)
    from_rel = exif_altitude_to_ellipsoidal_m(lat, lon, alt_msl_m - takeoff_msl_m, 'relative', takeoff_msl_m)
    assert np.allclose(from_rel, from_msl, atol=1e-9)
    takeoff_h_m = float(exif_altitude_to_ellipsoidal_m(lat[0], lon[0], takeoff_msl_m))
    assert 440.28 + 45 < takeoff_h_m < 440.28 + 50
    from_ell = exif_altitude_to_ellipsoidal_m(lat, lon, alt_msl_m - takeoff_msl_m, 'relative', takeoff_h_m,
                                              'ellipsoidal')
    assert np.allclose(from_ell, from_msl, atol=0.02)


def test_exif_altitude_bad_options_raise_config_errors():
    with pytest.raises(ConfigError, match='take-off'):
        exif_altitude_to_ellipsoidal_m(0.0, 0.0, 40.0, 'relative')
    with pytest.raises(ConfigError, match='not a number'):
        exif_altitude_to_ellipsoidal_m(0.0, 0.0, 40.0, 'relative', float('nan'))
    with pytest.raises(ConfigError, match='baro'):
        exif_altitude_to_ellipsoidal_m(0.0, 0.0, 40.0, 'baro')
    with pytest.raises(ConfigError, match='agl'):
        exif_altitude_to_ellipsoidal_m(0.0, 0.0, 40.0, 'relative', 10.0, 'agl')


@pytest.mark.parametrize('ground_msl_m, photo_alt_m, relative', [
    (445.0, 485.0, False),   # an ordinary MSL survey, 40 m up
    (5.0, 45.0, True),       # relative: ground by the take-off point, photos 40 m above
    (-12.0, 60.0, True),     # relative, the block 12 m below the take-off point
    (-40.0, 0.0, True),      # a barometric altitude far off: ground below -30 m MSL
    (3.0, 12.0, False),      # a coast survey at 9 m above the ground: too low to call
    (445.0, 40.0, True),     # GCPs hold the ground, the photos are under it
    (-25.0, 20.0, False),    # a shore of the Caspian at -25 m, 45 m up: plausible as MSL
])
def test_exif_altitudes_look_relative_rule(ground_msl_m, photo_alt_m, relative):
    assert exif_altitudes_look_relative(ground_msl_m, photo_alt_m) is relative
