"""Coverage of a replay's products inside the convex hull of its camera centres, read from the files alone
(dsm.tif, ortho.tif, trajectory.csv), and the DSM against a peer's point cloud (OpenDroneMap's
odm_model.laz of the same photos) when given.

Shares: DSM cells holding a height, of them measured by stereo (band 2 >= 1) and interpolated (band 2 = 0;
a one-band DSM counts every height as measured); ortho cells holding a colour (alpha > 0).
Against the peer: its points gridded on our DSM cells (median per cell, cells with >= 3 points), dz = ours -
peer, minus the median dz over the cells compared (a constant offset: the two blocks' datums differ), as
median / p90 |dz|, over all cells, the measured ones, the interpolated ones, and those inside the hull; for
all and the measured cells also after a fitted plane (offset + tilt, least absolute deviations) instead of the
constant offset, with the tilt (a tilted georeference is another problem than a noisy surface), and after a
quadratic surface (a bowl: what an unmodelled lens distortion gives a block), with the quadratic part's spread
over the cells (its 5th to 95th percentile) and its curvatures. `--shift-m S` first moves our DSM horizontally by
the offset (grid search +-S m in 0.25 m) that fits the peer best (the two georeferences differ horizontally too).
`--photos DIR`: the adjusted camera heights (trajectory.csv) against the photos' EXIF altitudes (matched by the
replay's stamps) after a constant and after a quadratic surface: whether the block's cameras bend away from the
altitude the drone held (a dome of the cameras goes with a bowl of the ground).
`--truth FLIGHT` (a simulated flight's folder, the replay's input beside its ground_truth.json): the DSM's
measured cells against the true DEM and the keyframe centres against the true cameras, each after a constant
and after a quadratic surface, with the quadratic part's spread and curvatures: the block's doming against
truth (`truth_shape`).
Prints one JSON line per folder.

    .venv/bin/python bench/products_coverage.py OUT [OUT ...] [--peer ../shared/data/photos/brighton_beach/odm_model.laz]
        [--shift-m 2] [--photos ../shared/data/photos/brighton_beach/images] [--truth SIMULATED_FLIGHT]
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import rasterio


def hull(shape, transform, e, n) -> np.ndarray:
    c, r = (~transform) * (np.asarray(e), np.asarray(n))
    out = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(out, cv2.convexHull(np.column_stack([c, r]).round().astype(np.int32)), 1)
    return out > 0


def peer_median(path, transform, shape) -> np.ndarray:
    import laspy
    las = laspy.read(path)
    c, r = (~transform) * (np.asarray(las.x), np.asarray(las.y))
    c, r = np.floor(c).astype(int), np.floor(r).astype(int)
    ok = (c >= 0) & (r >= 0) & (c < shape[1]) & (r < shape[0])
    key, z = r[ok] * shape[1] + c[ok], np.asarray(las.z)[ok]
    o = np.lexsort((z, key))
    ks, zs = key[o], z[o]
    start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    n = np.diff(np.r_[start, ks.size])
    med = np.full(shape[0] * shape[1], np.nan)
    good = n >= 3
    med[ks[start[good]]] = zs[start[good] + (n[good] - 1) // 2]
    return med.reshape(shape)


def quadratic_part(e: np.ndarray, n: np.ndarray, dz: np.ndarray, iters: int = 3) -> dict:
    """The quadratic surface fitted to dz (least absolute deviations, as plane_residual): the spread of its
    quadratic terms over the cells (5th, 95th percentile, m) and its two curvatures (1/km; both positive: a
    bowl of ours against the peer, both negative: a dome)."""
    e, n = e - e.mean(), n - n.mean()
    A = np.column_stack([np.ones_like(e), e, n, e * e, e * n, n * n])
    w = np.ones_like(dz)
    for _ in range(iters + 1):
        coef = np.linalg.lstsq(A * w[:, None], dz * w, rcond=None)[0]
        w = 1.0 / np.sqrt(np.maximum(np.abs(dz - A @ coef), 0.02))
    q = A[:, 3:] @ coef[3:]
    H = np.array([[2 * coef[3], coef[4]], [coef[4], 2 * coef[5]]])
    return {'quadratic_p5_p95_m': [round(float(np.percentile(q, 5)), 3), round(float(np.percentile(q, 95)), 3)],
            'curvatures_per_km': [round(float(v) * 1e3, 3) for v in np.linalg.eigvalsh(H)]}


def best_shift(z, T, measured, peer: str, search_m: float) -> tuple[float, float]:
    """The horizontal move (m, east and north) of our DSM that minimises the median |dz - median dz| against
    the peer over the measured cells (grid search in 0.25 m steps)."""
    import rasterio
    best = (np.inf, 0.0, 0.0)
    for dx in np.arange(-search_m, search_m + 1e-9, 0.25):
        for dy in np.arange(-search_m, search_m + 1e-9, 0.25):
            med = peer_median(peer, rasterio.Affine(T.a, T.b, T.c + dx, T.d, T.e, T.f + dy), z.shape)
            both = measured & np.isfinite(med)
            if both.sum() < 100:
                continue
            d = z[both] - med[both]
            best = min(best, (float(np.median(np.abs(d - np.median(d)))), float(dx), float(dy)))
    return best[1], best[2]


def camera_heights(rows: list[dict], photos: str) -> dict:
    """Adjusted camera heights against the photos' EXIF altitudes (read as MSL, as the replay reads them)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.io.image_source import FolderSource
    from photogram_ros.io.photo_block import exif_position
    by_stamp = {int(t): p for p, t in FolderSource(photos).entries}
    est, ref = [], []
    for r in rows:
        p = by_stamp.get(int(r['stamp_ns']))
        g = exif_position(p) if p is not None else None
        if g is not None:
            est.append((float(r['lat_deg']), float(r['lon_deg']), float(r['h_ellipsoid_m'])))
            ref.append(g[:3])
    if len(est) < 7:
        return {'n': len(est)}
    est, ref = np.array(est), np.array(ref, float)
    o = LocalFrame(*ref.mean(axis=0))
    E, G = o.geodetic_to_enu(*est.T), o.geodetic_to_enu(*ref.T)
    dz = E[:, 2] - G[:, 2]
    e, n = E[:, 0] - E[:, 0].mean(), E[:, 1] - E[:, 1].mean()
    A = np.column_stack([np.ones_like(e), e, n, e * e, e * n, n * n])
    rq = dz - A @ np.linalg.lstsq(A, dz, rcond=None)[0]
    return {'n': len(est), 'exif_h_range_m': round(float(np.ptp(G[:, 2])), 2),
            'adjusted_h_range_m': round(float(np.ptp(E[:, 2])), 2),
            'rms_after_constant_m': round(float(np.std(dz)), 3),
            'rms_after_quadratic_m': round(float(np.sqrt(np.mean(rq ** 2))), 3)}


def _shape(e: np.ndarray, n: np.ndarray, dz: np.ndarray) -> dict:
    """dz's median |dz| after a constant (its median) and after a quadratic surface, with that surface's
    quadratic part (quadratic_part)."""
    dzq, _ = plane_residual(e, n, dz, degree=2)
    d0 = dz - np.median(dz)
    return {'n': int(dz.size), 'median_abs_after_constant_m': round(float(np.median(np.abs(d0))), 3),
            'median_abs_after_quadratic_m': round(float(np.median(np.abs(dzq))), 3),
            **quadratic_part(e, n, dz)}


def truth_shape(out: str, flight: str) -> dict:
    """The DSM's measured cells (band 2 >= 1) against the simulator's true DEM and the keyframe centres
    (trajectory.csv, matched by stamp) against the true cameras, heights in the truth's ENU: the shape of
    the block against truth (a bowl or dome: both curvatures of one sign)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from photogram_ros.io.flight_report import _raster_cells_enu
    from photogram_ros.sim.truth import GroundTruth
    truth = GroundTruth.load(flight)
    enu, pairs, _ = _raster_cells_enu(f'{out}/dsm.tif', truth.crs, truth.origin.geodetic_to_enu)
    m = pairs >= 1 if pairs is not None else np.ones(len(enu), bool)
    dz = enu[m, 2] - truth.dem.sample(enu[m, 0], enu[m, 1])
    ok = np.isfinite(dz)
    res = {'gsd_m': truth.gsd_m, 'dsm_measured': _shape(enu[m, 0][ok], enu[m, 1][ok], dz[ok])}
    est, true = [], []
    for r in csv.DictReader(open(f'{out}/trajectory.csv')):
        f = truth.frame_by_stamp(int(r['stamp_ns']), tol_ns=50_000_000)
        if f is not None:
            est.append(truth.origin.geodetic_to_enu(float(r['lat_deg']), float(r['lon_deg']),
                                                    float(r['h_ellipsoid_m'])))
            true.append(f.map_T_cam[:3, 3])
    if len(est) >= 7:
        E, T = np.array(est), np.array(true)
        res['cameras'] = _shape(T[:, 0], T[:, 1], E[:, 2] - T[:, 2])
    return res


def plane_residual(e: np.ndarray, n: np.ndarray, dz: np.ndarray, iters: int = 3,
                   degree: int = 1) -> tuple[np.ndarray, tuple]:
    """dz minus a plane a + b e + c n (degree 1; degree 2 adds e^2, e n, n^2: a bowl or dome) fitted by
    least absolute deviations (iteratively reweighted least squares): what is left of ours - peer once a
    tilted (or domed) georeference is taken out. Returns (residuals, (b, c) in m per m)."""
    e, n = e - e.mean(), n - n.mean()
    A = np.column_stack([np.ones_like(e), e, n] + ([e * e, e * n, n * n] if degree == 2 else []))
    w = np.ones_like(dz)
    for _ in range(iters + 1):
        coef = np.linalg.lstsq(A * w[:, None], dz * w, rcond=None)[0]
        r = dz - A @ coef
        w = 1.0 / np.sqrt(np.maximum(np.abs(r), 0.02))
    return r, (float(coef[1]), float(coef[2]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('outs', nargs='+')
    ap.add_argument('--peer', default=None, help='a peer\'s LAS/LAZ of the same photos, in the products\' CRS')
    ap.add_argument('--shift-m', type=float, default=0.0, help='search a horizontal move of our DSM against the '
                                                                'peer within +- this, m (0: none)')
    ap.add_argument('--photos', default=None, help='the replayed photo folder: camera heights against its EXIF')
    ap.add_argument('--truth', default=None, help='the simulated flight (ground_truth.json): shape against truth')
    a = ap.parse_args()
    for out in a.outs:
        rows = list(csv.DictReader(open(f'{out}/trajectory.csv')))
        e = [float(r['easting_m']) for r in rows]
        n = [float(r['northing_m']) for r in rows]
        with rasterio.open(f'{out}/dsm.tif') as ds:
            z, T, nod = ds.read(1).astype(float), ds.transform, ds.nodata
            pairs = ds.read(2) if ds.count > 1 else None
        valid = z != nod
        measured = valid & (pairs >= 1) if pairs is not None else valid
        h = hull(z.shape, T, e, n)
        res = {'out': out, 'dsm_valid_in_hull': float(valid[h].mean()), 'dsm_measured_in_hull': float(measured[h].mean()),
               'dsm_filled_in_hull': float((valid & ~measured)[h].mean())}
        with rasterio.open(f'{out}/ortho.tif') as ds:
            alpha, To = ds.read(4), ds.transform
        res['ortho_valid_in_hull'] = float((alpha > 0)[hull(alpha.shape, To, e, n)].mean())
        if a.photos:
            res['cameras_vs_exif_height'] = camera_heights(rows, a.photos)
        if a.truth:
            res['truth_shape'] = truth_shape(out, a.truth)
        if a.peer:
            if a.shift_m > 0:
                dx, dy = best_shift(z, T, measured, a.peer, a.shift_m)
                res['peer_shift_m'] = [dx, dy]
                T = rasterio.Affine(T.a, T.b, T.c + dx, T.d, T.e, T.f + dy)
            med = peer_median(a.peer, T, z.shape)
            for name, m in (('all', valid), ('measured', measured), ('filled', valid & ~measured),
                            ('all_in_hull', valid & h), ('measured_in_hull', measured & h)):
                both = m & np.isfinite(med)
                if not both.any():
                    continue
                dz = z[both] - med[both]
                dz -= np.median(dz)
                res[f'peer_{name}'] = {'cells': int(both.sum()), 'median_abs_m': round(float(np.median(np.abs(dz))), 3),
                                       'p90_abs_m': round(float(np.percentile(np.abs(dz), 90)), 3)}
                if name in ('measured', 'all'):
                    r_, c_ = np.nonzero(both)
                    e_, n_ = T * (c_ + 0.5, r_ + 0.5)
                    dzp, tilt = plane_residual(np.asarray(e_), np.asarray(n_), z[both] - med[both])
                    res[f'peer_{name}_plane'] = {'median_abs_m': round(float(np.median(np.abs(dzp))), 3),
                                                 'p90_abs_m': round(float(np.percentile(np.abs(dzp), 90)), 3),
                                                 'tilt_e_mm_per_m': round(tilt[0] * 1e3, 2),
                                                 'tilt_n_mm_per_m': round(tilt[1] * 1e3, 2)}
                    dzq, _ = plane_residual(np.asarray(e_), np.asarray(n_), z[both] - med[both], degree=2)
                    res[f'peer_{name}_quadratic'] = {'median_abs_m': round(float(np.median(np.abs(dzq))), 3),
                                                     'p90_abs_m': round(float(np.percentile(np.abs(dzq), 90)), 3),
                                                     **quadratic_part(np.asarray(e_), np.asarray(n_),
                                                                      z[both] - med[both])}
        print(json.dumps(res))
    return 0


if __name__ == '__main__':
    sys.exit(main())
