"""Poses from the first keyframes (provisional, labelled, replaced at the turn) and each keyframe's
orientation prior from the autopilot attitude and the camera's mount: the adjustment stage without ROS."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from photogram_ros.core.frames import BASE_T_OPTICAL_NADIR
from photogram_ros.core.gnss_fix import COV_DIAGONAL_KNOWN, STATUS_GBAS_FIX
from photogram_ros.core.pose_status import PROVISIONAL_ROLL_SIGMA_RAD, is_provisional
from photogram_ros.errors import ConfigError
from photogram_ros.params import from_dict
from photogram_ros.sim.observations import simulate_keyframes
from photogram_ros.sim.scenario import preset
from photogram_ros.stages.adjustment import AdjustmentParams, AdjustmentStage, DiagnosticsLog, RecordedOutputs


@pytest.fixture(scope='module')
def flight():
    return simulate_keyframes(preset('tiny'), keyframe_interval_s=1.0, attitude_sigma_deg=None)


class EveryPose(RecordedOutputs):
    """Every publication of poses, in order: (stamp, provisional by its covariance)."""

    def __init__(self):
        super().__init__()
        self.log = []

    def poses(self, poses):
        super().poses(poses)
        self.log.extend((stamp, is_provisional(cov)) for _, stamp, cov in poses)


def _stage(sk, out=None, **overrides):
    p = from_dict(AdjustmentParams, {'lever_arm_cam_m': [float(v) for v in sk.lever_arm_cam_m], **overrides})
    stage = AdjustmentStage(p, DiagnosticsLog(), out or RecordedOutputs())
    assert stage.set_camera(sk.camera)
    return stage


def _keyframe(stage, r):
    f = r.fix
    stage.add_fix(r.stamp_ns, f.lat_deg, f.lon_deg, f.h_m, np.diag(np.diag(f.cov_enu_m2)), STATUS_GBAS_FIX,
                  COV_DIAGONAL_KNOWN)
    stage.add_keyframe(r.stamp_ns, r.track_ids, r.uv)


def test_poses_go_out_from_the_first_line_labelled_provisional_and_the_turn_replaces_them(flight):
    sk = flight
    out = EveryPose()
    stage = _stage(sk, out)
    first_pose_at = final_at = None
    provisional_said = []
    for i, r in enumerate(sk.records):
        _keyframe(stage, r)
        assert stage.drain() == 1
        if out.log and first_pose_at is None:
            first_pose_at = i
        if stage.at.georeferenced and stage.at.georef_provisional and out.log:
            provisional_said.append(stage.diag.values['poses_provisional'])
        if stage.at.georeferenced and not stage.at.georef_provisional and final_at is None:
            final_at = i
    assert stage.finish().status == 'done'
    print(f'first pose at keyframe {first_pose_at}, final georeference at {final_at}, '
          f'{sum(p for _, p in out.log)} provisional publications')
    # The first poses go out on the straight first line, before the turn, each labelled provisional.
    assert first_pose_at is not None and final_at is not None and first_pose_at < final_at
    before_turn = [p for s, p in out.log if s <= sk.records[final_at].stamp_ns][:1]
    assert before_turn == [True]
    assert provisional_said and min(provisional_said) > 0
    assert stage.diag.values['georeferenced'] == 'True'
    # The turn republishes every pose final: none is provisional any more, on the wire or on /diagnostics.
    assert not any(is_provisional(cov) for _, cov in out.pose_by_stamp.values())
    assert len(out.pose_by_stamp) >= len(sk.records) - 1
    assert stage.diag.values['poses_provisional'] == 0
    provisional_stamps = {s for s, p in out.log if p}
    assert provisional_stamps and provisional_stamps <= set(out.pose_by_stamp)


def test_without_publish_provisional_poses_wait_for_the_turn(flight):
    sk = flight
    out = EveryPose()
    stage = _stage(sk, out, publish_provisional=False)
    for r in sk.records[:12]:
        _keyframe(stage, r)
        stage.drain()
        if stage.at.georef_provisional:
            assert not out.log
    assert not any(p for _, p in out.log)


def test_the_provisional_label_lies_about_the_line_and_says_so():
    from photogram_ros.core.pose_status import line_direction, provisional_covariance
    C = np.diag([0.01, 0.01, 0.02, 1e-6, 1e-6, 1e-6])
    assert not is_provisional(C)
    d = line_direction(np.array([[0.0, 0.0, 50.0], [3.0, 4.0, 50.1], [6.0, 8.0, 49.9]]))
    assert np.allclose(np.abs(d), [0.6, 0.8, 0.0], atol=1e-6)
    P = provisional_covariance(C, d)
    assert is_provisional(P) and np.allclose(P[:3, :3], C[:3, :3])
    # The roll about the line is the uncertain angle; about the across-line axis nothing is added.
    across = np.array([-d[1], d[0], 0.0])
    assert np.isclose(d @ P[3:, 3:] @ d, 1e-6 + PROVISIONAL_ROLL_SIGMA_RAD ** 2)
    assert np.isclose(across @ P[3:, 3:] @ across, 1e-6)


def _prior(sk, q_xyzw, **overrides):
    """The orientation prior the stage gives a keyframe with the attitude q around its stamp."""
    stage = _stage(sk, **overrides)
    r = sk.records[0]
    for dt_ns in (-50_000_000, 50_000_000):
        stage.add_attitude(r.stamp_ns + dt_ns, q_xyzw)
    _keyframe(stage, r)
    batch, _ = stage.take_work(lambda: False, 0.0)
    stage.work_done()
    assert [b.stamp_ns for b in batch] == [r.stamp_ns]
    return batch[0].map_R_cam_prior


def test_each_keyframe_carries_the_cameras_orientation_from_the_attitude_and_the_mount(flight):
    sk = flight
    att = Rotation.from_euler('ZYX', [30.0, -5.0, 12.0], degrees=True)   # heading 30, nose up 5, rolled 12 (FLU)
    enu_R_flu, nadir = att.as_matrix(), BASE_T_OPTICAL_NADIR[:3, :3]
    # A camera fixed to the body turns with it.
    R = _prior(sk, att.as_quat(), camera_mount='fixed')
    assert np.allclose(R, enu_R_flu @ nadir, atol=1e-9)
    # A gimbal holds nadir against roll and pitch and follows the yaw: the optical axis straight down, image
    # top toward the nose's heading.
    R = _prior(sk, att.as_quat(), camera_mount='gimbal')
    yaw = Rotation.from_euler('z', 30.0, degrees=True).as_matrix()
    assert np.allclose(R, yaw @ nadir, atol=1e-9)
    assert np.allclose(R[:, 2], [0.0, 0.0, -1.0], atol=1e-9)
    # A camera mounted pitched 20 degrees ahead, on a level body flying north (FLU x = north: yaw 90): the
    # optical axis leans 20 degrees north of nadir.
    north = Rotation.from_euler('z', 90.0, degrees=True)
    R = _prior(sk, north.as_quat(), camera_mount='fixed', mount_rpy_deg=[0.0, 20.0, 0.0])
    s, c = np.sin(np.radians(20.0)), np.cos(np.radians(20.0))
    assert np.allclose(R[:, 2], [0.0, s, -c], atol=1e-9)
    # auto: a body lever arm says gimbal.
    R = _prior(sk, att.as_quat(), lever_arm_cam_m=[0.0, 0.0, 0.0], lever_arm_body_frd_m=[0.05, 0.0, -0.2])
    assert np.allclose(R, yaw @ nadir, atol=1e-9)
    assert np.allclose(Rotation.from_matrix(R).as_matrix(), R)   # a rotation


def test_no_attitude_no_prior_and_a_bad_mount_is_refused(flight):
    sk = flight
    stage = _stage(sk)
    _keyframe(stage, sk.records[0])
    batch, _ = stage.take_work(lambda: False, 0.0)
    assert batch[0].map_R_cam_prior is None
    with pytest.raises(ConfigError, match='mount_rpy_deg'):
        from_dict(AdjustmentParams, {'mount_rpy_deg': [0.0, 10.0]})
