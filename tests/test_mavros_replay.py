"""MAVROS input without MAVLink: the sample flight's fixes recorded as MAVROS publishes them
(/mavros/global_position/raw/fix, NavSatFix with STATUS_FIX for RTK too, no raw MAVLink) are taken by
tracker_node's `fix_topic` (docs/nodes.md, "Inputs from MAVROS and PX4 uXRCE-DDS"), and the replay maps the
flight from them: every keyframe oriented, the check points measured. (With tracker_node taking MAVROS's fix by
its own name, the player leaves MAVROS's topics under their names (replay_session.player_plays_mavros), so no
attitude is played and the body lever arm is left out here, as for any bag without an attitude; the player's own
MAVROS mapping, with the attitude, is tests/test_eco_autopilot_replay.py.)"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import yaml

from conftest import ROOT

pytestmark = [pytest.mark.slow, pytest.mark.ros]

MAVROS_FIX = '/mavros/global_position/raw/fix'


def _mavros_bag(sample_bag, out):
    """The sample flight's camera topics and its /gps/fix as MAVROS's raw fix (status FIX: MAVROS does not mark
    RTK), without /mavlink/from_fcu."""
    from photogram_ros.io.bag import BagReader, BagWriter, deserialize, serialize
    with BagReader(sample_bag) as r, BagWriter(out, storage='mcap') as w:
        topics = r.topics()
        for name in ('/camera/camera_info', '/camera/image_raw/compressed'):
            w.add_topic(name, topics[name].msgtype)
        w.add_topic(MAVROS_FIX, 'sensor_msgs/msg/NavSatFix')
        fixes = 0
        for m in r.messages(topics=['/camera/camera_info', '/camera/image_raw/compressed', '/gps/fix']):
            if m.topic != '/gps/fix':
                w.write_raw(m.topic, m.stamp_ns, m.data)
                continue
            fix = deserialize(m.msgtype, m.data)
            fix.status.status = min(int(fix.status.status), 0)
            fix.header.frame_id = 'base_link'
            w.write_raw(MAVROS_FIX, m.stamp_ns, serialize(fix))
            fixes += 1
    return fixes


def test_sample_flight_maps_from_mavros_topics(sample_bag, tmp_path):
    bag = tmp_path / 'mavros_bag'
    assert _mavros_bag(sample_bag, bag) > 300
    params = yaml.safe_load((ROOT / 'config' / 'replay.yaml').read_text())
    params.pop('mavlink_node', None)
    params['tracker_node']['ros__parameters']['fix_topic'] = MAVROS_FIX
    (tmp_path / 'mavros.yaml').write_text(yaml.safe_dump(params))
    out = tmp_path / 'out'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(bag), '--out', str(out), '--quiet',
                        '--params', str(tmp_path / 'mavros.yaml'), '--truth', str(sample_bag)], cwd=ROOT,
                       capture_output=True, text=True, timeout=1800)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    rep = json.loads((out / 'report.json').read_text())
    cp = rep['check_points']['rmse']
    print(f"MAVROS replay: {rep['keyframes_oriented']}/{rep['keyframes_taken']} keyframes oriented; check points "
          f"{cp['horizontal_m'] * 100:.1f} cm H, {cp['z_m'] * 100:.1f} cm V over {cp['count']}; cameras against "
          f"truth {rep['trajectory_vs_truth']}")
    assert rep['mapping']['mapped'] and rep['keyframes_oriented'] == rep['keyframes_taken'] >= 50
    assert cp['count'] >= 6
