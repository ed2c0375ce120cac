"""Attitude quaternions (core.rotations): the values io.mavlink computed before they moved here, and the
rotation-matrix route as an independent oracle."""

import numpy as np
import pytest

from photogram_ros.core.rotations import (R_from_quat, enu_R_flu_from_ned_R_frd, ned_R_frd_from_euler, quat_from_R,
                                          quat_enu_flu_from_quat_ned_frd, quat_mul, quat_ned_frd_from_euler)

# (roll, pitch, yaw) -> (q_ned_frd, q_enu_flu), both (x, y, z, w), printed by io/mavlink.py's own
# quat_ned_frd_from_euler / enu_flu_quat at commit ec83a90, before the copy was removed.
OLD = [
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), (-0.0, -0.0, 0.7071067811865476, 0.7071067811865476)),
    ((0.1, -0.2, 0.3), (0.06407134770607116, -0.09115754934299071, 0.15343930202422257, 0.9818561728660808),
     (-0.019152836854051974, 0.10976340573950011, 0.5857791870216184, 0.8027751289453354)),
    ((0.5, 0.4, -2.9), (0.22030907274855432, -0.21750949192506433, -0.9486018486627832, 0.06563585986884417),
     (-0.001979602584769591, -0.30958447601007677, -0.7171743614378188, 0.6243512382332794)),
    ((-0.7, 0.05, 3.1), (-0.030605066687608512, -0.3422282323791067, 0.9390543555701518, 0.01095829094550038),
     (-0.2636329540222265, 0.22035085363527748, -0.6562630208886393, 0.6717603845641962)),
    ((0.0, 1.5707963267948966, 0.0), (0.0, 0.7071067811865475, 0.0, 0.7071067811865476),
     (0.5, -0.5, 0.5000000000000001, 0.5000000000000001)),
]


@pytest.mark.parametrize('euler, q_ned_frd, q_enu_flu', OLD)
def test_quaternions_are_the_values_ingest_published_before(euler, q_ned_frd, q_enu_flu):
    q = quat_ned_frd_from_euler(*euler)
    assert q == q_ned_frd                                   # bit for bit: /mavlink/attitude is unchanged
    assert quat_enu_flu_from_quat_ned_frd(q) == q_enu_flu


def test_attitude_quaternion_algebra_matches_rotation_matrices():
    rng = np.random.default_rng(0)
    for _ in range(50):
        r, p, y = rng.uniform(-0.7, 0.7), rng.uniform(-0.7, 0.7), rng.uniform(-3.1, 3.1)
        R = ned_R_frd_from_euler(r, p, y)
        q = quat_ned_frd_from_euler(r, p, y)
        assert np.allclose(R_from_quat(q), R, atol=1e-12)
        q_out = quat_enu_flu_from_quat_ned_frd(q)
        assert q_out[3] >= 0 and np.allclose(q_out, quat_from_R(enu_R_flu_from_ned_R_frd(R)), atol=1e-12)
    # Level, nose north (NED yaw 0) -> FLU x axis points north = ENU +y: a +90 deg yaw in ENU.
    R = R_from_quat(quat_enu_flu_from_quat_ned_frd(quat_ned_frd_from_euler(0.0, 0.0, 0.0)))
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0]) and np.allclose(R @ [0, 0, 1], [0, 0, 1])


def test_quat_mul_composes_like_matrices():
    rng = np.random.default_rng(1)
    for _ in range(20):
        a, b = rng.normal(size=4), rng.normal(size=4)
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        assert np.allclose(R_from_quat(quat_mul(a, b)), R_from_quat(a) @ R_from_quat(b), atol=1e-12)
