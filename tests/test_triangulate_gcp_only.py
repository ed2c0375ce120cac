"""`triangulate` of photos without any position (no EXIF GPS, no geo.txt) and a gcp_list.txt: the GCPs alone
place the block, checked against the simulator's truth; without a GCP file the folder is refused with what
to give."""

from __future__ import annotations

import csv
import io
import json
import shutil

import numpy as np
import pytest

from photogram_ros.cli import main
from photogram_ros.sim.scenario import preset, simulate
from test_triangulate_command import with_exif


def _without_gps(jpeg: bytes) -> bytes:
    """The JPEG with the GPS IFD taken out of its EXIF, pixels untouched."""
    from PIL import Image
    with Image.open(io.BytesIO(jpeg)) as im:
        exif = im.getexif()
    del exif[0x8825]
    return with_exif(jpeg, exif)


@pytest.fixture(scope='module')
def no_gps_survey(tmp_path_factory):
    """The tiny simulated survey's photos without EXIF GPS and without geo.txt, its gcp_list.txt beside them."""
    from photogram_ros.io.image_source import read_exif_gps
    flight = tmp_path_factory.mktemp('nogps') / 'flight'
    truth = simulate(preset('tiny', photos=True), flight)
    bare = flight / 'bare'
    bare.mkdir()
    for p in sorted((flight / 'photos').glob('*.JPG')):
        (bare / p.name).write_bytes(_without_gps(p.read_bytes()))
        assert read_exif_gps(bare / p.name) is None
    shutil.copy(flight / 'photos' / 'gcp_list.txt', flight / 'gcp_list.txt')
    return flight, bare, truth


def test_gcps_alone_place_photos_without_positions(no_gps_survey, tmp_path, capsys):
    flight, bare, truth = no_gps_survey
    out = tmp_path / 'out'
    rc = main(['triangulate', str(bare), '--gcp', str(flight / 'gcp_list.txt'), '--out', str(out)])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    rep = json.loads((out / 'report.json').read_text())
    rows = list(csv.DictReader(open(out / 'poses.csv')))
    err = np.array([truth.origin.geodetic_to_enu(float(r['lat_deg']), float(r['lon_deg']), float(r['h_m']))
                    - truth.frames[int(r['image'][4:8])].map_T_cam[:3, 3] for r in rows]).reshape(-1, 3)
    cam = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
    ck = rep['check']['rmse']
    n_photos = len(list(bare.glob('*.JPG')))
    sc = rep['self_calibration']
    print(f'no positions, {rep["verdict"]["figures"]["georeference"]}: exit {rc}, {len(rows)}/{n_photos} photos, '
          f'check n={ck["n"]} h {ck["horizontal_m"] * 100:.2f} cm v {ck["vertical_m"] * 100:.2f} cm, camera '
          f'centres {cam * 100:.1f} cm (mean error {np.round(err.mean(axis=0) * 100, 1)} cm), fx '
          f'{sc["fx"]["before"]:.1f} -> {sc["fx"]["after"]:.1f} px (true {truth.camera.fx:.1f}); {last}')
    assert rc == 0 and len(rows) == n_photos
    assert rep['verdict']['figures']['georeference'] == {'georeferenced': True, 'cameras_with_fix': 0,
                                                         'gcps_in_block': 4}
    assert not any(f['check'] in ('georeference', 'ground_below', 'nadir') for f in rep['verdict']['findings'])
    assert any('the GCPs alone place the block' in a for a in rep['assumptions'])
    # The EXIF focal is kept (no geotags: the cameras' heights would trade off with it).
    assert rep['self_calibration']['fx']['after'] == pytest.approx(rep['self_calibration']['fx']['before'])
    # Measured 0.96 / 1.31 cm (2 check points: the vertical gated at 1 cm at least), camera centres 13.2 cm
    # (with the geotags, test_triangulate_command.py: 12.1 cm).
    assert ck['n'] == 2 and ck['horizontal_m'] <= 1.5 * 0.0096 and ck['vertical_m'] <= max(1.5 * 0.0131, 0.01)
    assert cam <= 1.5 * 0.132


def test_photos_without_positions_or_gcps_are_refused_with_what_to_give(no_gps_survey, tmp_path, capsys):
    _, bare, _ = no_gps_survey
    rc = main(['triangulate', str(bare), '--out', str(tmp_path / 'out')])
    err = capsys.readouterr().err
    assert rc != 0 and 'georeferencing impossible' in err and '--gcp' in err
