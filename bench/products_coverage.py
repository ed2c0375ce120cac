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
quadratic surface (a bowl: what an unmodelled lens distortion gives a block).
Prints one JSON line per folder.

    .venv/bin/python bench/products_coverage.py OUT [OUT ...] [--peer ../shared/data/photos/brighton_beach/odm_model.laz]
"""

from __future__ import annotations

import argparse
import csv
import json
import sys

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
        if a.peer:
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
                                                     'p90_abs_m': round(float(np.percentile(np.abs(dzq), 90)), 3)}
        print(json.dumps(res))
    return 0


if __name__ == '__main__':
    sys.exit(main())
