"""OpenDroneMap's geo.txt, the positions file beside a folder of photos (a PPK `geotag`'s, or any survey tool's).

`geo_txt_fixes` reads it into core.gnss_fix.GnssFix per image (io/image_source.py: a folder played as a camera);
`read_geo_txt` gives the same as tuples (io/photo_block.py, `triangulate FOLDER`); io/geotag.py writes the file.
Nothing of the photos themselves is read here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from photogram_ros.core import gnss_fix as gf
from photogram_ros.core.geodesy import crs_to_geodetic
from photogram_ros.errors import DataError

# Sigmas of an EXIF geotag (a consumer GNSS), and of a geo.txt line without accuracies. The heights
# of one flight agree far better than their absolute error (DJI writes a barometric-fused altitude:
# decimetres over a flight); a 10 m sigma let a near-nadir block bend its cameras by 0.4 m into a
# dome that trades with the lens's k1 (brighton_beach: k1 0.013-0.017 from run to run, the GNSS
# heights then 0.4 m off; with 2 m: k1 -0.0005, heights within 0.19 m, the same from 0.5 to 2 m).
EXIF_SIGMA_H_M = 5.0
EXIF_SIGMA_V_M = 2.0


def geo_txt_fixes(path: str | Path) -> dict[str, gf.GnssFix]:
    """OpenDroneMap geo.txt -> {image name: GnssFix} (WGS84, ellipsoidal height, no time of its own).

    First line a CRS, then ``image x y z [omega phi kappa] [h_acc v_acc]`` (geographic: x = longitude); h_acc is
    the per-axis horizontal 1-sigma, v_acc the vertical one (at least 1 mm; without them EXIF_SIGMA_H_M /
    EXIF_SIGMA_V_M), the covariance diagonal and known; the quality a single solution's (geo.txt has none).
    """
    path = Path(path)
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith('#')]
    if not lines:
        raise DataError(f'{path} is empty')
    crs = ' '.join(lines[0])
    out = {}
    for ln in lines[1:]:
        if len(ln) < 4:
            raise DataError(f'{path}: line {" ".join(ln)!r} needs: image x y z [omega phi kappa] [h_acc v_acc]')
        x, y, z = (float(v) for v in ln[1:4])
        if crs.upper() in ('EPSG:4326', 'WGS84', 'EPSG:4979'):
            lat, lon, h = y, x, z
        else:
            lat, lon, h = (float(v) for v in crs_to_geodetic(x, y, z, crs))
        h_acc = max(float(ln[7]) if len(ln) >= 9 else EXIF_SIGMA_H_M, 1e-3)
        v_acc = max(float(ln[8]) if len(ln) >= 9 else EXIF_SIGMA_V_M, 1e-3)
        out[ln[0]] = gf.GnssFix(lat, lon, h, np.diag([h_acc ** 2, h_acc ** 2, v_acc ** 2]),
                                cov_type=gf.COV_DIAGONAL_KNOWN, quality=gf.Q_SINGLE, source='geo.txt')
    return out


def read_geo_txt(path: str | Path) -> dict[str, tuple[float, float, float, float, float]]:
    """OpenDroneMap geo.txt -> {image name: (lat_deg, lon_deg, h_m ellipsoidal, h_acc_m, v_acc_m)}: `geo_txt_fixes`
    as tuples (h_acc the per-axis horizontal 1-sigma, v_acc the vertical one)."""
    out = {}
    for name, f in geo_txt_fixes(path).items():
        _, sn, su = (float(v) for v in f.sigma_enu_m)
        out[name] = (f.lat_deg, f.lon_deg, f.h_m, sn, su)
    return out
