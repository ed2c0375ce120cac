"""A replay of frames that cannot map (a white wall, geotagged) says so: the report's verdict at ERROR,
named in report.json and report.md, and the command's last line and exit status 5."""

import json
import subprocess
import sys
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from conftest import ROOT

pytestmark = pytest.mark.ros


def write_white_wall(folder, n: int = 8, size=(640, 480)):
    """`n` plain white JPEGs, 2 s apart, geotagged along a 10 m-spaced line at 40 m (the simulator's EXIF)."""
    from PIL import Image

    from photogram_ros.sim.photos import exif_bytes
    folder.mkdir()
    t0 = datetime(2024, 5, 1, 10, 0, 0, tzinfo=timezone.utc)
    for k in range(n):
        img = Image.fromarray(np.full((size[1], size[0], 3), 250, np.uint8))
        lat = 47.0 + k * 10.0 / 111_320.0
        img.save(folder / f'WALL_{k:03d}.JPG', quality=92,
                 exif=exif_bytes(lat, 8.0, 500.0, t0 + timedelta(seconds=2 * k), 1.56, size))
    return folder


def test_white_wall_photos_report_that_nothing_mapped(tmp_path):
    photos = write_white_wall(tmp_path / 'wall')
    out = tmp_path / 'out'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(photos), '--out', str(out),
                        '--quiet'], cwd=ROOT, capture_output=True, text=True, timeout=600)
    text = r.stdout + r.stderr
    assert r.returncode == 5, text
    last = r.stdout.strip().splitlines()[-1]
    assert last.startswith('MAPPING FAILED:') and 'no georeferenced keyframe' in last, text
    rep = json.loads((out / 'report.json').read_text())
    assert rep['mapping']['mapped'] is False
    assert any("no georeferenced keyframe" in f for f in rep["mapping"]["failures"])
    assert any("took no keyframe from 8 frames" in f for f in rep["mapping"]["failures"]), rep["mapping"]
    assert rep['keyframes_oriented'] == 0 and rep['keyframes_taken'] >= 0
    # The failure is at ERROR in the health table, with its reason, beside every node's worst level.
    health = {h['node']: h for h in rep['health']}
    assert health['replay']['worst_level'] == 'ERROR'
    assert any('no georeferenced keyframe' in why for why in health['replay']['reasons'])
    assert {'/camera_node', '/tracker_node', '/bundle_node'} <= set(health)
    md = (out / 'report.md').read_text()
    top = md.split('## ')[1]   # the first section is the verdict
    assert top.startswith('Verdict') and 'MAPPING FAILED' in top and 'no georeferenced keyframe' in top


def test_verdict_names_each_way_a_flight_fails_to_map():
    from photogram_ros.io.flight_verdict import keyframe_accounting, mapping_verdict
    counts = {'tracker': {'keyframes': 34, 'frames_tracked': 42},
              'bundle': {'keyframes_received': 33, 'keyframes_oriented': 1, 'keyframes_not_oriented': 32}}
    acc = keyframe_accounting(counts, 1, 'too_few_known_points (0)')
    assert acc['keyframes_taken'] == 34 and acc['keyframes_oriented'] == 1 and acc['keyframes_not_oriented'] == 33
    assert acc['keyframes_not_oriented_by_reason'] == {
        'never reached the bundle adjuster': 1,
        'not oriented by the bundle adjuster (its last status: too_few_known_points (0))': 32}
    v = mapping_verdict(acc, georeferenced=True, dsm_share=0.028, mapped_products=True)
    assert not v['mapped'] and len(v['failures']) == 2
    assert 'only 1 of 34 keyframes (3 %)' in v['failures'][0] and '2.8 % of the DSM' in v['failures'][1]
    # A DSM measured by stereo over under half its area (trees, water: the rest interpolated) is a warning,
    # not a failed flight.
    holes = mapping_verdict(acc, georeferenced=True, dsm_share=0.3, mapped_products=True)
    assert holes['warnings'] and '30.0 %' in holes['warnings'][0] and len(holes['failures']) == 1
    assert 'interpolated over much of its area' in holes['warnings'][0]
    # Per-reason counters of the adjuster, when it has them, replace its last status.
    counts['bundle'].update(not_oriented_too_few_known_points=30, not_oriented_no_fix=2)
    acc = keyframe_accounting(counts, 1, 'whatever')
    assert acc['keyframes_not_oriented_by_reason']['not oriented: too few known points'] == 30
    # A good flight: nothing missing, even when the window had given some up that the final adjustment oriented.
    good = keyframe_accounting({'tracker': {'keyframes': 14}, 'bundle': {
        'keyframes_received': 14, 'keyframes_oriented': 13, 'keyframes_not_oriented': 1}}, 14)
    assert good['keyframes_not_oriented'] == 0 and good['keyframes_not_oriented_by_reason'] == {}
    assert good['keyframes_oriented_after_the_window_gave_up'] == 1
    # The keyframes before an early break that their GNSS could not place are named as given up.
    early = keyframe_accounting({'tracker': {'keyframes': 27}, 'bundle': {
        'keyframes_received': 27, 'keyframes_oriented': 27, 'keyframes_unplaced': 6}}, 21)
    assert early['keyframes_not_oriented_by_reason'] == {
        'given up: before an early break (a line too short for its GNSS)': 6}
    assert mapping_verdict(good, True, 0.73, True) == {'mapped': True, 'failures': [], 'warnings': [],
                                                        'dsm_valid_share': 0.73}
    assert mapping_verdict(good, True, 0.3, True)['mapped'] is True
    assert mapping_verdict(good, True, None, True)['failures'] == ['no DSM was written']


def test_health_names_each_node_worst_level_with_its_reasons():
    from photogram_ros.io.flight_report import node_health
    diag = {'/bundle_node': {'level': 1, 'problems': [(1.0, 'no georeference after 20 keyframes'), (2.0, 'x')],
                             'problem_levels': {'no georeference after 20 keyframes': 1, 'x': 1}},
            '/stereo_node': {'level': 2, 'problems': [(1.0, 'minor'), (3.0, 'pair failed')],
                             'problem_levels': {'minor': 1, 'pair failed': 2}},
            '/map_node': {'level': 0, 'problems': []}}
    rows = {h['node']: h for h in node_health(diag)}
    assert rows['/bundle_node']['worst_level'] == 'WARN' and rows['/bundle_node']['reasons'][0].startswith('no geo')
    assert rows['/stereo_node']['worst_level'] == 'ERROR' and rows['/stereo_node']['reasons'] == ['pair failed']
    assert rows['/map_node'] == {'node': '/map_node', 'worst_level': 'OK', 'problems': 0, 'reasons': []}
