"""`run` with camera_node playing a photo folder without a calibration file (an EXIF camera) self-calibrates the lens
in flight as `replay` does (nodes/replay_session.EXIF_LENS_BUNDLE through commands/run.exif_lens_setup); a
calibration file, a device, or the parameter file's own choice leave the bundle node's parameters alone."""

from __future__ import annotations

from photogram_ros.commands.run import exif_lens_setup
from photogram_ros.nodes.graph import GraphSpec, role_values
from photogram_ros.nodes.replay_session import EXIF_LENS_BUNDLE

ROLES = ('camera', 'tracker', 'bundle', 'stereo', 'map')


def _spec(tmp_path, camera: str, bundle: str = '') -> GraphSpec:
    params = tmp_path / 'p.yaml'
    params.write_text(f'camera_node:\n  ros__parameters:\n{camera}' + (f'bundle_node:\n  ros__parameters:\n{bundle}'
                                                                        if bundle else ''))
    return GraphSpec(roles=ROLES, params_file=str(params))


def test_an_exif_camera_gets_the_lens_self_calibration_replay_gives_it(tmp_path):
    (tmp_path / 'photos').mkdir()
    spec = exif_lens_setup(_spec(tmp_path, f'    source: {tmp_path / "photos"}\n    rate: 1.0\n'))
    bundle = role_values(spec, 'bundle')
    assert {k: bundle[k] for k in EXIF_LENS_BUNDLE} == EXIF_LENS_BUNDLE
    assert 'k1' in bundle['pass_self_calibration']


def test_a_calibrated_camera_a_device_or_the_file_s_own_choice_stay(tmp_path):
    (tmp_path / 'photos').mkdir()
    calibrated = _spec(tmp_path, f'    source: {tmp_path / "photos"}\n    calibration_file: cam.yaml\n')
    assert exif_lens_setup(calibrated) is calibrated
    device = _spec(tmp_path, '    source: "0"\n')
    assert exif_lens_setup(device) is device
    own = exif_lens_setup(_spec(tmp_path, f'    source: {tmp_path / "photos"}\n',
                                '    pass_self_calibration: ""\n    growth_ratio: 2.0\n'))
    bundle = role_values(own, 'bundle')
    assert bundle['pass_self_calibration'] == '' and bundle['growth_ratio'] == 2.0
    assert bundle['final_self_calibration'] == EXIF_LENS_BUNDLE['final_self_calibration']
