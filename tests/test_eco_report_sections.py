"""The flight report's sections at OpenDroneMap's level on a real photo set (slow): brighton_beach's 18 DJI photos
replayed (`photogram-ros replay <folder>`, the camera node playing the photos with their EXIF GPS) give the report
every section tests/test_flight_report_sections.py checks on the sample flight: capture date and time span, the
software and its parameters, area covered and GSD, a DSM preview, overlap, the GNSS residual of each photo, the
calibration before and after; with no surveyed targets the check-point section says none were given."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

from conftest import ROOT, shared_data

def test_parameters_section_lists_the_file_and_the_commands_overrides(tmp_path):
    from photogram_ros.io.flight_report import parameters_section
    f = tmp_path / 'replay.yaml'
    f.write_text('tracker_node:\n  ros__parameters:\n    max_features: 1500\n    fix_topic: gps/fix\n'
                 'bundle_node:\n  ros__parameters:\n    lever_arm_body_frd_m: [0.0, 0.0, -0.2]\n')
    figures = {}
    sec = parameters_section({'params_file': str(f), 'parameter_overrides': {'bundle': {
        'lever_arm_body_frd_m': [0.0, 0.0, 0.0]}}}, figures)
    assert sec.title == 'Parameters' and sec.text[0] == f'Parameters file: {f}.'
    rows = sec.tables[0][1]
    assert {'node': 'tracker_node', 'parameter': 'max_features', 'value': '1500', 'from': 'file'} in rows
    assert {'node': 'bundle_node', 'parameter': 'lever_arm_body_frd_m', 'value': '[0.0, 0.0, -0.2]',
            'from': 'file'} in rows
    assert rows[-1] == {'node': 'bundle', 'parameter': 'lever_arm_body_frd_m', 'value': '[0.0, 0.0, 0.0]',
                        'from': 'command'}
    assert figures['parameters']['file'] == str(f) and len(figures['parameters']['rows']) == 4
    # A run that did not record its parameters says so: no table that looks complete.
    sec = parameters_section({}, {})
    assert not sec.tables and 'did not record its parameters file' in sec.text[0]


@pytest.mark.slow
@pytest.mark.ros
def test_real_photo_set_flight_report_sections(tmp_path):
    out = tmp_path / 'brighton'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay',
                        str(shared_data('photos', 'brighton_beach', 'images')), '--out', str(out), '--quiet'],
                       cwd=ROOT, capture_output=True, text=True, timeout=2400)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    md = (out / 'report.md').read_text()
    titles = re.findall(r'^## (.+)$', md, re.M)
    for t in ('Verdict', 'Summary', 'Capture and coverage', 'DSM', 'Check points', 'GNSS residuals per photo',
              'Camera', 'Overlap', 'Parameters', 'Software'):
        assert t in titles, (t, titles)
    assert 'No surveyed targets given' in md
    rep = json.loads((out / 'report.json').read_text())
    cap = rep['capture']
    print(f"brighton_beach replay report: {cap}; gnss residuals rms {rep['gnss_residuals']['rms']}")
    # The photos were taken on 2016-06-23 (EXIF), 6-7 s apart: 18 photos span about 2 minutes.
    assert cap['date'].startswith('2016-06-2') and cap['photos'] >= 9 and cap['duration_s'] > 30
    assert cap['area_m2'] > 0 and 0.005 < cap['gsd_m'] < 0.2
    assert len(rep['gnss_residuals']['photos']) == cap['photos']
    cams = [row['camera'] for row in rep['calibration']]
    assert any(c.startswith('before') for c in cams) and any(c.startswith('after') for c in cams)
    from photogram_ros import __version__
    assert rep['software']['photogram_ros'] == __version__ and 'replay' in rep['software']['command']
    for png in ('dsm.png', 'overlap.png', 'gnss_residuals.png'):
        assert (out / png).stat().st_size > 0, png
