"""The flight report's overview, as OpenDroneMap's report gives it: when the photos were taken, the area the
products cover and the GSD, a DSM preview, the GNSS residual of each photo and the camera calibration before
and after the adjustment (io/flight_report.py puts them in the report).

Inputs are what the user receives (dsm.tif, export.json) and the map folder (keyframes, camera.json, and
io/flight_inputs.py's keyframe fixes and input calibration where the flight kept them).
"""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from photogram_ros.io.report import Section, series_png

CALIBRATION_KEYS = ('fx_px', 'fy_px', 'cx_px', 'cy_px', 'k1', 'k2', 'p1', 'p2', 'k3')


def utc_text(stamp_ns: int) -> str:
    return datetime.fromtimestamp(stamp_ns / 1e9, tz=timezone.utc).strftime('%Y-%m-%d %H:%M:%S UTC')


def capture_span(kfs: list[dict]) -> dict:
    """First and last keyframe stamps (the photos' capture times), the span and the count."""
    stamps = sorted(int(k['stamp_ns']) for k in kfs)
    if not stamps:
        return {}
    return {'first_utc': utc_text(stamps[0]), 'last_utc': utc_text(stamps[-1]),
            'duration_s': (stamps[-1] - stamps[0]) / 1e9, 'photos': len(stamps),
            'date': utc_text(stamps[0])[:10]}


def product_heights(out: Path) -> str:
    """'ellipsoidal' or 'orthometric': what export.json says the rasters hold ('ellipsoidal' without one)."""
    try:
        return json.loads((out / 'export.json').read_text()).get('heights') or 'ellipsoidal'
    except (OSError, ValueError):
        return 'ellipsoidal'


def dsm_area(dsm_path) -> dict:
    """{'area_m2', 'cells', 'res_m', 'measured_area_m2', 'ground_median'}: the DSM's cells holding a height
    (band 2 >= 1: measured by stereo), {} without a DSM."""
    if not dsm_path or not Path(dsm_path).exists():
        return {}
    import rasterio
    with rasterio.open(dsm_path) as ds:
        z = ds.read(1, masked=True)
        pairs = ds.read(2) if ds.count >= 2 else None
        res = abs(float(ds.res[0])) * abs(float(ds.res[1]))
    valid = ~np.ma.getmaskarray(z) & np.isfinite(np.ma.getdata(z))
    out = {'cells': int(valid.sum()), 'res_m': float(np.sqrt(res)), 'area_m2': float(valid.sum() * res)}
    if pairs is not None:
        out['measured_area_m2'] = float(np.sum(valid & (pairs >= 1)) * res)
    if valid.any():
        out['ground_median'] = float(np.median(np.ma.getdata(z)[valid]))
    return out


def hull_area_m2(easting, northing) -> float:
    """Area of the convex hull of the camera centres (m^2)."""
    import cv2
    pts = np.column_stack([easting, northing]).astype(np.float64)
    if len(pts) < 3:
        return 0.0
    hull = cv2.convexHull((pts - pts.mean(axis=0)).astype(np.float32))
    return float(cv2.contourArea(hull))


def gsd_m(run: dict, kfs: list[dict], cam, origin, area: dict, heights: str) -> tuple[float | None, str]:
    """(GSD in m, how it was found): the one densify derived (run['gsd']), else the median camera height above
    the DSM's median height divided by the focal length."""
    g = (run or {}).get('gsd') or {}
    if g.get('gsd_m'):
        return float(g['gsd_m']), (f"camera {g.get('width_px')}x{g.get('height_px')} px, f {g.get('focal_px', 0):.0f} "
                                   f"px, {g.get('flying_height_m', 0):.0f} m above the ground")
    if cam is None or not kfs or 'ground_median' not in area:
        return None, ''
    C = np.array([k['map_T_cam'][:3, 3] for k in kfs])
    lat, lon, h = origin.enu_to_geodetic(C)
    if heights == 'orthometric':
        from photogram_ros.core import geoid
        h = geoid.ellipsoid_to_msl_m(lat, lon, h)
    above = float(np.median(np.asarray(h) - area['ground_median']))
    if above <= 0:
        return None, ''
    return above / cam.fx, f'{above:.0f} m above the DSM\'s median height, f {cam.fx:.0f} px'


def capture_section(out: Path, kfs: list[dict], cam, origin, files: dict, run: dict, traj: dict,
                    figures: dict) -> Section:
    """When, how much ground, at what GSD (also into figures['capture'])."""
    span = capture_span(kfs)
    area = dsm_area(files.get('dsm'))
    heights = product_heights(out)
    g, how = gsd_m(run, kfs, cam, origin, area, heights)
    hull = hull_area_m2(traj.get('easting', []), traj.get('northing', [])) if traj else 0.0
    figures['capture'] = {**span, 'area_m2': area.get('area_m2'), 'measured_area_m2': area.get('measured_area_m2'),
                          'camera_hull_m2': hull, 'gsd_m': g, 'heights': heights}
    text = []
    if span:
        text.append(f"Captured on {span['date']} from {span['first_utc'][11:]} to {span['last_utc'][11:]} "
                    f"({span['duration_s']:.0f} s, {span['photos']} keyframe photos; the keyframes' stamps).")
    if area:
        text.append(f"Area covered by the DSM: {area['area_m2']:.0f} m^2 ({area['area_m2'] / 1e4:.2f} ha)"
                    + (f", of it measured by stereo {area['measured_area_m2']:.0f} m^2"
                       if 'measured_area_m2' in area else '')
                    + f"; the camera centres span {hull:.0f} m^2 ({hull / 1e4:.2f} ha).")
    else:
        text.append('No DSM: the area covered is not known.')
    text.append(f'GSD {g * 100:.2f} cm ({how}).' if g else 'GSD: not known (no DSM and no densify settings).')
    return Section('Capture and coverage', text)


def dsm_preview_png(path: Path, dsm_path, crs: str, heights: str, max_px: int = 1000) -> Path | None:
    """The DSM as colour over its hillshade, heights in metres on a colour bar; None without a DSM."""
    if not dsm_path or not Path(dsm_path).exists():
        return None
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    import rasterio
    with rasterio.open(dsm_path) as ds:
        step = max(1, int(np.ceil(max(ds.width, ds.height) / max_px)))
        z = ds.read(1, out_shape=(ds.height // step or 1, ds.width // step or 1), masked=True).astype(float)
        b = ds.bounds
        res = abs(ds.res[0]) * step
    data = np.ma.filled(z, np.nan)
    valid = np.isfinite(data)
    if not valid.any():
        return None
    lo, hi = np.percentile(data[valid], [1, 99])
    filled = np.where(valid, data, np.nanmedian(data))
    gy, gx = np.gradient(filled, res)
    slope = np.arctan(np.hypot(gx, gy))
    aspect = np.arctan2(-gx, gy)
    az, alt = np.radians(315.0), np.radians(45.0)
    shade = np.clip(np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect), 0, 1)
    cmap = plt.get_cmap('terrain')
    rgb = cmap(np.clip((filled - lo) / max(hi - lo, 1e-6), 0, 1))[..., :3] * (0.45 + 0.55 * shade[..., None])
    rgba = np.dstack([rgb, valid.astype(float)])
    fig, ax = plt.subplots(figsize=(7, 6), dpi=100)
    ax.imshow(rgba, extent=(b.left, b.right, b.bottom, b.top), interpolation='nearest')
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(lo, hi))
    fig.colorbar(sm, ax=ax, label=f'height, m ({heights})')
    ax.set_aspect('equal')
    ax.ticklabel_format(useOffset=False, style='plain')
    ax.tick_params(labelsize=7)
    ax.set_title(f'DSM ({crs})')
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def gnss_section(out: Path, kfs: list[dict], origin, fixes: dict, figures: dict) -> Section:
    """Adjusted camera centre minus the keyframe's GNSS fix, per photo (E, N, U in metres): a plot, a table and
    the RMS (also figures['gnss_residuals']). The fixes are the antenna's: a lever arm shows as an offset."""
    sec = Section('GNSS residuals per photo')
    rows, res = [], []
    for i, k in enumerate(kfs):
        f = fixes.get(int(k['stamp_ns']))
        if f is None:
            continue
        d = np.asarray(k['map_T_cam'][:3, 3], float) - np.asarray(
            origin.geodetic_to_enu(f['lat_deg'], f['lon_deg'], f['h_m']), float).reshape(3)
        res.append(d)
        rows.append({'photo': Path(k['image_path']).name, 'index': i, 'dE_m': float(d[0]), 'dN_m': float(d[1]),
                     'dU_m': float(d[2]), 'fix_status': int(f['status'])})
    if not rows:
        sec.text.append('The map folder keeps no keyframe fixes (keyframe_fixes.jsonl): the residual of each '
                        'photo against its GNSS fix is not known for this flight.')
        figures['gnss_residuals'] = None
        return sec
    r = np.array(res)
    rms = {'horizontal_m': float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1)))),
           'vertical_m': float(np.sqrt(np.mean(r[:, 2] ** 2))), 'photos': len(rows),
           'mean_enu_m': r.mean(axis=0).tolist()}
    figures['gnss_residuals'] = {'rms': rms, 'photos': rows}
    sec.text.append(f"{len(rows)} of {len(kfs)} photos have a fix: RMS horizontal {rms['horizontal_m'] * 100:.1f} "
                    f"cm, vertical {rms['vertical_m'] * 100:.1f} cm; mean (E, N, U) "
                    + ', '.join(f'{v * 100:+.1f}' for v in rms['mean_enu_m'])
                    + ' cm (adjusted camera centre minus fix: a lever arm between antenna and camera, or a GNSS '
                    'bias, shows as this offset).')
    series_png(out / 'gnss_residuals.png', [row['index'] for row in rows],
               {'E': r[:, 0], 'N': r[:, 1], 'U': r[:, 2]}, 'photo (keyframe order)', 'm',
               'Adjusted camera centre - GNSS fix')
    sec.figures.append(('Residual of each photo against its GNSS fix', 'gnss_residuals.png'))
    sec.tables.append(('Per photo, m', rows))
    return sec


def camera_row(cam) -> dict:
    row = {'width_px': cam.width, 'height_px': cam.height, 'fx_px': round(cam.fx, 2), 'fy_px': round(cam.fy, 2),
           'cx_px': round(cam.cx, 2), 'cy_px': round(cam.cy, 2)}
    row.update({k: float(f'{v:.5g}') for k, v in zip(('k1', 'k2', 'p1', 'p2', 'k3'), cam.dist)})
    return row


def calibration_rows(before, after) -> list[dict]:
    """Rows 'before' (the input calibration), 'after' (the products' camera) and 'change' (after - before)."""
    rows = []
    if before is not None:
        rows.append({'camera': 'before (input calibration)', **camera_row(before)})
    rows.append({'camera': 'after (the products\' camera)', **camera_row(after)})
    if before is not None:
        b, a = camera_row(before), camera_row(after)
        rows.append({'camera': 'change (after - before)', 'width_px': None, 'height_px': None,
                     **{k: float(f'{a[k] - b[k]:.5g}') for k in CALIBRATION_KEYS}})
    return rows


def place_labels(fig, ax, xy: list, texts: list, fontsize: int = 7, colour: str = 'black') -> list:
    """Annotate each point with its text where the label overlaps no label placed before nor another marker
    and stays inside the axes, trying offsets around the point, nearest first (else the place with the fewest
    clashes); returns the labels' display boxes."""
    from matplotlib.transforms import Bbox
    offsets = [(4, 4), (4, -12), (-4, 4), (-4, -12), (4, 14), (-4, 14), (4, -22), (-4, -22), (10, 24),
               (-10, 24), (10, -32), (-10, -32), (20, 36), (-20, 36), (20, -44), (-20, -44)]
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    markers = [Bbox.from_bounds(*(ax.transData.transform(p) - 3), 6, 6) for p in xy]
    placed: list = []
    for k, (p, text) in enumerate(zip(xy, texts)):
        best = None
        for dx, dy in offsets:
            ann = ax.annotate(text, p, xytext=(dx, dy), textcoords='offset points', fontsize=fontsize, color=colour,
                              ha='left' if dx >= 0 else 'right', va='bottom',
                              arrowprops=dict(arrowstyle='-', color=colour, lw=0.4) if abs(dy) > 14 else None)
            box = ann.get_window_extent(renderer).expanded(1.02, 1.05)
            inside = (frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1)
            clashes = (sum(box.overlaps(o) for o in placed) + sum(box.overlaps(m) for j, m in enumerate(markers)
                                                                   if j != k) + (not inside))
            if best is None or clashes < best[0]:
                if best is not None:
                    best[1].remove()
                best = (clashes, ann, box)
            else:
                ann.remove()
            if clashes == 0:
                break
        placed.append(best[2])
    return placed
