"""`triangulate --gcp`: the adjustment with the vetted control starts from the GNSS-only block the control was
vetted against (TriangulateOptions.control_from 'gnss_block') instead of building the block again photo by photo
('photos'); both on the tiny simulated survey (4 GCPs, 2 check points, geotags of the flight's GNSS)."""

import pytest

from photogram_ros.io.aerial_triangulation import TriangulateOptions, triangulate
from photogram_ros.sim.scenario import preset, simulate
from photogram_ros.sim.truth import GroundTruth

LEVER_ARM_CAM_M = (0.0, -0.05, -0.2)   # the simulator's (0.05, 0, -0.20) m FRD in the nadir camera frame


@pytest.fixture(scope='module')
def tiny_photos(tmp_path_factory):
    where = tmp_path_factory.mktemp('control_pass') / 'flight'
    simulate(preset('tiny', photos=True), where)
    return where / 'photos', GroundTruth.load(where)


def _run(photos, out, control_from):
    lines = []
    res = triangulate(photos, out, TriangulateOptions(gcp=str(photos / 'gcp_list.txt'),
                                                      lever_arm_cam_m=LEVER_ARM_CAM_M, control_from=control_from),
                      log=lines.append)
    return res, lines


def test_the_adjustment_with_the_gcps_starts_from_the_gnss_only_block(tiny_photos, tmp_path):
    """Measured: 'gnss_block' 0.93 / 0.12 cm H / V at the check points against 1.46 / 0.60 cm built again from the
    photos, fx 520.22 against 520.26 px (true 520.0); every photo oriented both ways."""
    photos, truth = tiny_photos
    new, new_log = _run(photos, tmp_path / 'gnss_block', 'gnss_block')
    old, old_log = _run(photos, tmp_path / 'photos', 'photos')
    assert new.registered == old.registered == new.inputs
    assert any(line.startswith('full adjustment with the control (from the GNSS-only block') for line in new_log)
    assert not any('from the GNSS-only block' in line for line in old_log)
    ck_new, ck_old = new.report['check']['rmse'], old.report['check']['rmse']
    print(f"check points H / V: gnss_block {100 * ck_new['horizontal_m']:.2f} / {100 * ck_new['vertical_m']:.2f} cm, "
          f"photos {100 * ck_old['horizontal_m']:.2f} / {100 * ck_old['vertical_m']:.2f} cm; fx "
          f"{new.report['self_calibration']['fx']['after']:.2f} / {old.report['self_calibration']['fx']['after']:.2f} px")
    assert ck_new['n'] == ck_old['n'] == 2
    assert ck_new['horizontal_m'] <= 1.5 * 0.0093
    assert ck_new['vertical_m'] <= max(1.5 * 0.0012, 0.01)   # two check points: 1 cm at least, as elsewhere
    assert abs(new.report['self_calibration']['fx']['after'] - truth.camera.fx) < 1.0
    assert new.report['gcp']['rmse']['n'] == old.report['gcp']['rmse']['n'] == 4
    assert new.verdict['status'] == old.verdict['status']


def test_control_from_is_checked(tiny_photos, tmp_path):
    from photogram_ros.errors import ConfigError
    photos, _ = tiny_photos
    with pytest.raises(ConfigError, match='control_from'):
        triangulate(photos, tmp_path / 'x', TriangulateOptions(gcp=str(photos / 'gcp_list.txt'), control_from='gcps'))
