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
    """The same survey three times: every photo fixed; a third FLOAT at their true positions; the same third FLOAT
    and 1 m off (the fixed photos' errors are the same in all three)."""
    from photogram_ros.sim.scenario import preset, simulate
    root = tmp_path_factory.mktemp('rtk')
    out = {}
    for case, extra in (('clean', {}), ('float_0m', {'rtk_float_every': 3, 'rtk_float_offset_m': 0.0}),
                        ('float_1m', {'rtk_float_every': 3, 'rtk_float_offset_m': 1.0})):
        simulate(preset('tiny', fps=1.0, rtk_photos=True, **extra), root / case)
        out[case] = root / case / 'rtk'
    return out


def _triangulate(folder, out):
    from photogram_ros.io.aerial_triangulation import TriangulateOptions
    from photogram_ros.io.triangulate_action import triangulate
    names = sorted({ln.split()[6] for ln in (folder / 'gcp_list.txt').read_text().splitlines()[1:]})
    triangulate(str(folder), str(out), TriangulateOptions(gcp=str(folder / 'gcp_list.txt'), check_names=tuple(names)))
    return json.loads((out / 'report.json').read_text())


# bench/results/ppk_formats_32c2764.jsonl (bench/ppk_formats.py, preset tiny): check points H, V (m) with a third of
# the photos FLOAT (0.5 / 0.8 m stated), 1 m off
MEASURED_THIRD_FLOAT_M = (0.086, 0.066)


@pytest.mark.slow
def test_rtk_xmp_weights_like_a_geo_txt_and_float_photos_errors_do_not_leak(rtk_flights, tmp_path):
    from photogram_ros.sim.photos import write_geo_txt_from_exif_and_rtk_xmp
    rtk = rtk_flights['clean']
    written = json.loads((rtk_flights['float_1m'] / 'rtk_truth.json').read_text())
    assert sum(w['flag'] == 34 for w in written.values()) == len(written) // 3
    hand = tmp_path / 'hand' / 'rtk'
    shutil.copytree(rtk, hand)
    write_geo_txt_from_exif_and_rtk_xmp(hand)
    reps = {'XMP': _triangulate(rtk, tmp_path / 'xmp'), 'hand-made geo.txt': _triangulate(hand, tmp_path / 'geo'),
            'a third FLOAT': _triangulate(rtk_flights['float_0m'], tmp_path / 'f0'),
            'a third FLOAT, 1 m off': _triangulate(rtk_flights['float_1m'], tmp_path / 'f1')}
    rows = {}
    for name, rep in reps.items():
        ck = rep['check']['rmse']
        rows[name] = (ck['n'], ck['horizontal_m'], ck['vertical_m'])
        print(f"{name}: check points n={ck['n']} RMSE H {ck['horizontal_m'] * 100:.1f} cm, "
              f"V {ck['vertical_m'] * 100:.1f} cm; flags {rep['matching'].get('rtk_flags')}")
    assert reps['XMP']['matching']['rtk_flags'] == {'50': len(list(rtk.glob('*.JPG')))}
    assert reps['a third FLOAT, 1 m off']['matching']['rtk_flags']['34'] == len(written) // 3
    assert any('RtkFlag' in a and 'float (34)' in a for a in reps['a third FLOAT, 1 m off']['assumptions'])
    n, h, v = rows['XMP']
    n_g, h_g, v_g = rows['hand-made geo.txt']
    assert n >= 2 and n == n_g and h <= 1.1 * h_g and v <= 1.1 * v_g        # measured: the same to 0.1 mm
    n0, h0, v0 = rows['a third FLOAT']
    n1, h1, v1 = rows['a third FLOAT, 1 m off']
    # the FLOAT photos' 1 m errors do not reach the check points (weighted as float): measured 1.01x / 1.02x
    assert n1 == n0 == n and h1 <= 1.1 * h0 and v1 <= 1.1 * v0
    # against the clean survey the check points lose what a third of the precise geotags gave (the same with
    # the FLOAT photos where they should be): measured 8.6 / 6.6 cm against 5.0 / 7.4 cm
    assert h1 <= 1.5 * MEASURED_THIRD_FLOAT_M[0] and v1 <= 1.5 * MEASURED_THIRD_FLOAT_M[1]


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
