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
