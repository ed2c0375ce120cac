"""Exports open in laspy/rasterio with the right CRS (and its vertical datum) and bounds, the rasters as
Cloud-Optimized GeoTIFFs with overviews, LAS points as valid single returns with classes; the
orthomosaic puts targets where they are."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from helpers.clouds import fused_map, pair_cloud

LAT, LON, H = 47.3977, 8.5456, 488.0
CRSES = ['EPSG:32632', 'EPSG:2056']


def surface(x, y):
    return 2.0 + 0.04 * x + 0.5 * np.sin(0.2 * y)


def oracle_crs(enu: np.ndarray, crs: str):
    """ENU -> crs through PROJ's own topocentric conversion (independent of core.geodesy)."""
    from pyproj import Transformer
    to_geo = Transformer.from_pipeline(f'+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 +lat_0={LAT} '
                                       f'+lon_0={LON} +h_0={H} +step +inv +proj=cart +ellps=WGS84')
    lon, lat, h = to_geo.transform(enu[:, 0], enu[:, 1], enu[:, 2])
    e, n, _ = Transformer.from_crs('EPSG:4979', crs, always_xy=True).transform(lon, lat, h)
    return np.asarray(e), np.asarray(n), np.asarray(h)


@pytest.fixture(scope='module')
def map_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp('exp') / 'map'
    rng = np.random.default_rng(5)
    fused_map(d, 0.08, (pair_cloud(rng, surface, -10.0 + 8 * k, 5.0, 10.0, 8.0, 60.0, 0.01, rgb=0x20A040)
                        for k in range(4)), (LAT, LON, H))
    return d


@pytest.mark.parametrize('crs', CRSES)
def test_las_laz_ply_carry_crs_and_bounds(map_dir, tmp_path, crs):
    import laspy
    from pyproj import CRS
    from photogram_ros.io.export import export_map, open_map, read_ply
    res = export_map(map_dir, tmp_path, crs, products=('las', 'laz', 'ply'))
    _, fusion = open_map(map_dir)
    p = fusion.points()
    e, n, h = oracle_crs(np.column_stack([p['x'], p['y'], p['z']]), crs)
    for kind in ('las', 'laz'):
        las = laspy.read(res.files[kind])
        assert str(las.header.version) == '1.4'
        # The horizontal part is the CRS asked for (the vertical part: test_products_state_their_vertical_datum).
        assert las.header.parse_crs().to_2d().equals(CRS.from_user_input(crs))
        assert las.header.global_encoding.wkt
        assert las.header.point_count == p['x'].size
        assert np.allclose(las.header.mins, [e.min(), n.min(), h.min()], rtol=0, atol=0.002)
        assert np.allclose(las.header.maxs, [e.max(), n.max(), h.max()], rtol=0, atol=0.002)
        assert np.all(las.red == 0x20 * 257) and np.all(las.green == 0xA0 * 257)
    v, comments = read_ply(res.files['ply'])
    assert v.size == p['x'].size and f'crs {crs}' in comments
    order = np.lexsort((v['y'], v['x']))
    ref = np.lexsort((n, e))
    assert np.abs(v['x'][order] - e[ref]).max() < 1e-3 and np.abs(v['z'][order] - h[ref]).max() < 1e-3
    if crs == 'EPSG:2056':   # LV95 around Zurich: E 2.68e6, N 1.25e6
        assert 2.68e6 < e.min() < 2.69e6 and 1.24e6 < n.min() < 1.26e6


@pytest.mark.parametrize('crs', CRSES)
def test_dsm_geotiff_crs_bounds_and_heights(map_dir, tmp_path, crs):
    import rasterio
    from pyproj import CRS
    from photogram_ros.core import geoid
    from photogram_ros.io.export import export_map, open_map
    ell = export_map(map_dir, tmp_path / 'ell', crs, products=('dsm',))
    ortho_h = export_map(map_dir, tmp_path / 'msl', crs, heights='orthometric', products=('dsm',))
    p = open_map(map_dir)[1].points()
    e, n, _ = oracle_crs(np.column_stack([p['x'], p['y'], p['z']]), crs)
    with rasterio.open(ell.files['dsm']) as ds:
        assert CRS.from_wkt(ds.crs.to_wkt()).to_2d().equals(CRS.from_user_input(crs))
        b = ds.bounds
        # The DSM's outer edges hold every map point, with less than one cell to spare.
        assert b.left <= e.min() < b.left + 0.16 and b.right - 0.16 < e.max() <= b.right
        assert b.bottom <= n.min() < b.bottom + 0.16 and b.top - 0.16 < n.max() <= b.top
        dsm = ds.read(1)
        assert ds.nodata == -9999.0
        assert ds.res == pytest.approx((0.16, 0.16))
        # A cell centre back to ENU: its height is the surface's, plus the ellipsoidal height of the origin.
        row, col = np.argwhere(dsm != ds.nodata)[len(np.argwhere(dsm != ds.nodata)) // 2]
        ce, cn = ds.xy(row, col)
    from photogram_ros.io.export import crs_to_enu
    from photogram_ros.core.geodesy import LocalFrame
    enu = crs_to_enu(LocalFrame(LAT, LON, H), ce, cn, dsm[row, col], crs)
    assert abs(enu[2] - surface(enu[0], enu[1])) < 0.1
    with rasterio.open(ortho_h.files['dsm']) as ds:
        msl = ds.read(1)
    lat, lon = LAT + enu[1] / 111_200, LON + enu[0] / 75_200
    assert dsm[row, col] - msl[row, col] == pytest.approx(geoid.undulation_m(lat, lon), abs=0.01)
    assert 45 < dsm[row, col] - msl[row, col] < 50   # EGM2008 near Zurich


def _crs_of_products(files) -> dict:
    """The CRS of each product, each GeoTIFF copied alone into a folder of its own and opened there with
    GDAL's sidecars (.aux.xml) off: what a user who uploads the .tif gets."""
    import shutil
    import tempfile
    from pathlib import Path

    import laspy
    import rasterio
    from pyproj import CRS
    out = {'las': laspy.read(files['las']).header.parse_crs()}
    for kind in ('dsm', 'dtm', 'ortho'):
        if kind not in files:
            continue
        assert not Path(str(files[kind]) + '.aux.xml').exists(), kind
        with tempfile.TemporaryDirectory() as alone:
            copy = Path(shutil.copy(files[kind], alone))
            with rasterio.Env(GDAL_PAM_ENABLED='NO'):
                with rasterio.open(copy) as ds:
                    assert ds.crs is not None, kind
                    out[kind] = CRS.from_wkt(ds.crs.to_wkt())
    return out


def test_products_state_their_vertical_datum(map_dir, tmp_path):
    """The rasters name their horizontal CRS by its EPSG code and their vertical datum in their metadata
    (io/crs_tags.py); the LAS WKT is the projected CRS (ellipsoidal heights) or a compound with EGM2008 height."""
    import json
    from pyproj import CRS
    from photogram_ros.io.crs_tags import read_vertical
    from photogram_ros.io.export import export_map
    products = ('las', 'dsm', 'dtm')
    ell = export_map(map_dir, tmp_path / 'ell', 'EPSG:32632', products=products)
    for kind, c in _crs_of_products(ell.files).items():
        assert c.to_epsg() == 32632, kind
    for kind in ('dsm', 'dtm'):
        assert read_vertical(ell.files[kind])['VERTICAL_DATUM'] == 'WGS 84 ellipsoid', kind
    msl = export_map(map_dir, tmp_path / 'msl', 'EPSG:32632', heights='orthometric', products=products)
    crses = _crs_of_products(msl.files)
    horizontal, vertical = crses.pop('las').sub_crs_list
    assert horizontal.equals(CRS.from_user_input('EPSG:32632'))
    assert vertical.is_vertical and vertical.to_epsg() == 3855 and vertical.datum.name == 'EGM2008 geoid'
    for kind, c in crses.items():
        assert c.to_epsg() == 32632, kind
        assert read_vertical(msl.files[kind])['VERTICAL_CRS'] == 'EPSG:3855', kind
    assert json.loads((tmp_path / 'msl' / 'export.json').read_text())['crs_with_heights'] == \
        'WGS 84 / UTM zone 32N + EGM2008 height'
    # LV95 is on CH1903+: no standard CRS says "WGS84 ellipsoidal heights" there; the metadata says it, a note too.
    lv95 = export_map(map_dir, tmp_path / 'lv95', 'EPSG:2056', products=products)
    assert all(c.to_epsg() == 2056 for c in _crs_of_products(lv95.files).values())
    assert read_vertical(lv95.files['dsm'])['HEIGHTS'] == 'ellipsoidal'
    assert any('cannot state' in n for n in lv95.notes)
    lv95_msl = export_map(map_dir, tmp_path / 'lv95msl', 'EPSG:2056', heights='orthometric', products=products)
    assert read_vertical(lv95_msl.files['dsm'])['COMPOUND_CRS'] == 'EPSG:2056+3855'


def _cog_layout(path) -> tuple[dict, list]:
    import rasterio
    with rasterio.open(path) as ds:
        return ds.tags(ns='IMAGE_STRUCTURE'), [ds.overviews(b) for b in ds.indexes], ds.profile


def test_rasters_are_cloud_optimized_geotiffs_with_overviews(map_dir, tmp_path):
    from photogram_ros.core.raster import Raster
    from photogram_ros.io.export import export_map, write_geotiff
    res = export_map(map_dir, tmp_path / 'small', 'EPSG:32632', products=('dsm',))
    tags, _, profile = _cog_layout(res.files['dsm'])
    assert tags['LAYOUT'] == 'COG' and tags['COMPRESSION'] == 'DEFLATE' and profile['tiled']
    # A map-sized raster: overviews by factors 2, 4, ... down to one 256-pixel tile, on every band.
    rng = np.random.default_rng(1)
    dsm = Raster(rng.normal(500, 5, (1500, 1100)).astype(np.float32), 465000.0, 5249000.0, 0.16)
    dsm.data[:100, :100] = dsm.nodata
    tags, overviews, profile = _cog_layout(write_geotiff(dsm, tmp_path / 'dsm.tif', 'EPSG:32632', 'DSM',
                                                          heights='ellipsoidal'))
    assert tags['LAYOUT'] == 'COG' and overviews == [[2, 4, 8]]
    assert (profile['blockxsize'], profile['blockysize']) == (256, 256) and profile['nodata'] == -9999.0
    rgba = Raster(rng.integers(0, 255, (2100, 1500, 4), dtype=np.uint8), 465000.0, 5249000.0, 0.08, None)
    tags, overviews, _ = _cog_layout(write_geotiff(rgba, tmp_path / 'ortho.tif', 'EPSG:32632', rgba=True))
    assert tags['LAYOUT'] == 'COG' and overviews == [[2, 4, 8, 16]] * 4     # 2100 px / 16 < 256
    import rasterio
    with rasterio.open(tmp_path / 'ortho.tif') as ds:
        assert [c.name for c in ds.colorinterp] == ['red', 'green', 'blue', 'alpha']
        assert np.array_equal(ds.read(4), rgba.data[:, :, 3])    # lossless


def test_las_points_are_single_returns_with_classes(map_dir, tmp_path):
    import laspy
    from photogram_ros.io.export import export_map, read_ply
    res = export_map(map_dir, tmp_path, 'EPSG:32632', products=('las', 'ply'))
    las = laspy.read(res.files['las'])
    n = las.header.point_count
    assert np.all(las.return_number == 1) and np.all(las.number_of_returns == 1)
    assert las.header.number_of_points_by_return[0] == n and sum(las.header.number_of_points_by_return[1:]) == 0
    classes = np.asarray(las.classification)
    assert set(np.unique(classes)) <= {1, 2, 6}
    # The test surface is bare, smooth ground (a 4 % slope with 0.5 m undulations): all of it ground.
    assert (classes == 2).mean() > 0.99
    v, _ = read_ply(res.files['ply'])
    assert np.array_equal(np.sort(v['classification']), np.sort(classes))


# --- orthomosaic against the simulator's truth -------------------------------------------------


@pytest.fixture(scope='module')
def rendered():
    """Keyframes of the tiny survey rendered from TRUE poses (about 12 frames, cached for the module)."""
    from photogram_ros.core.raster import Keyframe
    from photogram_ros.core.rotations import make_T
    from photogram_ros.sim.render import Exposure, Renderer
    from photogram_ros.sim.scenario import build_world, preset
    cfg = preset('tiny')
    rng = np.random.default_rng(cfg.seed)
    flight, terrain, targets = build_world(cfg, rng)
    cam = cfg.camera()
    r = Renderer(terrain, cam)
    kfs = []
    for t in np.arange(0.0, flight.duration_s, 2.2):
        st = flight.state(t)
        if not st.on_line:
            continue
        T = make_T(st.map_R_cam, st.pos_enu)
        kfs.append(Keyframe(r.render(T, Exposure(), rng), T, cam))
    return cfg, terrain, targets, kfs


def _detect_centres(img_bgr: np.ndarray) -> dict:
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50),
                                  cv2.aruco.DetectorParameters())
    corners, ids, _ = det.detectMarkers(cv2.cvtColor(img_bgr, cv2.COLOR_BGR2GRAY))
    if ids is None:
        return {}
    # float64: float32 pixel positions would round projected coordinates (5e6 m) to half a metre
    return {int(i): c.reshape(4, 2).astype(np.float64).mean(axis=0) for i, c in zip(ids.ravel(), corners)}


def test_orthomosaic_on_true_dem_puts_targets_within_2_gsd(rendered):
    from photogram_ros.core.raster import grid_for, orthomosaic
    cfg, terrain, targets, kfs = rendered
    gsd = cfg.gsd_m
    xs = [t.center_enu[0] for t in targets]
    ys = [t.center_enu[1] for t in targets]
    dem = grid_for(min(xs) - 15, min(ys) - 15, max(xs) + 15, max(ys) + 15, gsd)
    X, Y = dem.cell_centers()
    dem.data = terrain.height_at(X, Y).astype(np.float32)
    ortho = orthomosaic(dem, kfs)
    assert (ortho.data[..., 3] > 0).mean() > 0.9
    found = _detect_centres(ortho.data[..., :3])
    errs = []
    for t in targets:
        assert t.marker_id in found, f'target {t.name} not detected in the orthomosaic'
        u, v = found[t.marker_id]
        x = ortho.x0_m + (u + 0.5) * ortho.res_m
        y = ortho.y1_m - (v + 0.5) * ortho.res_m
        errs.append(np.hypot(x - t.center_enu[0], y - t.center_enu[1]))
    print(f'ortho target errors / GSD: {np.round(np.array(errs) / gsd, 2).tolist()}')
    assert max(errs) <= 2 * gsd


def test_export_command_writes_georeferenced_ortho(rendered, tmp_path):
    """The whole chain: fused map + saved keyframes -> `photogram-ros export` -> ortho GeoTIFF in UTM."""
    import rasterio
    from pyproj import CRS
    from photogram_ros.cli import main
    from photogram_ros.core.fusion import Fusion, FusionConfig
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.io.export import crs_to_enu
    from photogram_ros.io.map_store import MapStore
    cfg, terrain, targets, kfs = rendered
    origin = LocalFrame(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_h_m)
    store = MapStore(tmp_path / 'map', 0.08, 256)
    store.set_origin(origin)
    store.save_camera(kfs[0].camera)
    for k, kf in enumerate(kfs):
        store.save_keyframe_image(k, cv2.imencode('.jpg', kf.image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes())
        store.save_keyframe_pose(k, kf.map_T_cam)
    f = Fusion(FusionConfig(0.08, 256), store)
    rng = np.random.default_rng(9)
    for t in targets:   # ground around each target, from the true DEM
        f.add(pair_cloud(rng, terrain.height_at, t.center_enu[0], t.center_enu[1], 6.0, 6.0, 200.0, 0.02))
    f.flush()
    out = tmp_path / 'out'
    # Each target's ground came from one pair cloud: the default (2 pairs, as replay) would keep nothing.
    assert main(['export', str(tmp_path / 'map'), '--crs', 'EPSG:32632', '--out', str(out),
                 '--min-pairs', '1']) == 0
    for name in ('cloud.las', 'cloud.laz', 'cloud.ply', 'dsm.tif', 'dtm.tif', 'ortho.tif', 'export.json'):
        assert (out / name).exists(), name
    # Each product copied alone opens with its EPSG code; the DSM and DTM say WGS84 ellipsoidal heights.
    from photogram_ros.io.crs_tags import read_vertical
    crses = _crs_of_products({k: out / f for k, f in (('las', 'cloud.las'), ('dsm', 'dsm.tif'), ('dtm', 'dtm.tif'),
                                                        ('ortho', 'ortho.tif'))})
    for kind, c in crses.items():
        assert c.to_epsg() == 32632, kind
    assert read_vertical(out / 'dsm.tif')['HEIGHTS'] == read_vertical(out / 'dtm.tif')['HEIGHTS'] == 'ellipsoidal'
    with rasterio.open(out / 'ortho.tif') as ds:
        assert CRS.from_wkt(ds.crs.to_wkt()).to_2d().to_epsg() == 32632 and ds.count == 4
        rgba = np.dstack([ds.read(b) for b in (1, 2, 3, 4)])
        found = _detect_centres(np.ascontiguousarray(rgba[..., [2, 1, 0]]))
        errs = []
        for t in targets:
            if t.marker_id not in found:
                continue
            u, v = found[t.marker_id]
            e, n = ds.transform @ (float(u) + 0.5, float(v) + 0.5)
            enu = crs_to_enu(origin, e, n, origin.h_m + t.center_enu[2], 'EPSG:32632')
            errs.append(np.hypot(enu[0] - t.center_enu[0], enu[1] - t.center_enu[1]))
    print(f'export ortho target errors / GSD: {np.round(np.array(errs) / cfg.gsd_m, 2).tolist()}')
    assert len(errs) >= len(targets) - 1 and max(errs) <= 2 * cfg.gsd_m


def test_stereo_clouds_fused_then_ortho_on_the_fused_dsm(rendered):
    """The real chain on simulator frames with true poses: stereo pairs -> fusion -> DSM -> ortho."""
    from photogram_ros.core.fusion import Fusion, FusionConfig
    from photogram_ros.core.raster import dsm_from_points, orthomosaic
    from photogram_ros.core.stereo import StereoParams, stereo_pair
    cfg, terrain, targets, kfs = rendered
    gsd = cfg.gsd_m
    ground = float(np.median(terrain.dem.data))
    f = Fusion(FusionConfig(0.08))
    pairs = 0
    for a, b in zip(kfs[:-1], kfs[1:]):
        if np.linalg.norm(a.map_T_cam[:3, 3] - b.map_T_cam[:3, 3]) > 15:   # a turn between lines
            continue
        res = stereo_pair(a.camera, a.image, a.map_T_cam, b.image, b.map_T_cam, StereoParams(),
                          (cfg.altitude_m - ground - 15, cfg.altitude_m - ground + 15))
        if res.ok:
            f.add(res.cloud)
            pairs += 1
    assert pairs >= 4
    p = f.points()
    dz = np.abs(p['z'] - terrain.height_at(p['x'], p['y']))
    dsm = dsm_from_points(p['x'], p['y'], p['z'], 2 * gsd, weights=p['n'])
    X, Y = dsm.cell_centers()
    e = (dsm.data - terrain.height_at(X, Y))[dsm.valid()]
    print(f'stereo -> map: {pairs} pairs, fused cells |dz| median {np.median(dz) / gsd:.2f} GSD, '
          f'p90 {np.percentile(dz, 90) / gsd:.2f} GSD; DSM RMSE {np.sqrt(np.mean(e ** 2)) / gsd:.2f} GSD, '
          f'median {np.median(np.abs(e)) / gsd:.2f} GSD, p99 {np.percentile(np.abs(e), 99) / gsd:.2f} GSD')
    assert np.median(dz) <= gsd and np.percentile(dz, 90) <= 3 * gsd
    assert np.percentile(np.abs(e), 99) <= 3 * gsd
    ortho = orthomosaic(dsm, kfs, res_m=0.08)
    found = _detect_centres(ortho.data[..., :3])
    errs = []
    for t in targets:
        if t.marker_id in found:
            u, v = found[t.marker_id]
            errs.append(np.hypot(ortho.x0_m + (u + 0.5) * ortho.res_m - t.center_enu[0],
                                 ortho.y1_m - (v + 0.5) * ortho.res_m - t.center_enu[1]))
    print(f'ortho on the stereo DSM: {len(errs)}/{len(targets)} targets, errors / GSD '
          f'{np.round(np.array(errs) / gsd, 2).tolist()}')
    assert len(errs) >= len(targets) - 1 and max(errs) <= 2 * gsd


def test_las_of_a_cloud_wider_than_millimetres_can_span(tmp_path):
    """A cloud 3,000 km wide does not fit 32-bit millimetres: the LAS takes a coarser scale and every point
    reads back within it; non-finite coordinates are refused with a DataError, not a laspy traceback."""
    import laspy

    from photogram_ros.errors import DataError
    from photogram_ros.io.export import GeoCloud, write_las
    x = np.array([465712.25, 465750.0, -2204721.5])
    y = np.array([5249481.5, 5249490.0, 5249500.0])
    z = np.array([489.0, 496.25, 127757.5])
    n = len(x)
    cloud = GeoCloud(x, y, z, np.full((n, 3), 200, np.uint8), np.ones(n, np.uint32), np.ones(n, np.float32),
                     'EPSG:32632', 'ellipsoidal')
    las = laspy.read(write_las(cloud, tmp_path / 'wide.las'))
    assert las.header.scales[0] == 0.01 and las.header.scales[1] == 0.001
    assert np.allclose(las.x, x, atol=0.005) and np.allclose(las.z, z, atol=0.0005)
    cloud.z[1] = np.nan
    with pytest.raises(DataError, match='non-finite'):
        write_las(cloud, tmp_path / 'nan.las')


def test_tie_points_far_beyond_the_cameras_are_found():
    from photogram_ros.core.triangulation import near_the_cameras
    rng = np.random.default_rng(3)
    centres = np.column_stack([np.linspace(0, 100, 11), np.zeros(11), np.full(11, 40.0)])
    ground = np.column_stack([rng.uniform(-20, 120, 500), rng.uniform(-30, 30, 500), rng.normal(0, 1, 500)])
    far = np.array([[-2.6e6, 0.0, 0.0], [0.0, 0.0, 1.3e5], [np.nan, 0.0, 0.0]])
    ok = near_the_cameras(np.vstack([ground, far]), centres)
    assert ok[:500].all() and not ok[500:].any()
    assert near_the_cameras(ground, np.empty((0, 3))).all()
