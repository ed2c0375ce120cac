"""`photogram-ros triangulate` on the simulator's survey photos (geo.txt + ODM gcp_list.txt)."""

import csv
import json

import numpy as np
import pytest

from photogram_ros.cli import main
from photogram_ros.sim.scenario import preset, simulate
from photogram_ros.sim.truth import GroundTruth


@pytest.mark.slow
def test_triangulate_simulated_photos(tmp_path):
    simulate(preset('tiny', photos=True), tmp_path / 'flight')
    photos = tmp_path / 'flight' / 'photos'
    out = tmp_path / 'at'
    # The simulator's lever arm (0.05, 0, -0.20) m FRD is (0, -0.05, -0.20) in the nadir camera frame.
    rc = main(['triangulate', str(photos), '--gcp', str(photos / 'gcp_list.txt'), '--out', str(out),
               '--lever-arm=0,-0.05,-0.2'])
    assert rc == 0
    rep = json.loads((out / 'report.json').read_text())
    truth = GroundTruth.load(tmp_path / 'flight')
    rows = list(csv.DictReader(open(out / 'poses.csv')))
    n_photos = len(list(photos.glob('*.JPG')))
    ck = rep['check']['rmse']
    print(f"triangulate: {len(rows)}/{n_photos} photos, reprojection {rep['reprojection_rms_px']:.3f} px, "
          f"check n={ck['n']} h {ck['horizontal_m'] / truth.gsd_m:.2f} GSD v {ck['vertical_m'] / truth.gsd_m:.2f} GSD")
    assert len(rows) == n_photos and rep['reprojection_rms_px'] < 0.6
    assert ck['n'] == 2 and ck['horizontal_m'] < 1.5 * truth.gsd_m and ck['vertical_m'] < 2.5 * truth.gsd_m
    assert (out / 'sparse.las').stat().st_size > 10_000 and (out / 'report.md').exists()
    # Poses in WGS84 against the truth: decimetres at worst (geotags are the nearest 5 Hz fix).
    err = [truth.origin.geodetic_to_enu(float(r['lat_deg']), float(r['lon_deg']), float(r['h_m']))
           - truth.frames[int(r['image'][4:8])].map_T_cam[:3, 3] for r in rows]
    assert np.sqrt(np.mean(np.sum(np.square(err), axis=1))) < 0.5
