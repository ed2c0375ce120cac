"""Every real survey in ../shared/data through `triangulate` and `replay`, measured from the files they write.

Surveys (../shared/data, see its README):
- brighton: photos/brighton_beach/images, 18 DJI FC300S photos with EXIF GPS; peer: OpenDroneMap's
  odm_model.laz beside them (its heights follow the same EXIF altitudes, so it is compared after a
  constant 3D offset);
- toledo: photos/toledo/images, 42 DJI FC350 photos with EXIF GPS; peer: peer_pycolmap.json (pycolmap's
  per-photo residuals after a similarity to the same EXIF GPS);
- seneca: photos/seneca_part/images, 41 near-infrared photos of a fixed-wing survey with EXIF GPS; no peer;
- phantom3: video/phantom3_village, 100 1080p frames made a bag with `import-frames --noise-h-m 1.5
  --noise-v-m 3` (a 3D fix's noise on the published trajectory), then replayed; its reference is that
  published trajectory (a stand-in GNSS track, not truth). `triangulate` is not run on it (no EXIF).

Per survey and pipeline, from poses.csv / trajectory.csv, report.json, sparse.las and dsm.tif:
- oriented / given: cameras in the pose file / photos in the folder (triangulate) or keyframes taken (replay);
- camera - GNSS residual RMS, horizontal and vertical: after a robust similarity (Umeyama, refitted without
  the cameras beyond 3x the median residual, floor 1 m; those are named) and rigidly (the block's own
  georeference, no transform), in a local ENU frame; the EXIF altitude read as MSL, as `triangulate` does;
- replay against triangulate: the same photos' camera centres (both georeferenced), RMS and max;
- share of cameras within 15 degrees of nadir (the optical axis against the local vertical), median tilt;
- reprojection RMS (px) from report.json;
- DSM completeness: share of the DSM cells inside the convex hull of the camera centres that hold a height,
  and of them the share measured by stereo (dsm.tif band 2 >= 1; the rest interpolated); of the interpolated ones
  those only one stereo pair measured and how far that pair's heights lie from the interpolation (export.json
  dsm.one_pair_check: `dsm_one_pair`);
- agreement with the peer: brighton's DSM against ODM's cloud after a constant 3D offset over every cell
  both hold, and over those inside the camera centres' hull (the ground every flight line passed over), all
  and measured by stereo; the verdict (report.json `verdict`, else n/a) and the command's last line;
- the focal length after the adjustment against the EXIF one (triangulate);
- wall time of the command(s).

Variants (`--variants`): toledo, brighton and seneca with every other photo (half the forward overlap) through
triangulate and replay (the replay row: how many of the keyframes whose photos triangulate oriented replay
oriented, `share_of_triangulated`); through triangulate only: toledo with four geotags moved 80 m (a geo.txt beside copies
of the photos), and toledo + brighton photos in one folder. Their rows name what was broken and what
the verdict said; the other cameras are measured against the photos' own EXIF GPS.

Writes OUT/real_surveys.jsonl (one row a run, through bench/machine.py's ResultWriter: commit, clean-tree
flag, cores, load) and OUT/real_surveys.md (the table); each command's output
folder, log and outcome (.run.json) stay in OUT, and `--remeasure` measures them again without running.
The commands run one after the other (about 12 minutes for all on 2 loaded cores, 17 with --variants).

    ROS_DOMAIN_ID=85 .venv/bin/python bench/real_surveys.py [--only brighton,toledo,phantom3]
        [--pipelines triangulate,replay] [--variants] [--out DIR] [--remeasure]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from photogram_ros.core.geodesy import LocalFrame, geodetic_to_crs  # noqa: E402
from photogram_ros.core.rotations import map_R_cam_from_opk  # noqa: E402
from photogram_ros.core.similarity import umeyama  # noqa: E402
from bench.cover_footprint import dsm_footprint_shares  # noqa: E402
from bench.machine import ResultWriter  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data'
BRIGHTON = DATA / 'photos' / 'brighton_beach'
TOLEDO = DATA / 'photos' / 'toledo'
SENECA = DATA / 'photos' / 'seneca_part'
PHANTOM3 = DATA / 'video' / 'phantom3_village'
SURVEYS = ('brighton', 'toledo', 'seneca', 'phantom3')
# What every figure of this bench measures: the whole product code (a change there makes them stale).
MODULES = ['photogram_ros', 'config']
PIPELINES = ('triangulate', 'replay')
NADIR_DEG = 15.0
MOVED_PHOTOS = ('DJI_0066.JPG', 'DJI_0075.JPG', 'DJI_0086.JPG', 'DJI_0097.JPG')
MOVE_M = 80.0


# --- reading what the commands wrote -------------------------------------------------------------------


def read_poses(path: str | Path) -> dict[str, dict]:
    """poses.csv (triangulate) or trajectory.csv (replay) -> {image name: {lat_deg, lon_deg, h_m, omega_deg,
    phi_deg, kappa_deg[, stamp_ns]}} (heights ellipsoidal, angles in degrees)."""
    out = {}
    with open(path, newline='') as fh:
        for r in csv.DictReader(fh):
            h = r['h_m'] if 'h_m' in r else r['h_ellipsoid_m']
            row = {'lat_deg': float(r['lat_deg']), 'lon_deg': float(r['lon_deg']), 'h_m': float(h),
                   'omega_deg': float(r['omega_deg']), 'phi_deg': float(r['phi_deg']),
                   'kappa_deg': float(r['kappa_deg'])}
            if 'stamp_ns' in r:
                row['stamp_ns'] = int(r['stamp_ns'])
            out[r['image']] = row
    return out


def exif_reference(folder: str | Path) -> dict[str, tuple[float, float, float]]:
    """{photo name: (lat_deg, lon_deg, h_m ellipsoidal)} from each photo's EXIF GPS, its altitude read as
    MSL (as `triangulate` reads it by default)."""
    from photogram_ros.io.image_source import IMAGE_SUFFIXES
    from photogram_ros.io.photo_block import exif_position
    out = {}
    for p in sorted(Path(folder).iterdir()):
        if p.suffix.lower() in IMAGE_SUFFIXES:
            g = exif_position(p)
            if g is not None:
                out[p.name] = g[:3]
    return out


def photo_stamps(folder: str | Path) -> dict[int, str]:
    """{stamp_ns: photo name} as `replay` stamps a photo folder (EXIF time, io/image_source.FolderSource):
    its trajectory.csv names a keyframe by its stamp."""
    from photogram_ros.io.image_source import FolderSource
    return {int(t): p.name for p, t in FolderSource(folder).entries}


def track_reference(dataset: str | Path) -> dict[int, tuple[float, float, float]]:
    """A Map2DFusion data set's published trajectory (the stand-in GNSS track) -> {stamp_ns: (lat_deg,
    lon_deg, h_m ellipsoidal)} through its config.cfg GPS.Origin."""
    from photogram_ros.io.frame_import import read_map2dfusion_config, read_track
    dataset = Path(dataset)
    _, origin = read_map2dfusion_config(dataset / 'config.cfg')
    track = read_track(dataset / 'trajectory.txt')
    lat, lon, h = origin.enu_to_geodetic(track[:, 1:4])
    return {int(round(t * 1e9)): (float(a), float(o), float(z))
            for t, a, o, z in zip(track[:, 0], np.ravel(lat), np.ravel(lon), np.ravel(h))}


def paired_enu(poses: dict[str, dict], reference: dict, by: str = 'image'):
    """Camera centres and their reference positions in one local ENU frame (at the reference's mean).

    by: 'image' matches pose names to reference names, 'stamp_ns' matches pose stamps to reference stamps.
    Returns (names, est_enu (N, 3), ref_enu (N, 3))."""
    keys = [(n, n if by == 'image' else p['stamp_ns']) for n, p in poses.items()]
    keys = [(n, k) for n, k in keys if k in reference]
    if not keys:
        return [], np.zeros((0, 3)), np.zeros((0, 3))
    ref = np.array([reference[k] for _, k in keys], float)
    est = np.array([[poses[n]['lat_deg'], poses[n]['lon_deg'], poses[n]['h_m']] for n, _ in keys], float)
    frame = LocalFrame(float(ref[:, 0].mean()), float(ref[:, 1].mean()), float(ref[:, 2].mean()))
    return ([n for n, _ in keys], frame.geodetic_to_enu(est[:, 0], est[:, 1], est[:, 2]).reshape(-1, 3),
            frame.geodetic_to_enu(ref[:, 0], ref[:, 1], ref[:, 2]).reshape(-1, 3))


# --- metrics ---------------------------------------------------------------------------------------------


def rms_hv(residual_enu: np.ndarray) -> tuple[float, float]:
    """(N, 3) ENU residuals (m) -> (horizontal RMS, vertical RMS) in metres; NaN for none."""
    r = np.asarray(residual_enu, float).reshape(-1, 3)
    if not len(r):
        return float('nan'), float('nan')
    return float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1)))), float(np.sqrt(np.mean(r[:, 2] ** 2)))


def robust_similarity(est_enu: np.ndarray, ref_enu: np.ndarray, k: float = 3.0, floor_m: float = 1.0,
                      iterations: int = 10):
    """Similarity est -> ref (Umeyama), refitted without the cameras whose 3D residual exceeds
    max(k x the median 3D residual of the cameras kept, floor_m) until the set is stable (k = 3 is about 4.5
    sigma of a Gaussian error per axis). Returns (residuals ref-frame (N, 3) of every camera after the final
    fit, mask (N,) of the cameras kept)."""
    est, ref = np.asarray(est_enu, float), np.asarray(ref_enu, float)
    keep = np.ones(len(est), bool)
    res = np.zeros_like(est)
    for _ in range(iterations):
        if keep.sum() < 3:
            break
        res = umeyama(est[keep], ref[keep]).apply(est) - ref
        d = np.linalg.norm(res, axis=1)
        new = d <= max(k * float(np.median(d[keep])), floor_m)
        if np.array_equal(new, keep):
            break
        keep = new
    return res, keep


def residual_figures(names: list[str], est_enu: np.ndarray, ref_enu: np.ndarray) -> dict:
    """Camera - reference residual RMS after a robust similarity and rigidly, the outliers of the similarity
    by name, and the per-camera residuals after a plain similarity on all (as the peer reports them)."""
    if len(names) < 3:
        return {'n': len(names)}
    res, inl = robust_similarity(est_enu, ref_enu)
    h, v = rms_hv(res[inl])
    rh, rv = rms_hv(est_enu - ref_enu)
    plain = umeyama(est_enu, ref_enu).apply(est_enu) - ref_enu
    return {'n': len(names), 'sim_h_m': h, 'sim_v_m': v, 'sim_outliers': [n for n, ok in zip(names, inl) if not ok],
            'rigid_h_m': rh, 'rigid_v_m': rv,
            'per_camera_sim_enu_m': {n: [round(float(x), 3) for x in r] for n, r in zip(names, plain)},
            'per_camera_rigid_enu_m': {n: [round(float(x), 3) for x in r] for n, r in zip(names, est_enu - ref_enu)},
            'per_camera_robust_enu_m': {n: [round(float(x), 3) for x in r] for n, r in zip(names, res)}}


def pipeline_agreement(poses_a: dict[str, dict], poses_b: dict[str, dict]) -> dict:
    """Camera centres of the same photos from two runs (e.g. triangulate and replay), as they are (both
    georeferenced): n, RMS and max of the 3D distance, and the horizontal and vertical RMS (m)."""
    names, a, b = paired_enu(poses_a, {n: (p['lat_deg'], p['lon_deg'], p['h_m']) for n, p in poses_b.items()})
    if not names:
        return {'n': 0}
    d = a - b
    h, v = rms_hv(d)
    return {'n': len(names), 'rms_3d_m': float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)))),
            'max_3d_m': float(np.linalg.norm(d, axis=1).max()), 'h_m': h, 'v_m': v}


def tilt_deg(omega_deg, phi_deg, kappa_deg) -> np.ndarray:
    """Angle (degrees) between each camera's optical axis and straight down."""
    out = []
    for o, p, k in zip(np.ravel(omega_deg), np.ravel(phi_deg), np.ravel(kappa_deg)):
        R = map_R_cam_from_opk(np.radians(o), np.radians(p), np.radians(k))
        out.append(np.degrees(np.arccos(np.clip(-R[2, 2], -1.0, 1.0))))   # optical z against -Up
    return np.array(out)


def nadir_figures(poses: dict[str, dict], max_deg: float = NADIR_DEG) -> dict:
    """Share of cameras within `max_deg` of nadir, median and max tilt (degrees)."""
    if not poses:
        return {}
    t = tilt_deg(*(np.array([p[k] for p in poses.values()]) for k in ('omega_deg', 'phi_deg', 'kappa_deg')))
    return {'nadir_share': float(np.mean(t <= max_deg)), 'tilt_median_deg': float(np.median(t)),
            'tilt_max_deg': float(t.max())}


def read_dsm(path: str | Path):
    """A DSM GeoTIFF -> (heights (H, W) float with NaN where empty, affine transform, CRS string)."""
    import rasterio
    with rasterio.open(path) as ds:
        z = ds.read(1, masked=True).astype(float).filled(np.nan)
        return z, ds.transform, ds.crs.to_string()


def read_dsm_measured(path: str | Path) -> np.ndarray | None:
    """The DSM's cells measured by stereo (band 2, the pairs that measured the cell, >= 1), or None for a
    one-band DSM."""
    import rasterio
    with rasterio.open(path) as ds:
        return ds.read(2) >= 1 if ds.count > 1 else None


def camera_hull_mask(shape: tuple, tr, crs: str, lat_deg, lon_deg) -> np.ndarray:
    """The raster cells (shape, affine `tr`, `crs`) inside the convex hull of the camera centres (lat/lon)."""
    import cv2
    e, n, _ = geodetic_to_crs(np.asarray(lat_deg, float), np.asarray(lon_deg, float), np.zeros(len(lat_deg)), crs)
    cols, rows = ~tr @ (np.asarray(e, float), np.asarray(n, float))
    hull = cv2.convexHull(np.column_stack([cols, rows]).astype(np.float32))
    mask = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull.reshape(-1, 2)).astype(np.int32), 1)
    return mask.astype(bool)


def dsm_completeness(dsm_path: str | Path, lat_deg, lon_deg) -> dict:
    """Share of the DSM's cells inside the convex hull of the camera centres (lat/lon) that hold a height, the
    share of them measured by stereo (band 2; all of them for a one-band DSM), and the share of the whole
    raster holding a height."""
    z, tr, crs = read_dsm(dsm_path)
    inside = camera_hull_mask(z.shape, tr, crs, lat_deg, lon_deg)
    valid = np.isfinite(z)
    measured = read_dsm_measured(dsm_path)
    measured = valid if measured is None else valid & measured
    return {'dsm_hull_share': float(valid[inside].mean()) if inside.any() else float('nan'),
            'dsm_measured_hull_share': float(measured[inside].mean()) if inside.any() else float('nan'),
            'dsm_raster_share': float(valid.mean()), 'dsm_hull_cells': int(inside.sum())}


def odm_grid(cell_m: float = 0.2):
    """OpenDroneMap's odm_model.laz (brighton) as a grid of median heights: (grid, x0, y0, cell_m), EPSG:32615."""
    import laspy
    las = laspy.read(BRIGHTON / 'odm_model.laz')
    x, y, z = np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)
    x0, y0 = x.min(), y.min()
    ix, iy = ((x - x0) / cell_m).astype(int), ((y - y0) / cell_m).astype(int)
    w = ix.max() + 1
    key = iy * w + ix
    order = np.lexsort((z, key))
    u, first, cnt = np.unique(key[order], return_index=True, return_counts=True)
    grid = np.full((iy.max() + 1) * w, np.nan)
    grid[u] = z[order][first + cnt // 2]
    return grid.reshape(-1, w), x0, y0, cell_m


def odm_agreement(points_xyz_32615: np.ndarray, max_points: int = 50_000, seed: int = 0,
                  search_m: float = 6.0) -> dict:
    """Heights of points (EPSG:32615, ellipsoidal as ours) against ODM's surface after a constant 3D offset
    (both follow the same consumer GPS): the horizontal shift by grid search (+-search_m in 0.25 m, then 4 cm
    steps) minimising the median |dz - median dz|, the vertical as the median dz. Returns the offset, n,
    median and p90 |dz| (m)."""
    P = np.asarray(points_xyz_32615, float).reshape(-1, 3)
    if len(P) > max_points:
        P = P[np.random.default_rng(seed).choice(len(P), max_points, replace=False)]
    grid, x0, y0, cell = odm_grid()

    def dz(dx, dy):
        jx = ((P[:, 0] + dx - x0) / cell).astype(int)
        jy = ((P[:, 1] + dy - y0) / cell).astype(int)
        ok = (jx >= 0) & (jx < grid.shape[1]) & (jy >= 0) & (jy < grid.shape[0])
        d = np.full(len(P), np.nan)
        d[ok] = P[ok, 2] - grid[jy[ok], jx[ok]]
        return d[np.isfinite(d)]

    def score(dx, dy):
        d = dz(dx, dy)
        return np.median(np.abs(d - np.median(d))) if len(d) > len(P) // 3 else np.inf

    span = np.arange(-search_m, search_m + 0.01, 0.25)
    _, bx, by = min((score(dx, dy), dx, dy) for dx in span for dy in span)
    _, bx, by = min((score(dx, dy), dx, dy) for dx in np.arange(bx - 0.24, bx + 0.25, 0.04)
                    for dy in np.arange(by - 0.24, by + 0.25, 0.04))
    d = dz(bx, by)
    if not len(d):
        return {'n': 0}
    r = d - np.median(d)
    return {'offset_m': [round(float(bx), 2), round(float(by), 2), round(float(np.median(d)), 3)], 'n': int(len(d)),
            'share_of_points': float(len(d) / len(P)), 'median_abs_dz_m': float(np.median(np.abs(r))),
            'p90_abs_dz_m': float(np.percentile(np.abs(r), 90))}


def sparse_points(las_path: str | Path) -> tuple[np.ndarray, str]:
    """sparse.las -> ((N, 3) x y z, CRS string or '' when the file carries none)."""
    import laspy
    las = laspy.read(las_path)
    crs = las.header.parse_crs()
    return np.column_stack([las.x, las.y, las.z]), (crs.to_string() if crs is not None else '')


def cell_points(z: np.ndarray, tr, cells: np.ndarray | None = None) -> np.ndarray:
    """(N, 3) centres and heights of the raster cells (heights `z`, NaN where empty; affine `tr`) holding a
    height, only where `cells` (a boolean raster of z's shape) is true when given."""
    keep = np.isfinite(z) if cells is None else np.isfinite(z) & cells
    j, i = np.nonzero(keep)
    x, y = tr @ (i + 0.5, j + 0.5)
    return np.column_stack([x, y, z[j, i]])


def dsm_points(dsm_path: str | Path, cells: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """dsm.tif -> ((N, 3) cell centres with a height, CRS string); only the cells where `cells` (a boolean
    raster of the DSM's shape) is true when given."""
    z, tr, crs = read_dsm(dsm_path)
    return cell_points(z, tr, cells), crs


def to_crs(points: np.ndarray, crs: str, dst: str = 'EPSG:32615') -> np.ndarray:
    """(N, 3) points in `crs` -> in `dst` (heights kept)."""
    if not crs or crs.upper() == dst.upper():
        return points
    from pyproj import Transformer
    x, y = Transformer.from_crs(crs, dst, always_xy=True).transform(points[:, 0], points[:, 1])
    return np.column_stack([x, y, points[:, 2]])


def pycolmap_agreement(per_camera_sim_enu_m: dict[str, list], peer_path: str | Path = TOLEDO / 'peer_pycolmap.json',
                       variant: str = 'exhaustive') -> dict:
    """Our per-photo residuals after a similarity to the EXIF GPS against pycolmap's (peer_pycolmap.json):
    the peer's RMS H/V and ours over the photos both oriented (the peer's residuals as it gave them, ours after
    our own similarity over the photos we oriented), and the RMS of the per-photo difference
    (horizontal, vertical), with the correlation of the horizontal components.

    'exhaustive' (pycolmap's default, focal refined) is the variant whose per-image residuals are those of
    its summary (an all-photo similarity: mean zero, RMS 1.181 / 0.843 m); those of 'exhaustive_fixfocal'
    have a mean of (0.06, 0.21, -0.48) m and an RMS of 1.42 / 1.86 m against its stated 1.384 / 1.629 m."""
    peer = json.loads(Path(peer_path).read_text())['variants'][variant]
    theirs = peer['per_image_residual_enu_m']
    common = sorted(set(theirs) & set(per_camera_sim_enu_m))
    if len(common) < 3:
        return {'variant': variant, 'n': len(common)}
    a = np.array([per_camera_sim_enu_m[n] for n in common], float)
    b = np.array([theirs[n] for n in common], float)
    dh, dv = rms_hv(a - b)
    corr = float(np.corrcoef(a[:, :2].ravel(), b[:, :2].ravel())[0, 1])
    oh, ov = rms_hv(a)
    ph, pv = rms_hv(b)
    return {'variant': variant, 'n': len(common), 'peer_h_m': ph, 'peer_v_m': pv, 'ours_h_m': oh, 'ours_v_m': ov,
            'diff_h_m': dh, 'diff_v_m': dv, 'corr_h': corr}


def report_figures(report: dict, pipeline: str) -> dict:
    """Reprojection RMS, verdict, keyframe counts and the camera model from a report.json."""
    out = {'verdict': report.get('verdict') or _find(report, 'verdict') or 'n/a'}
    if pipeline == 'triangulate':
        out['reprojection_px'] = report.get('reprojection_rms_px')
        sc = report.get('self_calibration') or {}
        if 'fx' in sc:
            out['fx_before_px'], out['fx_after_px'] = sc['fx'].get('before'), sc['fx'].get('after')
    else:
        out['reprojection_px'] = _find(report, 'reprojection_rms_px')
        out['keyframes_taken'] = _find(report, 'keyframes_taken')
        out['keyframes_oriented'] = _find(report, 'keyframes_oriented')
        out['mapping'] = _find(report, 'mapping')
    return out


def _find(d, key):
    """The first value under `key` anywhere in nested dicts/lists (depth first), else None."""
    if isinstance(d, dict):
        if key in d:
            return d[key]
        items = d.values()
    elif isinstance(d, list):
        items = d
    else:
        return None
    for v in items:
        r = _find(v, key)
        if r is not None:
            return r
    return None


def exif_focal_px(folder: str | Path) -> float:
    """The focal length (px) the first photo's EXIF gives (core/exif_intrinsics.py)."""
    from photogram_ros.io.image_source import IMAGE_SUFFIXES, exif_intrinsics
    first = next(p for p in sorted(Path(folder).iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES)
    return float(exif_intrinsics(first).camera.fx)


def measure(out: str | Path, pipeline: str, reference: dict, by: str = 'image', given: int | None = None,
            peer: str | None = None, photos: str | Path | None = None, names_by_stamp: dict | None = None) -> dict:
    """All figures of one run from its output folder `out`.

    reference: {image name or stamp_ns: (lat, lon, h ellipsoidal)}; peer: 'odm' or 'pycolmap' or None;
    photos: the folder whose EXIF focal length the adjusted one is compared with (triangulate);
    names_by_stamp: {stamp_ns: photo name} to name a replay's keyframes by their photo."""
    out = Path(out)
    row: dict = {}
    rep_path = out / 'report.json'
    report = json.loads(rep_path.read_text()) if rep_path.exists() else {}
    row.update(report_figures(report, pipeline))
    pose_file = out / ('poses.csv' if pipeline == 'triangulate' else 'trajectory.csv')
    poses = read_poses(pose_file) if pose_file.exists() else {}
    if names_by_stamp:
        poses = {names_by_stamp.get(p.get('stamp_ns'), n): p for n, p in poses.items()}
    row['oriented'] = len(poses)
    if given is None and pipeline == 'replay':
        given = row.get('keyframes_taken')
    row['given'] = given
    names, est, ref = paired_enu(poses, reference, by)
    res = residual_figures(names, est, ref)
    row.update({k: v for k, v in res.items() if not k.startswith('per_camera')})
    row.update(nadir_figures(poses))
    dsm = out / 'dsm.tif'
    if dsm.exists() and poses:
        row.update(dsm_completeness(dsm, [p['lat_deg'] for p in poses.values()], [p['lon_deg'] for p in poses.values()]))
        row.update(dsm_footprint_shares(dsm, *zip(*[(p['lat_deg'], p['lon_deg']) for p in poses.values()])))
    exported = json.loads((out / 'export.json').read_text()).get('dsm', {}) if (out / 'export.json').exists() else {}
    if exported.get('footprint'):   # the export's own: the camera centres' hull widened by a quarter of the height
        row['export_footprint'] = exported['footprint']
    if exported.get('one_pair_check'):
        # The cells only one stereo pair measured, against the interpolated DSM there (io/export_raster).
        row['dsm_one_pair'] = {'hull_share': (exported.get('camera_hull') or {}).get('filled_one_pair'),
                               **exported['one_pair_check']}
    if photos is not None and row.get('fx_after_px'):
        f0 = exif_focal_px(photos)
        row['fx_exif_px'] = f0
        row['focal_vs_exif'] = row['fx_after_px'] / f0 - 1.0
    if peer == 'pycolmap' and 'per_camera_sim_enu_m' in res:
        row['peer'] = pycolmap_agreement(res['per_camera_sim_enu_m'])
        row['peer_fixfocal'] = pycolmap_agreement(res['per_camera_sim_enu_m'], variant='exhaustive_fixfocal')
    elif peer == 'odm':
        if dsm.exists():
            z, tr, crs = read_dsm(dsm)
            row['peer'] = {'against': 'dsm.tif cells', **odm_agreement(to_crs(cell_points(z, tr), crs))}
            if poses:
                inside = camera_hull_mask(z.shape, tr, crs, [p['lat_deg'] for p in poses.values()],
                                          [p['lon_deg'] for p in poses.values()])
                measured = read_dsm_measured(dsm)
                for key, cells in (('peer_in_hull', inside),
                                   ('peer_in_hull_measured', inside if measured is None else inside & measured)):
                    row[key] = {'against': 'dsm.tif cells in the camera hull',
                                **odm_agreement(to_crs(cell_points(z, tr, cells), crs))}
        elif (out / 'sparse.las').exists():
            pts, crs = sparse_points(out / 'sparse.las')
            row['peer'] = {'against': 'sparse.las', **odm_agreement(to_crs(pts, crs or report.get('crs', '')))}
    row['per_camera_robust_enu_m'] = res.get('per_camera_robust_enu_m', {})
    row['per_camera_rigid_enu_m'] = res.get('per_camera_rigid_enu_m', {})
    return row


def safe_measure(*args) -> dict:
    """measure(*args), or {'measure_error': ...} when the outputs cannot be read (the row is kept)."""
    try:
        return measure(*args)
    except Exception as exc:   # noqa: BLE001 - a bench row records what went wrong and the run goes on
        return {'measure_error': f'{type(exc).__name__}: {exc}'}


# --- running the commands --------------------------------------------------------------------------------


REMEASURE = False   # --remeasure: take each command's outcome from its .run.json instead of running it
REPLAY_PARAMS = ''  # --replay-params: a parameter file every replay runs with (config/replay.yaml when empty)


def run_command(args: list[str], log_path: Path, timeout_s: float = 3600) -> dict:
    """`photogram-ros ARGS` in the project root (as a user runs it): exit code, wall time, the last stdout
    line; stdout and stderr go to `log_path`, the outcome to `log_path`.run.json."""
    saved = log_path.with_suffix('.run.json')
    if REMEASURE and saved.exists():
        return json.loads(saved.read_text())
    if REPLAY_PARAMS and args[0] == 'replay':
        args = [*args, '--params', REPLAY_PARAMS]
    env = {**os.environ, 'PYTHONPATH': str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', '')}
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', *args], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=timeout_s)
    wall = time.monotonic() - t0
    log_path.write_text(f'$ photogram-ros {" ".join(args)}\n--- stdout\n{r.stdout}\n--- stderr\n{r.stderr}')
    lines = [ln for ln in r.stdout.splitlines() if ln.strip()]
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    outcome = {'exit': r.returncode, 'wall_s': round(wall, 1), 'last_line': lines[-1] if lines else '',
               'stderr_last': err[-1] if err and r.returncode != 0 else ''}
    saved.write_text(json.dumps(outcome))
    return outcome


def photo_count(folder: Path) -> int:
    from photogram_ros.io.image_source import IMAGE_SUFFIXES
    return sum(p.suffix.lower() in IMAGE_SUFFIXES for p in folder.iterdir())


def run_photos(survey: str, pipeline: str, folder: Path, out: Path, peer: str | None, reference=None,
               extra_row: dict | None = None) -> dict:
    """triangulate or replay a photo folder into out/<survey>_<pipeline> and measure it."""
    dst = out / f'{survey}_{pipeline}'
    if not REMEASURE:
        shutil.rmtree(dst, ignore_errors=True)
    cmd = [pipeline, str(folder), '--out', str(dst)] + (['--quiet'] if pipeline == 'replay' else [])
    run = run_command(cmd, out / f'{survey}_{pipeline}.log')
    row = {'survey': survey, 'pipeline': pipeline, 'command': 'photogram-ros ' + ' '.join(cmd), **run,
           'photos': photo_count(folder), **(extra_row or {})}
    row.update(safe_measure(dst, pipeline, reference if reference is not None else exif_reference(folder), 'image',
                            photo_count(folder) if pipeline == 'triangulate' else None, peer, folder if pipeline == 'triangulate' else None,
                            photo_stamps(folder) if pipeline == 'replay' else None))
    return row


def run_phantom3(out: Path) -> dict:
    """import-frames (3D-fix noise) then replay; measured against the published trajectory."""
    bag, dst = out / 'phantom3_bag', out / 'phantom3_replay'
    if not REMEASURE:
        shutil.rmtree(bag, ignore_errors=True)
        shutil.rmtree(dst, ignore_errors=True)
    imp = ['import-frames', str(PHANTOM3), '--out', str(bag), '--noise-h-m', '1.5', '--noise-v-m', '3']
    r1 = run_command(imp, out / 'phantom3_import.log')
    cmd = ['replay', str(bag), '--out', str(dst), '--quiet']
    r2 = run_command(cmd, out / 'phantom3_replay.log')
    row = {'survey': 'phantom3', 'pipeline': 'replay',
           'command': 'photogram-ros ' + ' '.join(imp) + ' && photogram-ros ' + ' '.join(cmd),
           **r2, 'exit': r1['exit'] or r2['exit'], 'wall_s': round(r1['wall_s'] + r2['wall_s'], 1),
           'import_wall_s': r1['wall_s'], 'photos': len(list((PHANTOM3 / 'rgb').glob('*.jpg')))}
    row.update(safe_measure(dst, 'replay', track_reference(PHANTOM3), 'stamp_ns', None, None))
    return row


# --- deliberately broken blocks ----------------------------------------------------------------------


def write_geo_txt(path: Path, positions: dict[str, tuple[float, float, float]], h_acc_m: float = 5.0,
                  v_acc_m: float = 2.0) -> None:
    """An OpenDroneMap geo.txt (EPSG:4326: image lon lat h omega phi kappa h_acc v_acc; heights ellipsoidal)."""
    lines = ['EPSG:4326'] + [f'{n} {lon:.9f} {lat:.9f} {h:.3f} 0 0 0 {h_acc_m:g} {v_acc_m:g}'
                             for n, (lat, lon, h) in sorted(positions.items())]
    path.write_text('\n'.join(lines) + '\n')


def linked_block(src: Path, dst: Path):
    """The photos of `src` linked into `dst`: ({image: EXIF (lat, lon, h)}, a LocalFrame at their mean)."""
    dst.mkdir(parents=True, exist_ok=True)
    ref = exif_reference(src)
    for name in ref:
        link = dst / name
        if not link.exists():
            link.symlink_to(src / name)
    return ref, LocalFrame(*np.mean(np.array(list(ref.values())), axis=0))


def moved_geotags_block(dst: Path, moved: tuple[str, ...] = MOVED_PHOTOS, move_m: float = MOVE_M) -> dict:
    """toledo's photos (linked) in `dst` with a geo.txt of their EXIF positions, `moved` ones shifted by
    `move_m` horizontally (east, north, west, south in turn). Returns {image: true (lat, lon, h)}."""
    ref, frame = linked_block(TOLEDO / 'images', dst)
    geo = dict(ref)
    for k, name in enumerate(moved):
        enu = frame.geodetic_to_enu(*ref[name]).reshape(3)
        enu[:2] += move_m * np.array([(1, 0), (0, 1), (-1, 0), (0, -1)][k % 4])
        lat, lon, h = frame.enu_to_geodetic(enu)
        geo[name] = (float(np.ravel(lat)[0]), float(np.ravel(lon)[0]), float(np.ravel(h)[0]))
    write_geo_txt(dst / 'geo.txt', geo)
    return ref


def two_sites_block(dst: Path) -> dict:
    """toledo's and brighton's photos (linked) in one folder. Returns {image: EXIF (lat, lon, h)}."""
    dst.mkdir(parents=True, exist_ok=True)
    ref = {}
    for src in (TOLEDO / 'images', BRIGHTON / 'images'):
        for name, g in exif_reference(src).items():
            link = dst / name
            if not link.exists():
                link.symlink_to(src / name)
            ref[name] = g
    return ref


def half_overlap_block(src: Path, dst: Path) -> dict:
    """Every other photo of `src` (in name order, the flight's order) linked into `dst`: half the forward
    overlap. Returns {image: EXIF (lat, lon, h)} of those photos."""
    dst.mkdir(parents=True, exist_ok=True)
    ref = exif_reference(src)
    kept = sorted(ref)[::2]
    for name in kept:
        link = dst / name
        if not link.exists():
            link.symlink_to(src / name)
    return {n: ref[n] for n in kept}


def noisy_geotags_block(src: Path, dst: Path, sigma_h_m: float = 17.0, seed: int = 0) -> dict:
    """The photos of `src` (linked) in `dst` with a geo.txt of their EXIF positions moved by Gaussian noise of
    `sigma_h_m` horizontally (a compact camera's GPS; stated 5 m, as the EXIF would). Returns {image: EXIF
    (lat, lon, h)}: the block is measured against the photos' own, unperturbed geotags."""
    ref, frame = linked_block(src, dst)
    rng = np.random.default_rng(seed)
    geo = {}
    for name in sorted(ref):
        enu = frame.geodetic_to_enu(*ref[name]).reshape(3)
        enu[:2] += rng.normal(0.0, sigma_h_m, 2)
        lat, lon, h = frame.enu_to_geodetic(enu)
        geo[name] = (float(np.ravel(lat)[0]), float(np.ravel(lon)[0]), float(np.ravel(h)[0]))
    write_geo_txt(dst / 'geo.txt', geo)
    return ref


def run_noisy(out: Path, surveys=('brighton', 'toledo'), sigma_h_m: float = 17.0) -> list[dict]:
    """`triangulate` on brighton's and toledo's photos with geotags scattered `sigma_h_m` (noisy_geotags_block)."""
    rows = []
    for survey in surveys:
        src = (BRIGHTON if survey == 'brighton' else TOLEDO) / 'images'
        folder = out / 'blocks' / f'{survey}_noisy'
        ref = noisy_geotags_block(src, folder, sigma_h_m)
        rows.append(run_photos(f'{survey}_noisy', 'triangulate', folder, out, None, reference=ref,
                               extra_row={'broken': f'geotags of {survey} scattered {sigma_h_m:g} m horizontally '
                                                    '(geo.txt, stated 5 m)'}))
    return rows


def replay_share_of_triangulated(folder: Path, tri_dir: Path, rep_dir: Path) -> dict:
    """How many of the keyframes whose photos `triangulate` oriented `replay` oriented (issue #43's share):
    triangulate's oriented photos (poses.csv), replay's oriented keyframes (trajectory.csv, stamp -> photo) and
    keyframes taken (report.json). replay names only its oriented keyframes: when it took fewer keyframes than
    photos the denominator is min(keyframes taken, photos triangulate oriented) and the share a lower bound."""
    names = photo_stamps(folder)
    tri = set(read_poses(tri_dir / 'poses.csv')) if (tri_dir / 'poses.csv').exists() else set()
    traj = rep_dir / 'trajectory.csv'
    rep = {names.get(p.get('stamp_ns'), n) for n, p in read_poses(traj).items()} if traj.exists() else set()
    rj = rep_dir / 'report.json'
    taken = int((json.loads(rj.read_text()) if rj.exists() else {}).get('keyframes_taken') or 0)
    photos = photo_count(folder)
    denom = len(tri) if taken == photos else min(taken, len(tri))
    both = len(rep & tri)
    return {'triangulate_oriented': len(tri), 'replay_keyframes': taken, 'replay_oriented': len(rep),
            'replay_oriented_of_triangulated': both, 'keyframes_triangulated': denom,
            'share_of_triangulated': round(both / denom, 4) if denom else None, 'share_exact': taken == photos}


def run_variants(out: Path) -> list[dict]:
    """The broken blocks (triangulate), and every other photo of each photo set through triangulate and replay:
    the replay row carries replay_share_of_triangulated."""
    rows = []
    for survey, src in (('toledo', TOLEDO / 'images'), ('brighton', BRIGHTON / 'images'),
                        ('seneca', SENECA / 'images')):
        folder = out / 'blocks' / f'{survey}_half'
        ref = half_overlap_block(src, folder)
        what = f'every other photo of {survey} ({len(ref)}): half the forward overlap'
        rows.append(run_photos(f'{survey}_half', 'triangulate', folder, out, None, reference=ref,
                               extra_row={'broken': what}))
        rep = run_photos(f'{survey}_half', 'replay', folder, out, None, reference=ref, extra_row={'half': what})
        rep.update(replay_share_of_triangulated(folder, out / f'{survey}_half_triangulate',
                                                out / f'{survey}_half_replay'))
        rows.append(rep)
    folder = out / 'blocks' / 'toledo_moved4'
    ref = moved_geotags_block(folder)
    row = run_photos('toledo_moved4', 'triangulate', folder, out, None, reference=ref,
                     extra_row={'broken': f'geotags of {", ".join(MOVED_PHOTOS)} moved {MOVE_M:g} m (geo.txt)'})
    row.update(broken_block_figures(row, MOVED_PHOTOS))
    rows.append(row)
    folder = out / 'blocks' / 'two_sites'
    ref = two_sites_block(folder)
    row = run_photos('two_sites', 'triangulate', folder, out, None, reference=ref,
                     extra_row={'broken': 'toledo (42) and brighton (18) photos in one folder'})
    brighton = tuple(exif_reference(BRIGHTON / 'images'))
    row.update(broken_block_figures(row, brighton))
    rows.append(row)
    return rows


def broken_block_figures(row: dict, broken: tuple[str, ...]) -> dict:
    """Whether the verdict (report.json's, else the last line) names the broken photos; the other cameras'
    residuals against their true positions after the robust similarity (the block's shape) and rigidly (its
    georeference: what a user receives); and the broken photos' own rigid residuals (where the block put
    them, against where they really were)."""
    verdict = verdict_words(row)
    named = [n for n in broken if Path(n).stem in verdict]
    out = {'broken_named_in_verdict': f'{len(named)}/{len(broken)}'}
    for what, key in (('sim', 'per_camera_robust_enu_m'), ('rigid', 'per_camera_rigid_enu_m')):
        others = np.array([r for n, r in row.get(key, {}).items() if n not in broken]).reshape(-1, 3)
        h, v = rms_hv(others)
        out.update({'others_n': len(others), f'others_{what}_h_m': h, f'others_{what}_v_m': v,
                    f'others_{what}_max_h_m': float(np.hypot(others[:, 0], others[:, 1]).max()) if len(others)
                    else float('nan')})
    mine = np.array([r for n, r in row.get('per_camera_rigid_enu_m', {}).items() if n in broken]).reshape(-1, 3)
    out['broken_rigid_h_m'] = [round(float(np.hypot(r[0], r[1])), 2) for r in mine]
    return out


# --- the table -------------------------------------------------------------------------------------------


def _f(v, fmt='.2f', unit=''):
    return 'n/a' if v is None or (isinstance(v, float) and not np.isfinite(v)) else f'{v:{fmt}}{unit}'


def peer_text(row: dict) -> str:
    p = row.get('peer')
    if not p:
        return '—'
    if 'median_abs_dz_m' in p:
        hull, hull_m = row.get('peer_in_hull') or {}, row.get('peer_in_hull_measured') or {}
        return (f"ODM vs our {p['against']}: median \\|dz\\| {p['median_abs_dz_m'] * 100:.1f} cm, p90 "
                f"{p['p90_abs_dz_m'] * 100:.0f} cm (offset {p['offset_m']} m)"
                + (f"; in the camera hull {hull['median_abs_dz_m'] * 100:.1f} cm (measured cells "
                   f"{hull_m['median_abs_dz_m'] * 100:.1f} cm)" if hull.get('n') and hull_m.get('n') else ''))
    if 'diff_h_m' in p:
        q = row.get('peer_fixfocal') or {}
        return (f"pycolmap ({p['n']} photos) {p['peer_h_m']:.2f} / {p['peer_v_m']:.2f} m, ours (plain similarity) "
                f"{p['ours_h_m']:.2f} / {p['ours_v_m']:.2f} m; per-photo difference {p['diff_h_m']:.2f} m H, "
                f"{p['diff_v_m']:.2f} m V (corr {p['corr_h']:.2f})"
                + (f"; against pycolmap with the EXIF focal {q['diff_h_m']:.2f} m H, {q['diff_v_m']:.2f} m V "
                   f"(corr {q['corr_h']:.2f})" if q.get('diff_h_m') is not None else ''))
    return json.dumps(p)


def verdict_text(row: dict, most: int = 300) -> str:
    """report.json's verdict (core/block_check.py: status, summary, findings) as one line, or n/a."""
    v = row.get('verdict', 'n/a')
    if isinstance(v, dict):
        v = v.get('summary') or v.get('status') or json.dumps(v)
    return str(v).replace('|', '\\|')[:most]


def verdict_words(row: dict) -> str:
    """What the verdict says of which photos: its summary, its findings' texts and photos, the command's
    last line and (when it failed) its last error line."""
    v = row.get('verdict')
    parts = [row.get('last_line', ''), row.get('stderr_last', '')]
    if isinstance(v, dict):
        parts.append(str(v.get('summary', '')))
        for f in v.get('findings', []):
            parts += [str(f.get('text', '')), ' '.join(map(str, f.get('photos', [])))]
    return ' '.join(parts)


def markdown(rows: list[dict], commit: str) -> str:
    head = ('| survey | pipeline | oriented | GNSS RMS H / V after robust similarity (m) | rigid H / V (m) | '
            f'within {NADIR_DEG:g}° of nadir (median tilt) | reprojection (px) | DSM completeness in camera hull (measured by '
            'stereo; unclipped by the raster: measured, by one pair) | peer | verdict (report.json) | last line | wall (s) |')
    lines = [f'Measured with the product code of commit {commit}.', '', head, '|' + '---|' * 12]
    for r in rows:
        out = ''
        if r.get('sim_outliers'):
            out = f" (robust fit left out {len(r['sim_outliers'])}: {', '.join(r['sim_outliers'][:6])})"
        lines.append(' | '.join([
            f"| {r['survey']}", r['pipeline'], f"{r.get('oriented', 0)}/{r.get('given')}"
            + (f" keyframes of {r['photos']} images" if r['pipeline'] == 'replay' and r.get('photos') else ''),
            f"{_f(r.get('sim_h_m'))} / {_f(r.get('sim_v_m'))}{out}", f"{_f(r.get('rigid_h_m'))} / {_f(r.get('rigid_v_m'))}",
            f"{_f(r.get('nadir_share'), '.0%')} ({_f(r.get('tilt_median_deg'), '.1f', '°')})",
            _f(r.get('reprojection_px'), '.3f'),
            _f(r.get('dsm_hull_share'), '.1%') + (f" ({_f(r['dsm_measured_hull_share'], '.1%')} measured)"
                                                  if r.get('dsm_measured_hull_share') is not None else '')
            + (f"; unclipped {_f(r['dsm_footprint_measured_share'], '.1%')}, "
               f"{_f(r.get('dsm_footprint_one_pair_share'), '.1%')} by 1 pair" if 'dsm_footprint_measured_share' in r else ''),
            peer_text(r), verdict_text(r),
            r.get('last_line', '').replace('|', '\\|')[:160] or r.get('stderr_last', '')[:160],
            f"{r.get('wall_s', 0):.0f} |"]))
    both = [r for r in rows if r.get('vs_triangulate', {}).get('n')]
    if both:
        lines += ['', '| survey | replay against triangulate: the same photos\' camera centres, RMS 3D (H / V), max |',
                  '|---|---|']
        for r in both:
            a = r['vs_triangulate']
            lines.append(f"| {r['survey']} | {a['rms_3d_m']:.2f} m ({a['h_m']:.2f} / {a['v_m']:.2f} m), max "
                         f"{a['max_3d_m']:.2f} m over {a['n']} photos |")
    broken = [r for r in rows if r.get('broken')]
    if broken:
        lines += ['', '| broken block | what | exit | broken photos named in the verdict | other cameras against '
                  'their true GNSS: robust similarity H / V RMS, max H (m) | the same, rigid | broken photos: '
                  'rigid H from their true position (m) | verdict / last line |', '|---|---|---|---|---|---|---|---|']
        for r in broken:
            lines.append(f"| {r['survey']} | {r['broken']} | {r['exit']} | {r.get('broken_named_in_verdict')} | "
                         f"{_f(r.get('others_sim_h_m'))} / {_f(r.get('others_sim_v_m'))}, "
                         f"{_f(r.get('others_sim_max_h_m'))} (n={r.get('others_n')}) | "
                         f"{_f(r.get('others_rigid_h_m'))} / {_f(r.get('others_rigid_v_m'))}, "
                         f"{_f(r.get('others_rigid_max_h_m'))} | {r.get('broken_rigid_h_m')} | "
                         f"{verdict_text(r)}; {(r.get('last_line') or r.get('stderr_last', ''))[:200]} |")
    return '\n'.join(lines) + '\n'


def git_commit() -> str:
    """The last commit that changed the product code (photogram_ros/, config/), '+modified' when the working
    tree changes it, and HEAD."""
    def git(*args):
        return subprocess.run(['git', *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    try:
        product = git('log', '-1', '--format=%h', '--', 'photogram_ros', 'config')
        dirty = git('status', '--porcelain', 'photogram_ros', 'config')
        return f"{product}{'+modified' if dirty else ''} (HEAD {git('rev-parse', '--short', 'HEAD')})"
    except OSError:
        return 'unknown'


def run_all(surveys, pipelines, variants: bool, out: Path, noisy=()) -> list[dict]:
    out.mkdir(parents=True, exist_ok=True)
    commit = git_commit()
    rows = []
    writer = ResultWriter(out / 'real_surveys.jsonl', 'real_surveys', MODULES)

    def keep(row):
        row['commit'] = commit
        if REPLAY_PARAMS and 'replay' in row.get('command', ''):
            row['replay_params'] = Path(REPLAY_PARAMS).read_text()
        rows.append(row)
        writer.write({k: v for k, v in row.items() if not k.startswith('per_camera')})
        (out / 'real_surveys.md').write_text(markdown(rows, commit))
        print(f"{row['survey']} {row['pipeline']}: {row.get('oriented')}/{row.get('given')} oriented, "
              f"{_f(row.get('sim_h_m'))} / {_f(row.get('sim_v_m'))} m after a similarity, "
              f"{_f(row.get('rigid_h_m'))} / {_f(row.get('rigid_v_m'))} m rigid, nadir {_f(row.get('nadir_share'), '.0%')}, "
              f"{row['wall_s']:.0f} s", flush=True)

    photo_sets = {'brighton': (BRIGHTON, 'odm'), 'toledo': (TOLEDO, 'pycolmap'), 'seneca': (SENECA, None)}
    for s in surveys:
        for p in pipelines:
            if s in photo_sets:
                src, peer = photo_sets[s]
                row = run_photos(s, p, src / 'images', out, peer)
                if p == 'replay' and (out / f'{s}_triangulate' / 'poses.csv').exists():
                    # issue #43's share: of the keyframes whose photos triangulate oriented, how many replay oriented
                    row.update(replay_share_of_triangulated(src / 'images', out / f'{s}_triangulate', out / f'{s}_replay'))
                keep(row)
            elif s == 'phantom3' and p == 'replay':
                keep(run_phantom3(out))
        if s in ('brighton', 'toledo', 'seneca') and set(PIPELINES) <= set(pipelines):
            folder = {'brighton': BRIGHTON, 'toledo': TOLEDO, 'seneca': SENECA}[s] / 'images'
            tri, rep = out / f'{s}_triangulate' / 'poses.csv', out / f'{s}_replay' / 'trajectory.csv'
            if tri.exists() and rep.exists():
                names = photo_stamps(folder)
                rp = {names.get(p['stamp_ns'], n): p for n, p in read_poses(rep).items()}
                rows[-1]['vs_triangulate'] = pipeline_agreement(read_poses(tri), rp)
                (out / 'real_surveys.md').write_text(markdown(rows, commit))
                writer.write({'survey': s, 'pipeline': 'replay vs triangulate', **rows[-1]['vs_triangulate']})
    if variants:
        for row in run_variants(out):
            keep(row)
    for row in run_noisy(out, noisy) if noisy else []:
        keep(row)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--only', default=','.join(SURVEYS), help='surveys, comma separated (or "none")')
    ap.add_argument('--pipelines', default=','.join(PIPELINES), help='pipelines, comma separated')
    ap.add_argument('--variants', action='store_true', help='also the broken blocks (toledo with four geotags '
                                                            'moved 80 m; toledo + brighton in one folder)')
    ap.add_argument('--noisy', default='', help='also brighton and/or toledo with geotags scattered 17 m '
                                                '(comma separated)')
    ap.add_argument('--out', default='/tmp/real_surveys', help='output folder')
    ap.add_argument('--remeasure', action='store_true', help='measure the outputs already in --out again (no '
                                                              'command is run; wall times as recorded)')
    ap.add_argument('--replay-params', default='', help='a parameter file for every replay (a copy of '
                                                         'config/replay.yaml with a change; kept in each row)')
    a = ap.parse_args(argv)
    global REMEASURE, REPLAY_PARAMS
    REMEASURE = a.remeasure
    REPLAY_PARAMS = str(Path(a.replay_params).resolve()) if a.replay_params else ''
    surveys = [s.strip() for s in a.only.split(',') if s.strip() and s.strip() != 'none']
    pipelines = [p.strip() for p in a.pipelines.split(',') if p.strip()]
    bad = [s for s in surveys if s not in SURVEYS] + [p for p in pipelines if p not in PIPELINES]
    if bad:
        ap.error(f'unknown {bad}; surveys {SURVEYS}, pipelines {PIPELINES}')
    out = Path(a.out)
    rows = run_all(surveys, pipelines, a.variants, out, [x for x in a.noisy.split(',') if x])
    print(markdown(rows, rows[0]['commit'] if rows else git_commit()))
    return 0


if __name__ == '__main__':
    sys.exit(main())
