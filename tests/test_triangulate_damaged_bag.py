"""`photogram-ros triangulate` on a damaged bag: what the bag still holds is
triangulated, what was read and lost is said on the console and in the report, and the exit status is 3
as `replay`'s (docs/faults.md)."""

import json
import shutil
import subprocess
import sys

from conftest import ROOT, SAMPLE_BAG


def test_triangulate_of_a_truncated_bag_exits_3_and_says_what_was_lost(tmp_path):
    bag = tmp_path / 'bag'
    shutil.copytree(SAMPLE_BAG, bag, ignore=shutil.ignore_patterns('*.tlog', 'ground_truth*', 'targets.txt'))
    db = next(bag.glob('*.db3'))
    data = db.read_bytes()
    db.write_bytes(data[:int(len(data) * 0.35)])          # power loss at a third of the flight
    out = tmp_path / 'at'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'triangulate', str(bag), '--out', str(out),
                        '--lever-arm=0,-0.05,-0.20'], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert r.returncode == 3, r.stdout[-2000:] + r.stderr[-2000:]
    assert 'of 3726 messages readable' in r.stdout and 'lost' in r.stdout and 'bag damaged' in r.stdout
    assert 'messages readable' in r.stderr            # said while reading, too
    rep = json.loads((out / 'report.json').read_text())
    assert any('of 3726 messages readable' in e for e in rep['bag_damage'])
    assert 5 < rep['registered'] < 40                  # what the bag still holds was triangulated
    assert 'bag damaged' in (out / 'report.md').read_text()
