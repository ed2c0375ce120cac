"""A faulty flight replays to the end and still produces a map; the report says what went wrong and when.

Faults: 5 % of frames dropped, a 10-second GNSS outage, a stretch of corrupted MAVLink bytes and a
black frame, on a short simulated flight.
"""

import json
import subprocess
import sys

import pytest

from conftest import ROOT

pytestmark = pytest.mark.ros


@pytest.fixture(scope='module')
def faulty_replay(tmp_path_factory):
    from photogram_ros.sim.scenario import preset, simulate
    base = tmp_path_factory.mktemp('faulty')
    bag = base / 'bag'
    truth = simulate(preset('tiny', seed=3, drop_fraction=0.05, gnss_outages=[(9.0, 19.0)],
                            mavlink_corruption=[(3.0, 6.0)], black_frames=[6.0]), bag)
    out = base / 'out'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(bag), '--out', str(out), '--quiet'],
                       cwd=ROOT, capture_output=True, text=True, timeout=900)
    return r, out, truth


def test_faulty_flight_still_maps(faulty_replay):
    r, out, truth = faulty_replay
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    rep = json.loads((out / 'report.json').read_text())
    assert sum(not f.published for f in truth.frames) >= 1      # frames were really dropped
    assert rep['keyframes'] >= 10 and rep['run']['map_points'] > 10_000
    assert (out / 'dsm.tif').exists() and (out / 'ortho.tif').exists()


def test_report_lists_what_went_wrong_and_when(faulty_replay):
    r, out, truth = faulty_replay
    rep = json.loads((out / 'report.json').read_text())
    problems = [(node, t, text) for node, d in rep['nodes'].items() for t, text in d['problems']]
    texts = ' | '.join(p[2] for p in problems)
    assert 'NO_FIX' in texts                         # the GNSS outage
    assert 'corrupted MAVLink' in texts              # the damaged bytes
    assert 'tracking broke' in texts or rep['nodes']['/tracker_node']['values'].get('unusable_frames', 0) >= 1
    assert all(isinstance(t, (int, float)) and t >= 0 for _, t, _ in problems)
    md = (out / 'report.md').read_text()
    assert 'Problems (time from the start of the replay)' in md and 'NO_FIX' in md
