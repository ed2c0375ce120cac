"""Camera intrinsics from a photo's EXIF, for users who have photos but no calibration.

`intrinsics_from_exif(tags)` gives a `PinholeCamera` (focal length in pixels, principal point at
the image centre, distortion zero) and says which source it came from; the first that applies wins:

1. `xmp`: a DJI XMP `CalibratedFocalLength` (and `CalibratedOpticalCenterX/Y`), in pixels, which
   newer DJI cameras write from their factory calibration;
2. `focal_plane`: EXIF FocalLength (mm) times FocalPlaneXResolution (pixels per mm of the focal
   plane), when the sensor width that implies is plausible (1-60 mm) and agrees with the table
   below for a known model (some cameras state it for the full sensor, not the saved size);
3. `sensor_table`: FocalLength (mm) / sensor width (mm) x image width (px), with the sensor
   width of the camera model from `SENSOR_WIDTH_MM`. A frame cropped to 16:9 or 3:2 from a 4:3
   sensor keeps the sensor's full width (DJI, Parrot, most compacts), so the width still spans it;
4. `35mm`: FocalLengthIn35mmFilm (mm), an equivalent focal by the diagonal (CIPA DC-008: a
   43.27 mm diagonal): f_px = f35 / 43.27 x the frame's diagonal in pixels. The equivalent is
   stated for the sensor's full frame, so a frame wider than 4:3 (16:9, 3:2 cut from a 4:3 sensor)
   is taken as its full-width 4:3 frame: diagonal = 1.25 x width.

Accuracy: a table or EXIF focal is good to a few per cent (lens focus breathing, rounding of the
35 mm figure); the zero distortion is the larger approximation for wide drone lenses. Both are
stated in the report's assumptions; `--self-calibrate k1,k2` refines the distortion.

The sensor widths are from OpenSfM's sensor database (opensfm/data/sensor_data.json, mapillary/
OpenSfM, BSD-2-Clause; itself from digicamdb.com), keyed here by EXIF Make and Model as the cameras
write them (lowercase, "make model").
"""

from __future__ import annotations

from dataclasses import dataclass

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.errors import CalibrationError

# mm, from OpenSfM's sensor_data.json (see the module docstring).
SENSOR_WIDTH_MM: dict[str, float] = {
    'dji fc200': 6.17,         # Phantom 2 Vision ('DJI PHANTOM VISION FC200')
    'dji fc300s': 6.16,        # Phantom 3 Professional / Advanced
    'dji fc300c': 6.31,        # Phantom 3 Standard
    'dji fc300x': 6.2,         # Phantom 3 4K
    'dji fc330': 6.25,         # Phantom 4
    'dji fc350': 6.17,         # Inspire 1 (Zenmuse X3)
    'dji fc350z': 6.17,        # Inspire 1 (Zenmuse Z3)
    'dji fc220': 6.17,         # Mavic Pro
    'dji fc2103': 6.07,        # Mavic Air
    'dji fc6310': 13.2,        # Phantom 4 Pro
    'gopro hero4 black': 6.17,
    'gopro hero4 silver': 6.17,
    'canon powershot s100': 7.53,      # fixed-wing survey cameras (eBee)
    'canon powershot s110': 7.53,
    'canon powershot s120': 7.53,
    'canon powershot elph 110 hs': 6.16,
    'canon powershot g9 x': 13.2,
    'sony dsc-rx100': 13.2,
    'sony dsc-wx220': 6.16,
    'sony ilce-5100': 23.5,
    'sony ilce-6000': 23.5,            # 'Sony Alpha a6000'
    'sony ilce-qx1': 23.5,             # 'Sony QX1'
}
DIAGONAL_35MM_MM = 43.27            # 36 x 24 mm
MIN_SENSOR_MM, MAX_SENSOR_MM = 1.0, 60.0
FOCAL_PLANE_AGREEMENT = 0.05        # focal-plane sensor width vs the table's, relative


@dataclass(frozen=True)
class ExifCameraTags:
    """What a photo's EXIF (and DJI XMP) says about its camera; None where absent."""
    width_px: int
    height_px: int
    make: str = ''
    model: str = ''
    focal_mm: float | None = None               # FocalLength
    focal_35mm: float | None = None             # FocalLengthIn35mmFilm
    focal_plane_px_per_mm: float | None = None  # FocalPlaneXResolution in pixels per mm
    xmp_focal_px: float | None = None           # DJI XMP CalibratedFocalLength
    xmp_cx_px: float | None = None              # DJI XMP CalibratedOpticalCenterX
    xmp_cy_px: float | None = None

    @property
    def sensor_key(self) -> str:
        make = self.make.strip().lower()
        model = self.model.strip().lower()
        return model if make and model.startswith(make) else f'{make} {model}'.strip()


@dataclass(frozen=True)
class ExifIntrinsics:
    camera: PinholeCamera
    source: str             # 'xmp' | 'focal_plane' | 'sensor_table' | '35mm'
    note: str               # how it was computed, for the report's assumptions


def sensor_width_mm(tags: ExifCameraTags) -> float | None:
    return SENSOR_WIDTH_MM.get(tags.sensor_key)


def _camera(tags: ExifCameraTags, f_px: float, cx=None, cy=None) -> PinholeCamera:
    w, h = int(tags.width_px), int(tags.height_px)
    # Principal point at the centre (pixel centres at integers).
    return PinholeCamera(w, h, float(f_px), float(f_px), (w - 1) / 2.0 if cx is None else float(cx),
                         (h - 1) / 2.0 if cy is None else float(cy))


def intrinsics_from_exif(tags: ExifCameraTags) -> ExifIntrinsics:
    """The camera of a photo from its tags (see the module docstring); CalibrationError without any
    usable focal length."""
    w, h = int(tags.width_px), int(tags.height_px)
    long_px = max(w, h)
    name = f'{tags.make.strip()} {tags.model.strip()}'.strip() or 'unknown camera'
    base = 'principal point at the image centre, distortion zero'
    if tags.xmp_focal_px and tags.xmp_focal_px > 0:
        cam = _camera(tags, tags.xmp_focal_px, tags.xmp_cx_px, tags.xmp_cy_px)
        return ExifIntrinsics(cam, 'xmp', f'{name}: focal {tags.xmp_focal_px:.1f} px from the DJI XMP '
                                          f'CalibratedFocalLength; distortion zero')
    table = sensor_width_mm(tags)
    f_mm = tags.focal_mm if tags.focal_mm and tags.focal_mm > 0 else None
    if f_mm and tags.focal_plane_px_per_mm and tags.focal_plane_px_per_mm > 0:
        sensor = long_px / tags.focal_plane_px_per_mm     # the long side along the sensor's x
        plausible = MIN_SENSOR_MM <= sensor <= MAX_SENSOR_MM
        agrees = table is None or abs(sensor / table - 1.0) <= FOCAL_PLANE_AGREEMENT
        if plausible and agrees:
            f_px = f_mm * tags.focal_plane_px_per_mm
            return ExifIntrinsics(_camera(tags, f_px), 'focal_plane',
                                  f'{name}: focal {f_px:.1f} px = FocalLength {f_mm:g} mm x FocalPlaneXResolution '
                                  f'{tags.focal_plane_px_per_mm:.2f} px/mm; {base}')
    if f_mm and table:
        f_px = f_mm / table * long_px
        return ExifIntrinsics(_camera(tags, f_px), 'sensor_table',
                              f'{name}: focal {f_px:.1f} px = FocalLength {f_mm:g} mm / sensor width {table:g} mm '
                              f'(OpenSfM sensor table) x {long_px} px (the long side spanning the sensor width); '
                              f'{base}')
    if tags.focal_35mm and tags.focal_35mm > 0:
        aspect = long_px / max(min(w, h), 1)
        # Wider than 4:3 (16:9, 3:2): a crop of a 4:3 sensor keeping its width.
        diag_px = 1.25 * long_px if aspect > 4.0 / 3.0 + 0.02 else float((w * w + h * h) ** 0.5)
        f_px = tags.focal_35mm / DIAGONAL_35MM_MM * diag_px
        crop = ' (the frame taken as a crop of a full-width 4:3 sensor)' if aspect > 4.0 / 3.0 + 0.02 else ''
        return ExifIntrinsics(_camera(tags, f_px), '35mm',
                              f'{name}: focal {f_px:.1f} px from FocalLengthIn35mmFilm {tags.focal_35mm:g} mm by the '
                              f'diagonal{crop}; {base}')
    raise CalibrationError(f'{name}: the EXIF has no usable focal length (FocalLength with FocalPlaneXResolution '
                           'or a known sensor, or FocalLengthIn35mmFilm): pass --camera calib.yaml (make one with '
                           'photogram-ros calibrate)')
