"""How the products name their coordinate reference system, so that GIS tools (QGIS, GDAL, PDAL) show an EPSG code.

GeoTIFFs (ortho, DSM, DTM): the GeoKeys hold the 2D horizontal CRS by its EPSG code (rasterio's
`to_epsg()` gives e.g. 32632). GDAL reads any vertical GeoKey as a compound or 3D CRS, which has no EPSG
code of its own (QGIS then shows a custom CRS), so the rasters state their vertical reference in their
metadata items instead (`geotiff_georef().tags`, read back by `read_vertical`):

    HEIGHTS          ellipsoidal | orthometric
    VERTICAL_DATUM   WGS 84 ellipsoid | EGM2008 geoid
    VERTICAL_CRS     EPSG:4979 (WGS 84 3D: ellipsoidal heights, as GeoTIFF 1.1's VerticalGeoKey states them)
                     | EPSG:3855 (EGM2008 height)
    COMPOUND_CRS     EPSG:<horizontal>+3855 (orthometric heights only: what `gdalwarp -s_srs` takes)
    VERTICAL_UNIT    metre

and the height band's unit "metre" (GDAL's unit type). The orthomosaic has no heights: 2D CRS, no tags.

LAS 1.4: the CRS as OGC WKT1 (the WKT of the LAS 1.4 specification, OGC 01-009) with its EPSG
authorities: the 2D projected CRS for ellipsoidal heights (the heights of a CRS without a vertical
part are above its ellipsoid), a COMPD_CS of the projected CRS and EGM2008 height (EPSG:3855) for
orthometric ones; a CRS without a WKT1 form is written as WKT2. The System Identifier is "OTHER"
(the specification's value for data no listed hardware system made).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from photogram_ros.errors import GeodesyError

HEIGHTS = ('ellipsoidal', 'orthometric')
EGM2008_HEIGHT_EPSG = 3855
WGS84_3D_EPSG = 4979
LAS_SYSTEM_IDENTIFIER = 'OTHER'
HEIGHT_UNIT = 'metre'

VERTICAL = {
    'ellipsoidal': {'VERTICAL_DATUM': 'WGS 84 ellipsoid', 'VERTICAL_CRS': f'EPSG:{WGS84_3D_EPSG}'},
    'orthometric': {'VERTICAL_DATUM': 'EGM2008 geoid', 'VERTICAL_CRS': f'EPSG:{EGM2008_HEIGHT_EPSG}'},
}


def horizontal_crs(crs: str):
    """The 2D horizontal part of `crs` (a compound's first part) as a pyproj CRS, by its EPSG code when it has one."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError
    try:
        c = CRS.from_user_input(crs)
    except CRSError as exc:
        raise GeodesyError(f'unknown coordinate reference system {crs!r}: {exc}') from exc
    h = c.sub_crs_list[0] if c.is_compound else c.to_2d()
    code = h.to_epsg()
    return CRS.from_epsg(code) if code else h


def crs_with_heights(crs: str, heights: str) -> str:
    """The CRS that states `crs`'s positions with `heights`: `crs` itself for ellipsoidal heights, EPSG:<code>+3855
    (EGM2008 height) for orthometric ones (`crs` itself when its horizontal part has no EPSG code)."""
    _check_heights(heights)
    if heights != 'orthometric':
        return crs
    code = horizontal_crs(crs).to_epsg()
    return f'EPSG:{code}+{EGM2008_HEIGHT_EPSG}' if code else crs


def _check_heights(heights: str) -> None:
    if heights not in HEIGHTS:
        raise GeodesyError(f'heights must be one of {HEIGHTS}, not {heights!r}')


@dataclass(frozen=True)
class GeoTiffGeoref:
    """What a GeoTIFF writer gives GDAL: `crs` (a rasterio CRS, 2D, by EPSG code where it has one), the
    dataset metadata items `tags` (the vertical reference; empty without heights) and `height_unit`
    for band 1 ('' without heights)."""
    crs: object
    tags: dict = field(default_factory=dict)
    height_unit: str = ''


def geotiff_georef(crs: str, heights: str | None) -> GeoTiffGeoref:
    """The georeference of a GeoTIFF in `crs`; `heights` None for a raster without heights (the orthomosaic)."""
    from rasterio.crs import CRS as RioCRS
    h = horizontal_crs(crs)
    code = h.to_epsg()
    rio = RioCRS.from_epsg(code) if code else RioCRS.from_wkt(h.to_wkt())
    if heights is None:
        return GeoTiffGeoref(rio)
    _check_heights(heights)
    tags = {'HEIGHTS': heights, **VERTICAL[heights], 'VERTICAL_UNIT': HEIGHT_UNIT}
    if heights == 'orthometric' and code:
        tags['COMPOUND_CRS'] = f'EPSG:{code}+{EGM2008_HEIGHT_EPSG}'
    return GeoTiffGeoref(rio, tags, HEIGHT_UNIT)


def read_vertical(path: str | Path) -> dict:
    """The vertical reference a GeoTIFF written with `geotiff_georef` states: its metadata items named in
    VERTICAL plus HEIGHTS, and band 1's unit ('unit'); {} when it states none."""
    import rasterio
    keys = ('HEIGHTS', 'VERTICAL_DATUM', 'VERTICAL_CRS', 'COMPOUND_CRS', 'VERTICAL_UNIT')
    with rasterio.Env(GDAL_PAM_ENABLED='NO'):
        with rasterio.open(path) as ds:
            tags = ds.tags()
            out = {k: tags[k] for k in keys if k in tags}
            if out and ds.units and ds.units[0]:
                out['unit'] = ds.units[0]
    return out


def las_crs_wkt(crs: str, heights: str) -> str:
    """OGC WKT1 (with EPSG authorities) of the CRS of a LAS cloud in `crs` with `heights`."""
    from pyproj import CRS
    from pyproj.crs import CompoundCRS
    _check_heights(heights)
    h = horizontal_crs(crs)
    c = h
    if heights == 'orthometric':
        code = h.to_epsg()
        c = (CRS.from_user_input(f'EPSG:{code}+{EGM2008_HEIGHT_EPSG}') if code else
             CompoundCRS(f'{h.name} + EGM2008 height', [h, CRS.from_epsg(EGM2008_HEIGHT_EPSG)]))
    try:
        return c.to_wkt('WKT1_GDAL')
    except Exception:      # pyproj raises CRSError: a CRS that WKT1 cannot express (e.g. a dynamic datum's epoch)
        return c.to_wkt()


def describe_las(header, crs: str, heights: str) -> None:
    """Set a laspy LAS 1.4 header's CRS (one OGC WKT VLR, the WKT bit of the global encoding) and its
    System Identifier; any CRS VLR it held is replaced."""
    from laspy.vlrs.known import WktCoordinateSystemVlr
    wkt = las_crs_wkt(crs, heights)
    for name in ('WktCoordinateSystemVlr', 'GeoKeyDirectoryVlr', 'GeoAsciiParamsVlr', 'GeoDoubleParamsVlr'):
        while header.vlrs.get(name):
            header.vlrs.extract(name)
    header.vlrs.append(WktCoordinateSystemVlr(wkt))
    header.global_encoding.wkt = True
    header.system_identifier = LAS_SYSTEM_IDENTIFIER
