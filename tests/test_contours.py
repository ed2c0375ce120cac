"""Contour lines of the DTM (io/contours.py): at the right heights, in a GeoPackage whose tables and
geometry blobs follow OGC 12-128 (read back with sqlite3 alone), from `export --contours-m`."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest


def _cone():
    from photogram_ros.core.raster import NODATA, grid_for
    r = grid_for(500_000.0, 5_249_000.0, 500_100.0, 5_249_080.0, 0.5)
    X, Y = r.cell_centers()
    r.data = (120.0 - 0.1 * np.hypot(X - 500_050.0, Y - 5_249_040.0)).astype(np.float32)
    r.data[:20, :20] = NODATA
    return r


def test_contour_lines_lie_at_their_heights():
    from photogram_ros.core.raster import sample_bilinear
    from photogram_ros.io.contours import contour_lines
    r = _cone()
    lines = contour_lines(r, 1.0)
    levels = sorted({h for h, _ in lines})
    assert levels == [float(v) for v in range(114, 120)]     # the cone spans 113.6 to 120 m within the box
    for h, xy in lines:
        z = sample_bilinear(r, xy[:, 0], xy[:, 1])
        assert np.nanmax(np.abs(z - h)) < 0.01
        d = np.hypot(xy[:, 0] - 500_050.0, xy[:, 1] - 5_249_040.0)
        assert np.abs(d - (120.0 - h) / 0.1).max() < 0.1      # circles of radius (120 - h) / 0.1 m


def test_geopackage_tables_and_geometries(tmp_path):
    from photogram_ros.io.contours import GPKG_APPLICATION_ID, contour_lines, read_contours_gpkg, write_contours_gpkg
    lines = contour_lines(_cone(), 0.5)
    path = write_contours_gpkg(lines, tmp_path / 'c.gpkg', 'EPSG:32632')
    con = sqlite3.connect(path)
    assert con.execute('PRAGMA application_id').fetchone()[0] == GPKG_APPLICATION_ID
    assert con.execute("SELECT data_type, srs_id FROM gpkg_contents WHERE table_name = 'contours'").fetchone() == \
        ('features', 32632)
    assert con.execute("SELECT organization, organization_coordsys_id FROM gpkg_spatial_ref_sys WHERE srs_id = 32632"
                       ).fetchone() == ('EPSG', 32632)
    blob = con.execute('SELECT geom FROM contours LIMIT 1').fetchone()[0]
    assert blob[:2] == b'GP' and blob[8 + 32] == 1            # header, envelope, then little-endian WKB
    con.close()
    srs, back = read_contours_gpkg(path)
    assert srs == 32632 and len(back) == len(lines)
    assert all(h == hb and np.array_equal(xy, xyb) for (h, xy), (hb, xyb) in zip(lines, back))


def test_export_writes_contours_of_the_dtm_on_request(tmp_path):
    from helpers.clouds import fused_map, pair_cloud
    from photogram_ros.cli import main
    from photogram_ros.io.contours import read_contours_gpkg
    rng = np.random.default_rng(4)
    fused_map(tmp_path / 'map', 0.25, [pair_cloud(rng, lambda x, y: 0.1 * x, 0.0, 0.0, 20.0, 20.0, 40.0, 0.01)
                                       for _ in range(2)])
    out = tmp_path / 'out'
    assert main(['export', str(tmp_path / 'map'), '--crs', 'EPSG:32632', '--out', str(out), '--products', 'dtm',
                 '--contours-m', '1']) == 0
    srs, lines = read_contours_gpkg(out / 'contours.gpkg')
    heights = sorted({h for h, _ in lines})
    assert srs == 32632 and len(heights) >= 3 and np.allclose(np.diff(heights), 1.0)
    with pytest.raises(SystemExit):
        main(['export', str(tmp_path / 'map'), '--crs', 'EPSG:32632', '--out', str(out), '--contours-m', 'x'])
