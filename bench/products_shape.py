"""The shape of a block on a real photo survey: its ground against OpenDroneMap's cloud and its cameras against
the photos' EXIF altitudes, each split into a constant, a plane and a quadratic part (a bowl or a dome).

For each output folder (a `replay` OUT with dsm.tif and trajectory.csv, or a `triangulate` OUT with sparse.las
and poses.csv):
- ground: the DSM's measured cells (band 2 >= 1) or the sparse cloud's points against ODM's odm_model.laz
  gridded at 0.2 m (median per cell), after ODM's best horizontal offset (bench/real_surveys.odm_agreement):
  median |dz| after a constant, after a plane and after a quadratic surface (least absolute deviations), the
  quadratic part's spread (5th..95th percentile over the points, m) and its curvatures (1/km; both positive:
  ours a bowl against ODM);
- cameras: adjusted camera heights minus the EXIF altitudes (read as MSL, as the pipelines read them), the same
  split: a block whose cameras dome against a level flight's altitudes bends, whatever its ground does;
- `bowl_30m_m`: the quadratic part's value 30 m from the points' centre along its mean curvature, minus its
  value at the centre (the figure the notes quote), for ground and cameras alike.
- with two folders given as `--pair A B`: A's ground against B's (e.g. replay's DSM against triangulate's
  sparse cloud of the same photos), B gridded as ODM is.

    .venv/bin/python bench/products_shape.py OUT [OUT ...] [--photos ../shared/data/photos/brighton_beach/images]
        [--pair REPLAY_OUT TRIANGULATE_OUT] [--no-odm] [--pycolmap]
Prints one JSON line per folder (and per pair).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import real_surveys as rs  # noqa: E402

BRIGHTON_PHOTOS = rs.BRIGHTON / 'images'


def fit(e: np.ndarray, n: np.ndarray, dz: np.ndarray, degree: int, iters: int = 4) -> np.ndarray:
    """Coefficients of a surface of `degree` (0, 1, 2) in (e, n) fitted to dz by least absolute deviations."""
    cols = [np.ones_like(e)] + ([e, n] if degree >= 1 else []) + ([e * e, e * n, n * n] if degree >= 2 else [])
    A = np.column_stack(cols)
    w = np.ones_like(dz)
    for _ in range(iters):
        coef = np.linalg.lstsq(A * w[:, None], dz * w, rcond=None)[0]
        w = 1.0 / np.sqrt(np.maximum(np.abs(dz - A @ coef), 0.02))
    return coef


def shape(e: np.ndarray, n: np.ndarray, dz: np.ndarray) -> dict:
    """dz's split: median |dz| after a constant, a plane and a quadratic; the quadratic part's spread, its
    curvatures (1/km) and its rise 30 m from the centre along the mean curvature (m)."""
    e, n = e - e.mean(), n - n.mean()
    out = {'n': int(dz.size)}
    for deg, name in ((0, 'constant'), (1, 'plane'), (2, 'quadratic')):
        c = fit(e, n, dz, deg)
        A = np.column_stack([np.ones_like(e)] + ([e, n] if deg >= 1 else []) +
                            ([e * e, e * n, n * n] if deg >= 2 else []))
        out[f'median_abs_after_{name}_m'] = round(float(np.median(np.abs(dz - A @ c))), 3)
    q = np.column_stack([e * e, e * n, n * n]) @ c[3:]
    H = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    k = np.linalg.eigvalsh(H)
    out['quadratic_p5_p95_m'] = [round(float(np.percentile(q, 5)), 3), round(float(np.percentile(q, 95)), 3)]
    out['curvatures_per_km'] = [round(float(v) * 1e3, 3) for v in k]
    out['bowl_30m_m'] = round(float(0.5 * k.mean() * 30.0 ** 2), 3)
    return out


def ground_points(out: Path) -> tuple[np.ndarray, str]:
    """(N, 3) EPSG:32615 points of a folder's surface: the DSM's measured cells or the sparse cloud."""
    if (out / 'dsm.tif').exists():
        import rasterio
        with rasterio.open(out / 'dsm.tif') as ds:
            z, T, nod = ds.read(1).astype(float), ds.transform, ds.nodata
            pairs = ds.read(2) if ds.count > 1 else np.ones(z.shape)
            crs = ds.crs.to_string() if ds.crs else ''
        j, i = np.nonzero((z != nod) & np.isfinite(z) & (pairs >= 1))
        x, y = T * (i + 0.5, j + 0.5)
        return rs.to_crs(np.column_stack([x, y, z[j, i]]), crs), 'dsm measured cells'
    P, crs = rs.sparse_points(out / 'sparse.las')
    return rs.to_crs(P, crs), 'sparse cloud'


def against_grid(P: np.ndarray, grid, x0, y0, cell, offset) -> dict:
    jx = ((P[:, 0] + offset[0] - x0) / cell).astype(int)
    jy = ((P[:, 1] + offset[1] - y0) / cell).astype(int)
    ok = (jx >= 0) & (jx < grid.shape[1]) & (jy >= 0) & (jy < grid.shape[0])
    d = np.full(len(P), np.nan)
    d[ok] = P[ok, 2] - grid[jy[ok], jx[ok]]
    m = np.isfinite(d)
    return shape(P[m, 0], P[m, 1], d[m])


def grid_of(P: np.ndarray, cell: float = 0.2):
    x0, y0 = P[:, 0].min(), P[:, 1].min()
    ix, iy = ((P[:, 0] - x0) / cell).astype(int), ((P[:, 1] - y0) / cell).astype(int)
    w = ix.max() + 1
    key = iy * w + ix
    order = np.lexsort((P[:, 2], key))
    u, first, cnt = np.unique(key[order], return_index=True, return_counts=True)
    grid = np.full((iy.max() + 1) * w, np.nan)
    grid[u] = P[order, 2][first + cnt // 2]
    return grid.reshape(-1, w), x0, y0, cell


def cameras(out: Path, photos: Path) -> dict:
    """Adjusted camera heights against the EXIF altitudes, in a local ENU frame."""
    from photogram_ros.core.geodesy import LocalFrame
    poses = rs.read_poses(out / ('poses.csv' if (out / 'poses.csv').exists() else 'trajectory.csv'))
    ref = rs.exif_reference(photos)
    if any('stamp_ns' in p for p in poses.values()):
        names = rs.photo_stamps(photos)
        poses = {names[p['stamp_ns']]: p for p in poses.values() if p.get('stamp_ns') in names}
    both = [k for k in poses if k in ref]
    if len(both) < 7:
        return {'n': len(both)}
    est = np.array([(poses[k]['lat_deg'], poses[k]['lon_deg'], poses[k]['h_m']) for k in both])
    gt = np.array([ref[k] for k in both], float)
    o = LocalFrame(*gt.mean(axis=0))
    E, G = o.geodetic_to_enu(*est.T), o.geodetic_to_enu(*gt.T)
    return {'exif_h_range_m': round(float(np.ptp(G[:, 2])), 2), **shape(G[:, 0], G[:, 1], E[:, 2] - G[:, 2])}


def pycolmap_cameras() -> dict:
    """{variant: shape of pycolmap's vertical residuals (aligned camera - EXIF) over the EXIF positions} for
    toledo's peer_pycolmap.json."""
    from photogram_ros.core.geodesy import LocalFrame
    ref = rs.exif_reference(rs.TOLEDO / 'images')
    G = np.array(list(ref.values()), float)
    o = LocalFrame(*G.mean(axis=0))
    enu = {k: o.geodetic_to_enu(*np.array(v, float)) for k, v in ref.items()}
    out = {}
    for name, v in json.loads((rs.TOLEDO / 'peer_pycolmap.json').read_text())['variants'].items():
        r = v.get('per_image_residual_enu_m') or {}
        ks = [k for k in r if k in enu]
        if len(ks) >= 7:
            E, R = np.array([enu[k] for k in ks]), np.array([r[k] for k in ks], float)
            out[name] = shape(E[:, 0], E[:, 1], R[:, 2])
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('outs', nargs='*')
    ap.add_argument('--photos', default=str(BRIGHTON_PHOTOS))
    ap.add_argument('--pair', nargs=2, action='append', default=[], metavar=('A', 'B'))
    ap.add_argument('--no-odm', action='store_true', help='cameras only (a survey without ODM\'s cloud: toledo)')
    ap.add_argument('--pycolmap', action='store_true', help='also pycolmap\'s toledo cameras against the EXIF '
                                                             '(peer_pycolmap.json: its residuals after its similarity)')
    a = ap.parse_args()
    if a.pycolmap:
        for name, shp in pycolmap_cameras().items():
            print(json.dumps({'peer': f'pycolmap {name}', 'cameras_vs_exif': shp}))
    odm = None if a.no_odm else rs.odm_grid()
    for out in map(Path, a.outs):
        if odm is None:
            print(json.dumps({'out': str(out), 'cameras_vs_exif': cameras(out, Path(a.photos))}))
            continue
        P, what = ground_points(out)
        agree = rs.odm_agreement(P)
        res = {'out': str(out), 'ground': what, 'odm_offset_m': agree.get('offset_m'),
               'ground_vs_odm': against_grid(P, *odm, agree['offset_m'][:2]),
               'cameras_vs_exif': cameras(out, Path(a.photos))}
        print(json.dumps(res))
    for A, B in a.pair:
        PA, wa = ground_points(Path(A))
        PB, wb = ground_points(Path(B))
        g = grid_of(PB)
        # B's best horizontal offset to A: both against ODM's.
        oa, ob = rs.odm_agreement(PA)['offset_m'], rs.odm_agreement(PB)['offset_m']
        res = {'a': A, 'b': B, 'a_ground': wa, 'b_ground': wb,
               'a_vs_b': against_grid(PA, *g, [oa[0] - ob[0], oa[1] - ob[1]])}
        print(json.dumps(res))
    return 0


if __name__ == '__main__':
    sys.exit(main())
