"""Products GIS tools name: rasterio's `to_epsg()` gives the UTM code of the ortho, DSM and DTM, the DSM's and
DTM's metadata state their vertical datum and the unit "metre", laspy's parsed CRS of cloud.las has an EPSG
id (WKT1 with authorities, a compound with EGM2008 height for orthometric heights) and the System Identifier
is the specification's "OTHER" (io/crs_tags.py, used by io/export.py's writers)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

import test_export

map_dir = test_export.map_dir      # the fused map of tests/test_export.py (near Zurich: UTM 32N), a fixture

UTM = 32632


def _export_wired() -> bool:
    import inspect

    from photogram_ros.io import export
    return all(call in Path(inspect.getsourcefile(f)).read_text()
               for call, f in (('geotiff_georef(', export.write_geotiff), ('describe_las(', export.write_las)))


wired = pytest.mark.skipif(not _export_wired(), reason='io/export.py does not call io/crs_tags yet '
                           '(write_geotiff: geotiff_georef, write_las: describe_las)')


def _alone(path: Path, tmp: Path) -> Path:
    """The file copied alone into a folder of its own: what a user who uploads it has (no sidecar)."""
    folder = tmp / f'alone_{path.stem}'
    folder.mkdir(exist_ok=True)
    return Path(shutil.copy(path, folder))


@wired
@pytest.mark.parametrize('heights', ['ellipsoidal', 'orthometric'])
def test_exported_rasters_have_the_utm_epsg_code_and_state_their_vertical_datum(map_dir, tmp_path, heights):
    import laspy
    import rasterio
    from photogram_ros.io.crs_tags import read_vertical
    from photogram_ros.io.export import export_map
    res = export_map(map_dir, tmp_path / heights, f'EPSG:{UTM}', heights=heights, products=('las', 'dsm', 'dtm'))
    for kind in ('dsm', 'dtm'):
        copy = _alone(Path(res.files[kind]), tmp_path)
        with rasterio.Env(GDAL_PAM_ENABLED='NO'):
            with rasterio.open(copy) as ds:
                assert ds.crs.to_epsg() == UTM, kind
                assert ds.units[0] == 'metre', kind
        v = read_vertical(copy)
        assert v['HEIGHTS'] == heights and v['unit'] == 'metre', kind
        if heights == 'orthometric':
            assert v['VERTICAL_CRS'] == 'EPSG:3855' and v['VERTICAL_DATUM'] == 'EGM2008 geoid'
            assert v['COMPOUND_CRS'] == f'EPSG:{UTM}+3855'
        else:
            assert v['VERTICAL_CRS'] == 'EPSG:4979' and v['VERTICAL_DATUM'] == 'WGS 84 ellipsoid'
            assert 'COMPOUND_CRS' not in v
    with rasterio.open(res.files['dsm']) as ds:
        assert ds.units[1] in ('', None)     # band 2 counts stereo pairs: no unit
    las = laspy.read(res.files['las'])
    assert las.header.system_identifier == 'OTHER'
    assert las.header.global_encoding.wkt
    c = las.header.parse_crs()
    if heights == 'ellipsoidal':
        assert c.to_epsg() == UTM
    else:
        assert c.is_compound and [s.to_epsg() for s in c.sub_crs_list] == [UTM, 3855]
    wkt = las.header.vlrs.get('WktCoordinateSystemVlr')[0].string
    assert f'AUTHORITY["EPSG","{UTM}"]' in wkt      # WKT1, as the LAS 1.4 specification names it


@wired
def test_the_sample_flight_like_ortho_is_2d_with_its_epsg_code(tmp_path):
    """The orthomosaic (RGBA, no heights) carries the 2D CRS whatever the products' heights."""
    import rasterio
    from photogram_ros.core.raster import Raster
    from photogram_ros.io.crs_tags import read_vertical
    from photogram_ros.io.export import write_geotiff
    rgba = Raster(np.full((300, 300, 4), 200, np.uint8), 465000.0, 5249000.0, 0.1, None)
    path = write_geotiff(rgba, tmp_path / 'ortho.tif', f'EPSG:{UTM}', 'orthomosaic RGBA', rgba=True,
                         heights='orthometric')
    with rasterio.Env(GDAL_PAM_ENABLED='NO'):
        with rasterio.open(path) as ds:
            assert ds.crs.to_epsg() == UTM and len(ds.crs.to_dict()) > 0
    assert read_vertical(path) == {}


def test_geotiff_georef_by_code_and_for_a_crs_without_one():
    from photogram_ros.errors import GeodesyError
    from photogram_ros.io.crs_tags import geotiff_georef
    g = geotiff_georef(f'EPSG:{UTM}+3855', 'orthometric')
    assert g.crs.to_epsg() == UTM and g.tags['COMPOUND_CRS'] == f'EPSG:{UTM}+3855' and g.height_unit == 'metre'
    # A PROJ string of UTM 32N on WGS84 is named by its EPSG code.
    assert geotiff_georef('+proj=utm +zone=32 +datum=WGS84 +units=m +no_defs', None).crs.to_epsg() == UTM
    # A CRS without an EPSG code keeps its WKT; no compound code to give.
    g = geotiff_georef('+proj=tmerc +lat_0=47 +lon_0=8.5 +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m', 'orthometric')
    assert g.crs.to_epsg() is None and 'COMPOUND_CRS' not in g.tags and g.tags['VERTICAL_CRS'] == 'EPSG:3855'
    with pytest.raises(GeodesyError, match='heights'):
        geotiff_georef(f'EPSG:{UTM}', 'geoid')
    with pytest.raises(GeodesyError, match='unknown coordinate reference system'):
        geotiff_georef('EPSG:99999999', None)


@pytest.mark.parametrize('crs, heights, horizontal, vertical', [
    (f'EPSG:{UTM}', 'ellipsoidal', UTM, None), (f'EPSG:{UTM}', 'orthometric', UTM, 3855),
    ('EPSG:2056', 'ellipsoidal', 2056, None), ('EPSG:2056+3855', 'orthometric', 2056, 3855)])
def test_las_header_wkt1_with_epsg_ids_reads_back_through_laspy(tmp_path, crs, heights, horizontal, vertical):
    import laspy
    from photogram_ros.io.crs_tags import describe_las
    header = laspy.LasHeader(point_format=7, version='1.4')
    header.add_crs(__import__('pyproj').CRS.from_user_input('EPSG:4326'))   # a CRS VLR to be replaced
    describe_las(header, crs, heights)
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.array([1.0, 2.0]), np.array([3.0, 4.0]), np.array([5.0, 6.0])
    las.write(str(tmp_path / 'c.las'))
    back = laspy.read(str(tmp_path / 'c.las')).header
    assert len(back.vlrs.get('WktCoordinateSystemVlr')) == 1 and back.system_identifier == 'OTHER'
    c = back.parse_crs()
    if vertical is None:
        assert c.to_epsg() == horizontal
    else:
        assert [s.to_epsg() for s in c.sub_crs_list] == [horizontal, vertical]
