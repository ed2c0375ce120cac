"""A simulated PPK photo survey end to end: `simulate --ppk` -> `geotag` -> `triangulate` without GCPs.

The simulator writes what a PPK drone leaves (photos geotagged by a consumer GNSS, a 5 Hz RTKLIB
flight.pos of the antenna at survey accuracy whose epochs fall between the exposures, a DJI
Timestamp.MRK with the true antenna -> camera offset of each photo). Every target is a check point
(no GCP is used). The same photos on their EXIF GPS alone are the baseline: metres off. The camera is
the photos' EXIF one with the final self-calibration of k1, k2 and the principal point (what a user gets:
`auto` with PPK-precise geotags); the same PPK block
with the camera's calibration (the simulator's camera.yaml, `--camera`) shows what the EXIF camera's
model costs (its principal point, centred, is 1.5 px off: 10 cm on the ground at 40 m).
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from photogram_ros.sim.scenario import preset, simulate
from photogram_ros.sim.truth import GroundTruth


@pytest.fixture(scope='module')
def flight(tmp_path_factory):
    root = tmp_path_factory.mktemp('ppk') / 'flight'
    simulate(preset('tiny', fps=1.0, ppk=True), root)
    return root, GroundTruth.load(root)


def _triangulate(folder, out, camera=None):
    from photogram_ros.io.aerial_triangulation import TriangulateOptions
    from photogram_ros.io.triangulate_action import triangulate
    names = sorted({ln.split()[6] for ln in (folder / 'gcp_list.txt').read_text().splitlines()[1:]})
    opt = TriangulateOptions(gcp=str(folder / 'gcp_list.txt'), check_names=tuple(names),
                             camera=str(camera) if camera else None)
    triangulate(str(folder), str(out), opt)
    return json.loads((out / 'report.json').read_text())


@pytest.fixture(scope='module')
def geotagged(flight):
    """`geotag` on what the PPK drone left: geo.txt beside its photos."""
    from photogram_ros.io.geotag import GeotagInput, geotag
    root, truth = flight
    ppk = root / 'ppk'
    assert not (ppk / 'geo.txt').exists()
    return geotag(GeotagInput(str(ppk / 'flight.pos'), str(ppk / 'Timestamp.MRK'), str(ppk), str(ppk / 'geo.txt')))


def test_ppk_camera_positions(flight, geotagged, tmp_path):
    from photogram_ros.io.photo_block import read_geo_txt
    root, truth = flight
    ppk, res = root / 'ppk', geotagged
    assert res.match_how == 'by number' and res.placement.mode == 'trajectory' and not res.problems
    assert all(pe.how == 'interpolated' and pe.q == 1 for _, pe in res.rows)
    # camera positions against the true camera centres
    geo = read_geo_txt(ppk / 'geo.txt')
    frame = {f'IMG_{f.index:04d}.JPG': f for f in truth.frames}
    err = np.array([truth.origin.geodetic_to_enu(*g[:3]) - frame[n].map_T_cam[:3, 3] for n, g in geo.items()])
    med = np.median(np.linalg.norm(err, axis=1))
    print(f'{len(geo)} photos: camera position error median {med * 100:.1f} cm, max {np.abs(err).max() * 100:.1f} cm '
          '(the worst are the simulator\'s instant speed changes at t = 0 and at line ends)')
    assert med < 0.045                                     # measured 2.4 cm: the PPK error model's ~2-3 cm
    # the MRK's own positions are the onboard single-point solution (flag 16): metres, and said so
    from photogram_ros.io.camera_events import read_mrk
    assert {r.flag for r in read_mrk(ppk / 'Timestamp.MRK')} == {16}
    # the ArduPilot log of the same exposures (CAM: GPS time, attitude) with the simulator's body lever arm
    from photogram_ros.core.exposure_positions import ExposureOptions
    from photogram_ros.io.geotag import GeotagInput, geotag
    res_bin = geotag(GeotagInput(str(ppk / 'flight.pos'), str(ppk / 'flight.bin'), str(ppk), str(tmp_path / 'geo.txt'),
                                 options=ExposureOptions(lever_arm_frd_m=tuple(truth.lever_arm_frd_m))))
    d = [np.linalg.norm(truth.origin.geodetic_to_enu(pe.lat_deg, pe.lon_deg, pe.h_m)
                        - truth.origin.geodetic_to_enu(*geo[n][:3])) for n, pe in res_bin.rows]
    print(f'CAM + lever arm vs MRK offsets: max {max(d) * 1000:.1f} mm')
    assert len(d) == len(geo) and max(d) < 0.003         # measured 0.7 mm (the CAM attitude is in 0.01 deg)
    # the flight's .tlog (CAMERA_FEEDBACK for every frame, numbered by frame: the photos' numbers) and the
    # photos' own EXIF times (no attitude: level, heading from the track)
    # measured 0.7 mm (tlog) and 31.7 mm (EXIF: the body's roll and pitch, up to 7 deg, turn the 20 cm mast)
    for events, most_mm in ((root / 'flight.tlog', 3.0), ('exif', 48.0)):
        r = geotag(GeotagInput(str(ppk / 'flight.pos'), str(events), str(ppk), str(tmp_path / 'geo2.txt'),
                               options=ExposureOptions(lever_arm_frd_m=tuple(truth.lever_arm_frd_m))))
        d = [np.linalg.norm(truth.origin.geodetic_to_enu(pe.lat_deg, pe.lon_deg, pe.h_m)
                            - truth.origin.geodetic_to_enu(*geo[n][:3])) for n, pe in r.rows]
        print(f'{events}: vs MRK offsets max {max(d) * 1000:.1f} mm')
        assert len(d) == len(geo) and max(d) < most_mm * 1e-3
    assert sum('has no photo' in p for p in r.problems) == 0


@pytest.mark.slow
def test_ppk_triangulation_without_gcps_against_exif_gps(flight, geotagged, tmp_path):
    root, truth = flight
    ppk = root / 'ppk'
    # the same folder on its EXIF GPS alone (no geo.txt)
    exif_dir = tmp_path / 'exif' / 'ppk'
    shutil.copytree(ppk, exif_dir, ignore=shutil.ignore_patterns('geo.txt', 'geo.csv'))
    rep_ppk = _triangulate(ppk, tmp_path / 'tri_ppk')
    rep_cal = _triangulate(ppk, tmp_path / 'tri_cal', camera=ppk / 'camera.yaml')
    rep_exif = _triangulate(exif_dir, tmp_path / 'tri_exif')
    gsd = truth.gsd_m
    rows = []
    for name, rep in (('PPK geo.txt, EXIF camera', rep_ppk), ('PPK geo.txt, calibrated camera', rep_cal),
                      ('EXIF GPS, EXIF camera', rep_exif)):
        ck = rep['check']['rmse']
        rows.append((name, ck['n'], ck['horizontal_m'], ck['vertical_m']))
        print(f"{name}: check points n={ck['n']} "
              f"RMSE H {ck['horizontal_m'] * 100:.1f} cm ({ck['horizontal_m'] / gsd:.2f} GSD), "
              f"V {ck['vertical_m'] * 100:.1f} cm ({ck['vertical_m'] / gsd:.2f} GSD)")
    _, n, h, v = rows[0]
    assert n >= 4
    assert h <= 1.5 * MEASURED_EXIF_CAMERA_M[0] and v <= 1.5 * MEASURED_EXIF_CAMERA_M[1]
    _, n1, h1, v1 = rows[1]
    assert n1 == n and h1 <= 1.5 * MEASURED_CALIBRATED_M[0] and v1 <= 1.5 * MEASURED_CALIBRATED_M[1]
    _, n2, h2, v2 = rows[2]
    assert n2 == n and h2 > 0.7 and v2 > 0.5                # EXIF alone: measured 1.42 m / 1.00 m


MEASURED_EXIF_CAMERA_M = (0.079, 0.133)     # check-point RMSE H, V
MEASURED_CALIBRATED_M = (0.028, 0.055)
