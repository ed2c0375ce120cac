"""DJI RTK photos: each photo's own RTK flag and sigmas from its XMP weight it in `triangulate`.

The simulator writes a DJI RTK drone's photos (`rtk_photos`): EXIF GPS = the camera centre from its RTK
solution, XMP drone-dji:RtkFlag / RtkStdLon / RtkStdLat / RtkStdHgt. The fast tests read the XMP; the
slow one triangulates the folder (no GCP used, every target a check point) against the same photos with
a hand-made geo.txt of the same sigmas, and a survey with a third of its photos FLOAT and 1 m off against
the clean one.
"""

from __future__ import annotations

import json
import shutil
from datetime import datetime, timezone

import numpy as np
import pytest
from PIL import Image

from photogram_ros.io.photo_block import EXIF_SIGMA_H_M, dji_rtk_accuracy
from photogram_ros.sim.photos import dji_rtk_xmp, exif_bytes, insert_xmp


def _photo(path, xmp=None):
    Image.fromarray(np.full((48, 64, 3), 128, np.uint8)).save(
        path, quality=90, exif=exif_bytes(46.5, 6.5, 500.0, datetime(2024, 3, 8, tzinfo=timezone.utc), 8.8, (64, 48)))
    if xmp is not None:
        insert_xmp(path, xmp)
    return path


def test_dji_rtk_xmp_flag_and_sigmas(tmp_path):
    fixed = _photo(tmp_path / 'a.jpg', dji_rtk_xmp(50, 0.012, 0.010, 0.025))
    flag, h, v = dji_rtk_accuracy(fixed)
    assert flag == 50 and h == pytest.approx(np.sqrt((0.012 ** 2 + 0.010 ** 2) / 2), abs=1e-5) and v == pytest.approx(0.025)
    # a float photo with optimistic sigmas takes the float floor (10 / 20 cm); a single one the single floor
    flag, h, v = dji_rtk_accuracy(_photo(tmp_path / 'b.jpg', dji_rtk_xmp(34, 0.03, 0.03, 0.05)))
    assert flag == 34 and (h, v) == (0.10, 0.20)
    flag, h, v = dji_rtk_accuracy(_photo(tmp_path / 'c.jpg', dji_rtk_xmp(16, 0.8, 0.8, 1.0)))
    assert flag == 16 and (h, v) == (1.5, 3.0)
    # no XMP, or flag 0 (no solution): not an RTK photo (the EXIF sigmas apply)
    assert dji_rtk_accuracy(_photo(tmp_path / 'd.jpg')) is None
    assert dji_rtk_accuracy(_photo(tmp_path / 'e.jpg', dji_rtk_xmp(0, 0.0, 0.0, 0.0))) is None
    assert EXIF_SIGMA_H_M > 1.0


@pytest.fixture(scope='module')
def rtk_flights(tmp_path_factory):
    from photogram_ros.sim.scenario import preset, simulate
    from photogram_ros.sim.truth import GroundTruth
    root = tmp_path_factory.mktemp('rtk')
    clean, floaty = root / 'clean', root / 'float'
    simulate(preset('tiny', fps=1.0, rtk_photos=True), clean)
    simulate(preset('tiny', fps=1.0, rtk_photos=True, rtk_float_every=3, rtk_float_offset_m=1.0), floaty)
    return clean, floaty, GroundTruth.load(clean)


def _triangulate(folder, out):
    from photogram_ros.io.aerial_triangulation import TriangulateOptions, triangulate
    names = sorted({ln.split()[6] for ln in (folder / 'gcp_list.txt').read_text().splitlines()[1:]})
    triangulate(str(folder), str(out), TriangulateOptions(gcp=str(folder / 'gcp_list.txt'), check_names=tuple(names)))
    return json.loads((out / 'report.json').read_text())


@pytest.mark.slow
def test_rtk_xmp_weights_like_a_geo_txt_and_a_float_third_is_kept_down(rtk_flights, tmp_path):
    from photogram_ros.sim.photos import write_geo_txt_from_exif_and_rtk_xmp
    clean, floaty, truth = rtk_flights
    rtk = clean / 'rtk'
    written = json.loads((floaty / 'rtk' / 'rtk_truth.json').read_text())
    assert sum(w['flag'] == 34 for w in written.values()) == len(written) // 3
    rep_xmp = _triangulate(rtk, tmp_path / 'xmp')
    # the same photos with a hand-made geo.txt of the same positions and sigmas
    hand = tmp_path / 'hand' / 'rtk'
    shutil.copytree(rtk, hand)
    write_geo_txt_from_exif_and_rtk_xmp(hand)
    rep_geo = _triangulate(hand, tmp_path / 'geo')
    rep_float = _triangulate(floaty / 'rtk', tmp_path / 'float')
    rows = {}
    for name, rep in (('XMP', rep_xmp), ('geo.txt', rep_geo), ('XMP, a third FLOAT 1 m off', rep_float)):
        ck = rep['check']['rmse']
        rows[name] = (ck['n'], ck['horizontal_m'], ck['vertical_m'])
        print(f"{name}: check points n={ck['n']} RMSE H {ck['horizontal_m'] * 100:.1f} cm, "
              f"V {ck['vertical_m'] * 100:.1f} cm; flags {rep['matching'].get('rtk_flags')}")
    assert rep_xmp['matching']['rtk_flags'] == {'50': len(list(rtk.glob('*.JPG')))}
    assert rep_float['matching']['rtk_flags']['34'] == len(written) // 3
    assert any('RtkFlag' in a and 'float' in a for a in rep_float['assumptions'])
    n, h, v = rows['XMP']
    n_g, h_g, v_g = rows['geo.txt']
    assert n >= 2 and n == n_g
    assert h <= 1.1 * h_g + 0.005 and v <= 1.1 * v_g + 0.005
    n_f, h_f, v_f = rows['XMP, a third FLOAT 1 m off']
    assert n_f == n and h_f <= 1.5 * h + 0.01 and v_f <= 1.5 * v + 0.01


def test_photo_block_takes_each_photos_rtk_sigmas_and_counts_the_flags(tmp_path):
    from photogram_ros.io.photo_block import read_photo_block
    rng = np.random.default_rng(3)
    flags = [(50, 0.012, 0.010, 0.025), (50, 0.011, 0.011, 0.022), (34, 0.6, 0.5, 0.9), (16, 0.9, 0.9, 2.0), None]
    for k, f in enumerate(flags):
        p = tmp_path / f'DJI_{k:04d}.JPG'
        Image.fromarray(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)).save(
            p, quality=90, exif=exif_bytes(46.5 + k * 1e-5, 6.5, 500.0, datetime(2024, 3, 8, tzinfo=timezone.utc), 4.4,
                                           (320, 240)))
        if f is not None:
            insert_xmp(p, dji_rtk_xmp(*f))
    block = read_photo_block(tmp_path)
    assert block.stats['rtk_flags'] == {'50': 2, '34': 1, '16': 1}
    said = [a for a in block.assumptions if 'RtkFlag' in a]
    assert len(said) == 1 and '2 fixed (narrow-lane) (50)' in said[0] and '1 float (34)' in said[0] \
        and '1 single (16)' in said[0] and '1 photos without an RTK flag' in said[0]
    sig = {r.name: (np.sqrt(r.fix.cov_enu_m2[0][0]), np.sqrt(r.fix.cov_enu_m2[2][2])) for r in block.records}
    assert sig['DJI_0000.JPG'][0] == pytest.approx(np.sqrt((0.012 ** 2 + 0.010 ** 2) / 2), abs=1e-6)
    assert sig['DJI_0002.JPG'] == pytest.approx((np.sqrt((0.6 ** 2 + 0.5 ** 2) / 2), 0.9), abs=1e-6)
    assert sig['DJI_0003.JPG'] == pytest.approx((1.5, 3.0))            # the single class's floor
    assert sig['DJI_0004.JPG'] == pytest.approx((EXIF_SIGMA_H_M, 2.0))  # no XMP: the EXIF sigmas
