import numpy as np
import pytest
from pyproj import Transformer

from photogram_ros.core import geoid
from photogram_ros.core.geodesy import (LocalFrame, crs_to_geodetic, ecef_to_geodetic, geodetic_to_crs,
                                        geodetic_to_ecef, utm_epsg)
from photogram_ros.errors import GeodesyError

RNG = np.random.default_rng(0)
LAT = RNG.uniform(-89.9, 89.9, 500)
LON = RNG.uniform(-180, 180, 500)
H = RNG.uniform(-500, 9000, 500)


def test_geodetic_to_ecef_matches_pyproj():
    t = Transformer.from_crs('EPSG:4979', 'EPSG:4978', always_xy=True)
    x0, y0, z0 = t.transform(LON, LAT, H)
    x, y, z = geodetic_to_ecef(LAT, LON, H)
    assert np.max(np.abs(np.array([x - x0, y - y0, z - z0]))) < 1e-6


def test_ecef_round_trip_sub_millimetre():
    lat, lon, h = ecef_to_geodetic(*geodetic_to_ecef(LAT, LON, H))
    assert np.max(np.abs(lat - LAT)) * 111e3 < 1e-4
    assert np.max(np.abs((lon - LON + 180) % 360 - 180) * 111e3 * np.cos(np.radians(LAT))) < 1e-4
    assert np.max(np.abs(h - H)) < 1e-4


def test_enu_frame_round_trip_and_axes():
    f = LocalFrame(47.3977, 8.5456, 488.0)
    # 100 m north is +y, 100 m up is +z.
    lat, lon, h = f.enu_to_geodetic(np.array([0.0, 100.0, 0.0]))
    assert lat > f.lat_deg and abs(lon - f.lon_deg) < 1e-9
    enu = RNG.uniform(-2000, 2000, (200, 3))
    back = f.geodetic_to_enu(*f.enu_to_geodetic(enu))
    assert np.max(np.abs(back - enu)) < 1e-6
    # Against pyproj's topocentric conversion as an independent oracle.
    t = Transformer.from_pipeline(
        f'+proj=pipeline +step +proj=cart +ellps=WGS84 +step +proj=topocentric +ellps=WGS84 '
        f'+lat_0={f.lat_deg} +lon_0={f.lon_deg} +h_0={f.h_m}')
    lat, lon, h = f.enu_to_geodetic(enu)
    e, n, u = t.transform(lon, lat, h)
    assert np.max(np.abs(np.stack([e, n, u], -1) - enu)) < 1e-5


def test_utm_and_crs_transforms():
    assert utm_epsg(47.4, 8.5) == 32632
    assert utm_epsg(-33.9, 151.2) == 32756
    x, y, z = geodetic_to_crs(47.4, 8.5, 500.0, 'EPSG:32632')
    lat, lon, h = crs_to_geodetic(x, y, z, 'EPSG:32632')
    assert abs(lat - 47.4) < 1e-9 and abs(lon - 8.5) < 1e-9 and abs(h - 500.0) < 1e-6
    with pytest.raises(GeodesyError):
        geodetic_to_crs(47.4, 8.5, 0.0, 'EPSG:999999')
    with pytest.raises(GeodesyError):
        LocalFrame(95.0, 0.0, 0.0)


def test_geoid_egm2008_known_values():
    # EGM2008 geoid heights (tide-free), published values rounded to decimetres.
    assert geoid.undulation_m(0.0, 0.0) == pytest.approx(17.2, abs=0.15)
    assert geoid.undulation_m(49.2, -123.1) == pytest.approx(-19.6, abs=0.3)
    n = geoid.undulation_m(np.array([47.39, 47.40]), np.array([8.54, 8.55]))
    assert n.shape == (2,) and np.all((n > 45) & (n < 50))
    assert geoid.msl_to_ellipsoid_m(47.4, 8.5, 400.0) == pytest.approx(400.0 + geoid.undulation_m(47.4, 8.5))
    with pytest.raises(GeodesyError):
        geoid.undulation_m(np.nan, 0.0)
