"""A bag with input faults through `replay` (issue 48): the camera's stamps repeat once and jump back 5 s for four
frames, and the autopilot falls silent for 20 s (its raw MAVLink cut out of the bag): tracker_node and
mavlink_node warn on /diagnostics, the report names each fault with its count, and the flight still maps.
The nodes' own tests: tests/test_faults_stamps.py, tests/test_faults_link.py."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT, SAMPLE_BAG

IMAGES = '/camera/image_raw/compressed'
REPEAT_AT = 10            # this frame's stamp repeats the one before
BACK_FROM, BACK_N = 20, 4   # these frames are stamped 5 s back
BACK_NS = 5_000_000_000
SILENT_S = (30.0, 50.0)   # the autopilot's raw MAVLink cut out over this span of the bag (s from its start)


def faulty_sample_bag(dst: Path) -> dict:
    """The sample bag with the faults above written to `dst` (sqlite3): {what was done: how many}."""
    from photogram_ros.io.bag import BagReader, BagWriter, deserialize, serialize
    done = {'stamps_repeated': 0, 'stamps_back': 0, 'mavlink_cut': 0}
    with BagReader(SAMPLE_BAG) as r, BagWriter(dst) as w:
        t0 = r.start_ns
        for t in r.topics().values():
            w.add_topic(t.topic, t.msgtype)
        k, last = -1, None
        for m in r.messages():
            if m.topic == '/mavlink/from_fcu' and SILENT_S[0] <= (m.stamp_ns - t0) * 1e-9 < SILENT_S[1]:
                done['mavlink_cut'] += 1
                continue
            if m.topic != IMAGES:
                w.write_raw(m.topic, m.stamp_ns, m.data)
                continue
            k += 1
            msg = deserialize(m.msgtype, m.data)
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            if k == REPEAT_AT:
                stamp = last
                done['stamps_repeated'] += 1
            elif BACK_FROM <= k < BACK_FROM + BACK_N:
                stamp -= BACK_NS
                done['stamps_back'] += 1
            last = stamp
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            w.write_raw(m.topic, m.stamp_ns, serialize(msg))
    return done


@pytest.mark.slow
@pytest.mark.ros
def test_a_bag_with_stamp_faults_and_an_autopilot_silence_is_warned_and_reported(tmp_path):
    bag = tmp_path / 'faulty'
    done = faulty_sample_bag(bag)
    assert done['stamps_repeated'] == 1 and done['stamps_back'] == BACK_N and done['mavlink_cut'] > 500, done
    out = tmp_path / 'out'
    res = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(bag), '--out', str(out)],
                         cwd=ROOT, capture_output=True, text=True, timeout=1500,
                         env={**os.environ, 'PYTHONPATH': str(ROOT)})
    report = json.loads((out / 'report.json').read_text())
    text = json.dumps(report)
    faults = report['input_faults']
    print(json.dumps(faults), res.stdout[-600:])
    assert faults.get('frames_dropped_stamp_repeated') == 1, faults
    # The four back-stamped frames are dropped; the frames after them that still come before the last frame
    # tracked are dropped too (time never goes back in the tracker).
    assert faults.get('frames_dropped_stamp_back', 0) >= BACK_N, faults
    assert faults.get('link_silences', 0) >= 1 and 19.0 <= faults.get('link_longest_silence_s', 0) <= 22.0, faults
    # Named as the nodes said it on /diagnostics, in the report's node health.
    assert 'dropped: its stamp repeats' in text and 'goes back' in text, text[:2000]
    assert 'the autopilot was silent for' in text, text[:2000]
    md = (out / 'report.md').read_text()
    assert 'Input faults: frames dropped stamp back: ' in md and 'link silences: 1' in md, md[:1500]
    # The flight still maps.
    assert res.returncode in (0, 3), res.stdout[-2000:] + res.stderr[-2000:]
    assert report['keyframes_oriented'] >= 0.9 * report['keyframes_taken'], (report['keyframes_oriented'],
                                                                            report['keyframes_taken'])
