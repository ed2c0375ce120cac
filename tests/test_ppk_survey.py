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

import pytest

from bench import ppk_survey as ppk_bench
from figures import newest_figure

# What bench/ppk_survey.py measured; the gates below hold each figure within 1.5x.
PPK_RESULT = 'ppk_survey*.jsonl'   # the newest result file of the bench (tests/figures.newest_figure)


@pytest.fixture(scope='module')
def flight(tmp_path_factory):
    return ppk_bench.simulate_flight(tmp_path_factory.mktemp('ppk') / 'flight')


@pytest.fixture(scope='module')
def geotagged(flight):
    """`geotag` on what the PPK drone left: geo.txt beside its photos."""
    root, truth = flight
    assert not (root / 'ppk' / 'geo.txt').exists()
    return ppk_bench.geotag_ppk(root)


def test_ppk_camera_positions(flight, geotagged, tmp_path):
    root, truth = flight
    res = geotagged
    assert res.match_how == 'by number' and res.placement.mode == 'trajectory' and not res.problems
    assert all(pe.how == 'interpolated' and pe.q == 1 for _, pe in res.rows)
    # the MRK's own positions are the onboard single-point solution (flag 16): metres, and said so
    from photogram_ros.io.camera_events import read_mrk
    assert {r.flag for r in read_mrk(root / 'ppk' / 'Timestamp.MRK')} == {16}
    got = ppk_bench.camera_positions(root, truth, tmp_path)
    ppk_result, m = newest_figure(PPK_RESULT, case='camera_positions')
    print({k: got[k] for k in got}, f'measured ({ppk_result}):', {k: m[k] for k in got})
    # The geotags against the true camera centres (the PPK error model's few centimetres).
    assert got['median_m'] <= 1.5 * m['median_m']
    # The ArduPilot log's CAM (attitude in 0.01 deg) + lever arm and the .tlog's CAMERA_FEEDBACK against the MRK
    # offsets; the photos' EXIF times (no attitude: the body's roll and pitch turn the mast).
    for key in ('cam_bin', 'tlog', 'exif'):
        assert got[f'{key}_rows'] == got['photos']
        assert got[f'{key}_vs_mrk_max_m'] <= 1.5 * m[f'{key}_vs_mrk_max_m'], key
    assert got['exif_no_photo'] == 0


@pytest.mark.slow
def test_ppk_triangulation_without_gcps_against_exif_gps(flight, geotagged, tmp_path):
    root, truth = flight
    got = ppk_bench.triangulations(root, truth, tmp_path)
    for case, fig in got.items():
        print(f"{case}: check points n={fig['check_n']} RMSE H {fig['check_h_m'] * 100:.1f} cm "
              f"({fig['check_h_gsd']:.2f} GSD), V {fig['check_v_m'] * 100:.1f} cm ({fig['check_v_gsd']:.2f} GSD)")
    ppk, cal, exif = (got[k] for k in ('triangulate_ppk_exif_camera', 'triangulate_ppk_calibrated',
                                       'triangulate_exif_gps'))
    assert ppk['check_n'] >= 4 and cal['check_n'] == exif['check_n'] == ppk['check_n']
    for case in ('triangulate_ppk_exif_camera', 'triangulate_ppk_calibrated'):
        ppk_result, m = newest_figure(PPK_RESULT, case=case)
        assert got[case]['check_h_m'] <= 1.5 * m['check_h_m'] and got[case]['check_v_m'] <= 1.5 * m['check_v_m'], case
    # EXIF GPS alone: metres off (the baseline the PPK geotags improve on), within 1.5x of its measure either way.
    ppk_result, m = newest_figure(PPK_RESULT, case='triangulate_exif_gps')
    assert m['check_h_m'] / 1.5 <= exif['check_h_m'] <= 1.5 * m['check_h_m']
