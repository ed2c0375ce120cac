"""`photogram-ros triangulate BAG`: offline aerial triangulation of a whole flight bag."""

import csv
import subprocess
import sys

import numpy as np

from conftest import ROOT
from photogram_ros.sim.truth import GroundTruth


def test_triangulate_sample_bag_against_truth(sample_bag, tmp_path):
    out = tmp_path / 'at'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'triangulate', str(sample_bag), '--out', str(out),
                        '--lever-arm=0,-0.05,-0.20'], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    truth = GroundTruth.load(sample_bag)
    err = []
    for row in csv.DictReader(open(out / 'poses.csv')):
        f = truth.frame_by_stamp(int(row['image']), 5_000_000)
        c = truth.origin.geodetic_to_enu(float(row['lat_deg']), float(row['lon_deg']), float(row['h_m']))
        err.append(c - f.map_T_cam[:3, 3])
    err = np.array(err)
    assert len(err) >= 40
    # RTK-fixed priors: the cameras are as good as the fixes (this flight's RTK bias is about 2.5 cm).
    assert np.sqrt(np.mean(np.sum(err ** 2, axis=1))) < 0.05
    assert (out / 'sparse.las').exists() and (out / 'report.md').exists()
    assert 'camera_info' in (out / 'report.md').read_text()


def test_self_calibration_recovers_a_wrong_focal_length(sample_bag, tmp_path):
    """Start 2 % off in focal length: the final adjustment with --self-calibrate f brings it back."""
    import dataclasses
    import json

    import yaml
    truth = GroundTruth.load(sample_bag)
    wrong = dataclasses.replace(truth.camera, fx=truth.camera.fx * 1.02, fy=truth.camera.fy * 1.02)
    cal = tmp_path / 'cal.yaml'
    cal.write_text(yaml.safe_dump(wrong.to_ros_yaml_dict()))
    out = tmp_path / 'at'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'triangulate', str(sample_bag), '--out', str(out),
                        '--lever-arm=0,-0.05,-0.20', '--camera', str(cal), '--self-calibrate', 'f'],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    sc = json.loads((out / 'report.json').read_text())['self_calibration']
    assert abs(sc['fx']['before'] / truth.camera.fx - 1.02) < 1e-6
    assert abs(sc['fx']['after'] / truth.camera.fx - 1.0) < 0.005


def test_triangulate_bag_with_its_targets_file(sample_bag, tmp_path):
    """--targets: the flight's control file (as replay --gcp reads it); the ArUco markers found in the
    keyframes tie the block to the five GCPs and the four CHK* targets are check points, never used
    (measured: 3.4 cm horizontal, 2.5 cm vertical, 76 marker observations)."""
    import json
    out = tmp_path / 'at'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'triangulate', str(sample_bag), '--out', str(out),
                        '--lever-arm=0,-0.05,-0.20', '--targets', str(sample_bag / 'targets.txt')],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    rep = json.loads((out / 'report.json').read_text())
    gsd = GroundTruth.load(sample_bag).gsd_m
    ck = rep['check']['rmse']
    assert sorted(p['name'] for p in rep['check']['points']) == ['CHK01', 'CHK02', 'CHK03', 'CHK04']
    assert ck['horizontal_m'] <= 1.0 * gsd and ck['vertical_m'] <= 1.5 * gsd
    assert len(rep['gcp']['points']) == 5
    assert any('5 GCPs, 4 check points' in s for s in rep['assumptions'])
