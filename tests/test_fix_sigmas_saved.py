"""A keyframe's fix accuracy travels from its NavSatFix into the map folder, so a resumed run feeds the fix
again with its own sigmas (not the camera's EXIF default)."""

import numpy as np

from photogram_ros import msgs
from photogram_ros.io import flight_inputs
from photogram_ros.params import from_dict
from photogram_ros.stages.map import MapOutputs, MapParams, MapStage
from photogram_ros.stages.report import DiagnosticsLog
from sensor_msgs.msg import NavSatFix


def test_fix_sigmas_come_from_the_covariance_and_none_when_unknown():
    rtk = msgs.navsatfix_msg(1, 47.0, 8.0, 500.0, 2, [0.02 ** 2, 0.03 ** 2, 0.05 ** 2],
                             NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN)
    assert np.allclose(msgs.fix_sigmas_m(rtk), (0.03, 0.05))
    unknown = msgs.navsatfix_msg(1, 47.0, 8.0, 500.0, 0, [0.0, 0.0, 0.0], NavSatFix.COVARIANCE_TYPE_UNKNOWN)
    assert msgs.fix_sigmas_m(unknown) == (None, None)
    broken = msgs.navsatfix_msg(1, 47.0, 8.0, 500.0, 0, [float('nan'), 1.0, 1.0],
                                NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN)
    assert msgs.fix_sigmas_m(broken) == (None, None)


def test_the_map_saves_each_keyframe_fix_with_its_sigmas(tmp_path):
    stage = MapStage(from_dict(MapParams, {'map_dir': str(tmp_path / 'map'), 'cell_m': 0.1}), DiagnosticsLog(),
                     MapOutputs())
    stage.add_keyframe_fix(10, 47.0, 8.0, 500.0, 2, 0.03, 0.05)
    stage.add_keyframe_fix(20, 47.0001, 8.0, 500.0, 0)
    fixes = flight_inputs.keyframe_fixes(tmp_path / 'map')
    assert fixes[10]['sigma_h_m'] == 0.03 and fixes[10]['sigma_v_m'] == 0.05
    assert 'sigma_h_m' not in fixes[20] and fixes[20]['status'] == 0
