"""OpenDroneMap's geo.txt, the positions file beside a folder of photos (a PPK `geotag`'s, or any survey tool's).

`read_geo_txt` is read by io/image_source.py (a folder played as a camera) and io/photo_block.py (`triangulate
FOLDER`); io/geotag.py writes the file. Nothing of the photos themselves is read here.
"""

from __future__ import annotations

from pathlib import Path

from photogram_ros.core.geodesy import crs_to_geodetic
from photogram_ros.errors import DataError

# Sigmas of an EXIF geotag (a consumer GNSS), and of a geo.txt line without accuracies. The heights
# of one flight agree far better than their absolute error (DJI writes a barometric-fused altitude:
# decimetres over a flight); a 10 m sigma let a near-nadir block bend its cameras by 0.4 m into a
# dome that trades with the lens's k1 (brighton_beach: k1 0.013-0.017 from run to run, the GNSS
# heights then 0.4 m off; with 2 m: k1 -0.0005, heights within 0.19 m, the same from 0.5 to 2 m).
EXIF_SIGMA_H_M = 5.0
EXIF_SIGMA_V_M = 2.0


def read_geo_txt(path: str | Path) -> dict[str, tuple[float, float, float, float, float]]:
    """OpenDroneMap geo.txt -> {image name: (lat_deg, lon_deg, h_m ellipsoidal, h_acc_m, v_acc_m)}.

    First line a CRS, then ``image x y z [omega phi kappa] [h_acc v_acc]`` (geographic: x = longitude).
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
        h_acc = float(ln[7]) if len(ln) >= 9 else EXIF_SIGMA_H_M
        v_acc = float(ln[8]) if len(ln) >= 9 else EXIF_SIGMA_V_M
        out[ln[0]] = (lat, lon, h, max(h_acc, 1e-3), max(v_acc, 1e-3))
    return out
