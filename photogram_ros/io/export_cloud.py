"""The fused map as a point cloud in an output CRS, and its LAS 1.4 / LAZ and PLY files (io/export.py writes them).

Map ENU coordinates go to WGS84 through the map's LocalFrame, then to the requested CRS with pyproj
(easting, northing). Heights are WGS84 ellipsoidal by default; `heights='orthometric'` gives
heights above the EGM2008 geoid instead. Only the horizontal part of the CRS is taken from PROJ,
so a datum shift between WGS84 and e.g. CH1903+ never changes the height reference silently. The LAS
WKT is the projected CRS, compound with EGM2008 height (e.g. EPSG:32632+3855) for orthometric heights
(io/crs_tags.py). LAS/LAZ points are classified (core.ground: 2 ground, 6 building, 1 the rest) with
return 1 of 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from photogram_ros.core import geoid
from photogram_ros.core.fusion import Fusion, FusionConfig
from photogram_ros.core.geodesy import LocalFrame, crs_to_geodetic, geodetic_to_crs
from photogram_ros.core.ground import GroundParams, classify_points
from photogram_ros.errors import DataError, GeodesyError
from photogram_ros.io.crs_tags import describe_las
from photogram_ros.io.map_store import MapStore, as_map_store

HEIGHTS = ('ellipsoidal', 'orthometric')


@dataclass
class GeoCloud:
    """Fused map cells in an output CRS."""
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    rgb: np.ndarray           # (N, 3) uint8 R, G, B
    count: np.ndarray         # points fused per cell
    confidence: np.ndarray
    crs: str
    heights: str
    sigma_z: np.ndarray | None = None   # height spread of the points fused in each cell, m
    pairs: np.ndarray | None = None     # stereo pairs that measured each cell
    classes: np.ndarray | None = None   # ASPRS class per point (core.ground); None: not classified (1)

    def subset(self, keep: np.ndarray) -> 'GeoCloud':
        """The cells where `keep` (a boolean mask over the cells) holds."""
        def cut(a):
            return None if a is None else a[keep]
        return GeoCloud(self.x[keep], self.y[keep], self.z[keep], self.rgb[keep], self.count[keep],
                        self.confidence[keep], self.crs, self.heights, cut(self.sigma_z), cut(self.pairs),
                        cut(self.classes))


# --- coordinates -----------------------------------------------------------------------------------


def enu_to_crs(origin: LocalFrame, enu: np.ndarray, crs: str, heights: str = 'ellipsoidal'):
    """(N, 3) map ENU -> easting, northing, height in `crs` (heights per `heights`)."""
    if heights not in HEIGHTS:
        raise GeodesyError(f'heights must be one of {HEIGHTS}, not {heights!r}')
    lat, lon, h = origin.enu_to_geodetic(np.asarray(enu, float))
    e, n, _ = geodetic_to_crs(lat, lon, h, crs)
    if heights == 'orthometric':
        h = geoid.ellipsoid_to_msl_m(lat, lon, h)
    return np.asarray(e, float), np.asarray(n, float), np.asarray(h, float)


def crs_to_enu(origin: LocalFrame, e, n, h_ellipsoidal, crs: str) -> np.ndarray:
    """Easting, northing in `crs` with WGS84 ellipsoidal heights -> (N, 3) map ENU."""
    lat, lon, _ = crs_to_geodetic(e, n, np.zeros_like(np.asarray(e, float)), crs)
    return origin.geodetic_to_enu(lat, lon, np.asarray(h_ellipsoidal, float))


EGM2008_HEIGHT = 'EPSG:3855'


def product_crs(crs: str, heights: str):
    """(pyproj CRS with the products' vertical reference, note or '') for a projected `crs`.

    orthometric: compound with EGM2008 height; ellipsoidal: the CRS promoted to 3D (ellipsoidal
    height axis) when its datum is WGS84, else the 2D CRS and a note saying why.
    """
    from pyproj import CRS
    from pyproj.crs import CompoundCRS
    if heights not in HEIGHTS:
        raise GeodesyError(f'heights must be one of {HEIGHTS}, not {heights!r}')
    c = CRS.from_user_input(crs)
    horizontal = c.sub_crs_list[0] if c.is_compound else c.to_2d()
    if heights == 'orthometric':
        vertical = CRS.from_user_input(EGM2008_HEIGHT)
        return CompoundCRS(f'{horizontal.name} + {vertical.name}', [horizontal, vertical]), ''
    if 'World Geodetic System 1984' in (horizontal.datum.name if horizontal.datum else ''):
        return horizontal.to_3d(), ''
    return horizontal, (f'heights are WGS84 ellipsoidal, which a CRS on the {horizontal.datum.name} datum cannot '
                        'state: the products\' CRS is 2D (--heights orthometric gives a compound CRS with EGM2008)')


def check_projected(crs: str) -> None:
    from pyproj import CRS
    c = CRS.from_user_input(crs)
    if not c.is_projected:
        raise GeodesyError(f'{crs} is not a projected CRS: rasters and clouds need metric easting/northing '
                           '(e.g. the UTM zone EPSG:326xx, or a national grid such as EPSG:2056)')

# --- reading a map folder --------------------------------------------------------------------------


def open_map(map_dir: str | Path | MapStore) -> tuple[MapStore, Fusion]:
    """The map folder (or the open MapStore) and a fusion over all its tiles, for reading."""
    store = as_map_store(map_dir)
    return store, Fusion(FusionConfig(store.cell_m, store.tile_cells, max_tiles_in_memory=10**6), store)


def too_few_pairs(min_pairs: int) -> DataError:
    return DataError('the map holds no fused points yet' if min_pairs <= 1 else
                     f'no cell of the map was measured by {min_pairs} stereo pairs that agree (too little overlap '
                     f'for a second pair), nor by one pair inside the cameras\' footprint in agreement with its '
                     f'neighbours; `export MAP --min-pairs 1` writes every cell one pair measured, unchecked')


def map_cloud(fusion: Fusion, origin: LocalFrame, crs: str, heights: str = 'ellipsoidal',
              min_pairs: int = 1) -> GeoCloud:
    """Fused cells in `crs`; `min_pairs` keeps only cells that that many stereo pairs agreed on."""
    p = fusion.points()
    if min_pairs > 1:
        keep = p['n_pairs'] >= min_pairs
        p = {k: v[keep] for k, v in p.items()}
    if p['x'].size == 0:
        raise too_few_pairs(min_pairs)
    return _geo_cloud(p, origin, crs, heights)


def map_clouds(fusion: Fusion, origin: LocalFrame, crs: str, heights: str = 'ellipsoidal',
               min_pairs: int = 1) -> tuple[GeoCloud, GeoCloud | None]:
    """The cells `min_pairs` stereo pairs agreed on (maybe none), and the cells fewer pairs measured (None with
    min_pairs 1), both in `crs`, from one read of the map's tiles (io/export_raster.covering_clouds takes the
    products' cells from both). DataError when the map holds no fused cell."""
    p = fusion.points()
    if p['x'].size == 0:
        raise too_few_pairs(1)
    everything = _geo_cloud(p, origin, crs, heights)
    del p
    if min_pairs <= 1:
        return everything, None
    keep = everything.pairs >= min_pairs
    return everything.subset(keep), everything.subset(~keep)


def _geo_cloud(p: dict, origin: LocalFrame, crs: str, heights: str) -> GeoCloud:
    e, n, h = enu_to_crs(origin, np.column_stack([p['x'], p['y'], p['z']]), crs, heights)
    rgb = np.column_stack([p['r'], p['g'], p['b']])
    return GeoCloud(e, n, h, np.clip(np.rint(rgb), 0, 255).astype(np.uint8), p['n'].astype(np.uint32),
                    p['confidence'].astype(np.float32), crs, heights, p['sigma_z'].astype(np.float32),
                    p['n_pairs'].astype(np.uint32))


def classify_cloud(cloud: GeoCloud, p: GroundParams | None = None) -> dict:
    """Set cloud.classes (ground / building / unclassified, core.ground) and return the class counts."""
    c = classify_points(cloud.x, cloud.y, cloud.z, p)
    cloud.classes = c.classes
    return {'counts': c.counts(), 'buildings': c.buildings, 'notes': c.notes}


# --- point clouds ----------------------------------------------------------------------------------


def write_las(cloud: GeoCloud, path: str | Path) -> Path:
    """LAS 1.4 point format 7 (RGB), CRS as an OGC WKT1 VLR with EPSG ids (io/crs_tags.py); .laz compresses (lazrs).

    Every point is return 1 of 1 (a photogrammetric point is the only return of its ray; 0 is invalid
    in LAS 1.4) with its class from cloud.classes (1, unclassified, when not classified).
    """
    import laspy
    path = Path(path)
    header = laspy.LasHeader(point_format=7, version='1.4')
    xyz = (cloud.x, cloud.y, cloud.z)
    if not all(np.all(np.isfinite(v)) for v in xyz):
        raise DataError(f'{path.name}: the cloud holds non-finite coordinates; nothing written')
    header.offsets = [np.floor(v.min()) if v.size else 0.0 for v in xyz]
    # Millimetres, or the finest power of ten whose 32-bit integers span the cloud's extent.
    header.scales = [_las_scale(float(np.ptp(v)) if v.size else 0.0) for v in xyz]
    describe_las(header, cloud.crs, cloud.heights)     # WKT1 with EPSG ids, System Identifier (io/crs_tags.py)
    header.add_extra_dims([laspy.ExtraBytesParams('observations', np.uint32, 'points fused in the cell'),
                           laspy.ExtraBytesParams('confidence', np.float32, 'mean stereo confidence')])
    header.generating_software = 'photogram_ros'
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud.x, cloud.y, cloud.z
    las.return_number = np.ones(cloud.x.size, np.uint8)
    las.number_of_returns = np.ones(cloud.x.size, np.uint8)
    las.classification = cloud.classes if cloud.classes is not None else np.ones(cloud.x.size, np.uint8)
    # LAS colour is 16-bit: scale 0..255 to 0..65535 as GIS tools expect.
    las.red = cloud.rgb[:, 0].astype(np.uint16) * 257
    las.green = cloud.rgb[:, 1].astype(np.uint16) * 257
    las.blue = cloud.rgb[:, 2].astype(np.uint16) * 257
    las.observations = cloud.count
    las.confidence = cloud.confidence
    las.write(str(path))
    return path


def _las_scale(extent_m: float) -> float:
    scale = 0.001
    while extent_m / scale > 2_000_000_000:
        scale *= 10.0
    return scale


_PLY_FIELDS = [('x', '<f8', 'double'), ('y', '<f8', 'double'), ('z', '<f8', 'double'),
               ('red', 'u1', 'uchar'), ('green', 'u1', 'uchar'), ('blue', 'u1', 'uchar'),
               ('confidence', '<f4', 'float'), ('observations', '<u4', 'uint'), ('classification', 'u1', 'uchar')]
_PLY_TYPES = {'char': 'i1', 'uchar': 'u1', 'short': '<i2', 'ushort': '<u2', 'int': '<i4', 'uint': '<u4',
              'float': '<f4', 'double': '<f8', 'int8': 'i1', 'uint8': 'u1', 'int16': '<i2', 'uint16': '<u2',
              'int32': '<i4', 'uint32': '<u4', 'float32': '<f4', 'float64': '<f8'}


def write_ply(cloud: GeoCloud, path: str | Path) -> Path:
    """Binary little-endian PLY; coordinates in double so projected eastings keep millimetres."""
    path = Path(path)
    arr = np.empty(cloud.x.size, dtype=[(n, t) for n, t, _ in _PLY_FIELDS])
    arr['x'], arr['y'], arr['z'] = cloud.x, cloud.y, cloud.z
    arr['red'], arr['green'], arr['blue'] = cloud.rgb[:, 0], cloud.rgb[:, 1], cloud.rgb[:, 2]
    arr['confidence'], arr['observations'] = cloud.confidence, cloud.count
    arr['classification'] = cloud.classes if cloud.classes is not None else 1
    lines = ['ply', 'format binary_little_endian 1.0', 'comment generated by photogram_ros',
             f'comment crs {cloud.crs}', f'comment heights {cloud.heights}', f'element vertex {arr.size}']
    lines += [f'property {ply} {n}' for n, _, ply in _PLY_FIELDS] + ['end_header']
    with open(path, 'wb') as f:
        f.write(('\n'.join(lines) + '\n').encode('ascii'))
        f.write(arr.tobytes())
    return path


def read_ply(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """Vertices of a binary little-endian PLY (scalar properties) and its comments."""
    data = Path(path).read_bytes()
    end = data.find(b'end_header\n')
    if not data.startswith(b'ply\n') or end < 0:
        raise DataError(f'{path} is not a PLY file')
    header = data[:end].decode('ascii').splitlines()
    if 'format binary_little_endian 1.0' not in header:
        raise DataError(f'{path}: only binary little-endian PLY is read here')
    fields, comments, n, in_vertex = [], [], 0, False
    for line in header:
        parts = line.split()
        if parts[:1] == ['comment']:
            comments.append(line[8:])
        elif parts[:1] == ['element']:
            in_vertex = parts[1] == 'vertex'
            if in_vertex:
                n = int(parts[2])
            elif fields:
                break
        elif parts[:1] == ['property'] and in_vertex:
            if parts[1] == 'list':
                raise DataError(f'{path}: list properties in vertices are not supported')
            fields.append((parts[2], _PLY_TYPES[parts[1]]))
    return np.frombuffer(data, dtype=np.dtype(fields), count=n, offset=end + len('end_header\n')).copy(), comments
