"""bench/inflight_20mp.py --flight seneca: seneca_part's photos upscaled to 20 MP, re-timed, with their EXIF GPS and an
EXIF camera that is the original one scaled the same way (what `replay` of the folder takes)."""

from __future__ import annotations

import sys
from pathlib import Path

import yaml
from conftest import shared_data

ROOT = Path(__file__).resolve().parents[1]


def test_seneca_flight_is_upscaled_retimed_and_keeps_its_exif(tmp_path):
    src = shared_data('photos', 'seneca_part', 'images')
    sys.path.insert(0, str(ROOT / 'bench'))
    import inflight_20mp as bench

    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.io.image_source import FolderSource, read_exif_gps
    folder, calib = bench.build_flight(2.0, 2, folder=tmp_path / 'seneca', flight='seneca')
    built, original = FolderSource(folder), FolderSource(src)
    assert [p.name for p, _ in built.entries] == [p.name for p, _ in original.entries[:2]]
    (p0, t0), (p1, t1) = built.entries
    assert t1 - t0 == 2_000_000_000
    from PIL import Image
    with Image.open(p0) as im:
        assert im.size == bench.SENECA_SIZE
    # The EXIF camera of the 20 MP photos is the original one scaled by 5164 / 1600.
    cam, want = built.exif_intrinsics().camera, original.exif_intrinsics().camera.scaled(5164 / 1600)
    assert (cam.width, cam.height) == (5164, 3873)
    assert abs(cam.fx - want.fx) < 1e-6 * want.fx and abs(cam.cy - want.cy) < 1e-6
    assert PinholeCamera.from_ros_yaml_dict(yaml.safe_load(calib.read_text())).fx == want.fx
    a, b = read_exif_gps(p0), read_exif_gps(original.entries[0][0])
    assert a is not None and (a.lat_deg, a.lon_deg, a.alt_msl_m) == (b.lat_deg, b.lon_deg, b.alt_msl_m)
