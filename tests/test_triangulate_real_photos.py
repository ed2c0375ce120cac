"""`triangulate` on a real DJI survey with nothing but its photos: brighton_beach, 18 FC300S
photos, EXIF GPS; no calibration, no GCPs. The peer is OpenDroneMap's cloud of the same photos."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from bench import real_surveys as rs
from conftest import shared_data
from figures import newest_figure
from photogram_ros.cli import main


def relief_against_odm(points_xyz: np.ndarray) -> dict:
    """Heights of `points_xyz` (EPSG:32615) against ODM's surface after a constant 3D offset
    (bench/real_surveys.py odm_agreement, the real-survey benchmark's measure)."""
    return rs.odm_agreement(points_xyz, search_m=3.0)


# brighton `triangulate` as bench/real_surveys.py measured it: the gates below are its figures x1.5, of the line the
# real-surveys table renders (the newest bench/results/real_surveys*.jsonl holding it, named in the messages).
REAL = 'real_surveys*.jsonl'


@pytest.fixture(scope='module')
def brighton(tmp_path_factory):
    out = tmp_path_factory.mktemp('brighton') / 'at'
    assert main(['triangulate', str(shared_data('photos', 'brighton_beach', 'images')), '--out', str(out)]) == 0
    return out


@pytest.mark.slow
def test_brighton_oriented_from_exif_alone_and_its_relief_matches_opendronemap(brighton):
    import laspy
    rep = json.loads((brighton / 'report.json').read_text())
    print(f"brighton: {rep['registered']}/{rep['keyframes']} oriented, reprojection {rep['reprojection_rms_px']:.3f} px, "
          f"{rep['points']} tie points; matching {rep['matching']}; timing {rep['timing_s']}")
    name, m = newest_figure(REAL, survey='brighton', pipeline='triangulate')
    assert rep['registered'] == m['oriented'] == 18 and rep['reprojection_rms_px'] <= 1.5 * m['reprojection_px'], name
    assert any('camera from the EXIF of DJI_0018.JPG' in a and 'sensor_table' in a for a in rep['assumptions'])
    # Auto self-calibration: the EXIF says nothing of distortion, so k1, k2 are candidates and f is kept; k2 takes
    # the lens's profile, k1 would buy under 1 % of the reprojection and is left out.
    sc = rep['self_calibration']
    assert sc['fx']['after'] == sc['fx']['before'] and sc['k1']['after'] == 0.0 and 'sigma' in sc['k2']
    las = laspy.read(brighton / 'sparse.las')
    pts = np.column_stack([las.x, las.y, las.z])
    rows = list(csv.DictReader(open(brighton / 'poses.csv')))
    depth_m = np.mean([float(r['h_m']) for r in rows]) - np.median(pts[:, 2])
    gsd_m = depth_m / sc['fx']['after']
    rel = relief_against_odm(pts)
    print(f"relief against ODM (n={rel['n']}, offset {np.round(rel['offset_m'], 2)} m): median |dz| "
          f"{rel['median_abs_dz_m'] * 100:.1f} cm = {rel['median_abs_dz_m'] / gsd_m:.2f} GSD "
          f"(GSD {gsd_m * 100:.2f} cm at {depth_m:.1f} m), p90 {rel['p90_abs_dz_m'] * 100:.1f} cm")
    assert rel['n'] > 0.6 * len(pts)
    # The sparse cloud against ODM's surface: within 1.5x of the bench's figure (its 'peer').
    assert rel['median_abs_dz_m'] <= 1.5 * m['peer']['median_abs_dz_m'] and rel['median_abs_dz_m'] < 8 * gsd_m
    # The EXIF heights' residual (the cameras against their geotag heights as adjusted, the bench's rigid V).
    assert rep['gnss']['rmse']['vertical_m'] <= 1.5 * m['rigid_v_m'], (rep['gnss']['rmse'], name)
    # The XMP's barometric height above take-off (39.8-40.2 m) against the adjusted depth to the ground
    # (the take-off point lies in the block's relief of a few metres): the EXIF focal is right to ~10 %.
    assert abs(depth_m / 40.0 - 1.0) < 0.1


@pytest.mark.slow
def test_brighton_self_calibrated_focal_is_reported_not_determined(tmp_path):
    """The trap of a flat nadir block with GNSS heights only: refining f moves it 15-20 % with a covariance
    sigma of about 1 %; the report must say f is not determined instead."""
    out = tmp_path / 'at'
    assert main(['triangulate', str(shared_data('photos', 'brighton_beach', 'images')), '--out', str(out),
                 '--self-calibrate', 'f,k1,k2']) == 0
    rep = json.loads((out / 'report.json').read_text())
    sc = rep['self_calibration']
    print(f"f {sc['fx']['before']:.1f} -> {sc['fx']['after']:.1f} px, focal {sc['focal']}")
    assert sc['focal']['determined'] is False and 'sigma' not in sc['fx']
    assert -1.0 <= sc['fx']['height_correlation'] <= 1.0
    assert any('focal length NOT DETERMINED' in a for a in rep['assumptions'])
