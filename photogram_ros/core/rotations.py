"""Rotations and rigid transforms, with frames in the names.

`a_R_b` rotates vectors from frame b into frame a; `a_T_b` is the 4x4 transform that maps points
in b to a. Quaternions are (x, y, z, w), the ROS order. Camera frames use the optical convention
(x right, y down, z forward); the photogrammetric camera (x right, y up, z backward) appears only in
omega-phi-kappa angles, because that is how survey software reports them.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

# NED <-> ENU and FRD <-> FLU are the same axis swap/flip in either direction.
ENU_R_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
FLU_R_FRD = np.diag([1.0, -1.0, -1.0])
# Optical camera <-> photogrammetric camera (x right, y up, z back).
OPTICAL_R_PHOTO = np.diag([1.0, -1.0, -1.0])


def rot_x(a_rad: float) -> np.ndarray:
    c, s = np.cos(a_rad), np.sin(a_rad)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=float)


def rot_y(a_rad: float) -> np.ndarray:
    c, s = np.cos(a_rad), np.sin(a_rad)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=float)


def rot_z(a_rad: float) -> np.ndarray:
    c, s = np.cos(a_rad), np.sin(a_rad)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=float)


def quat_from_R(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) -> quaternion (..., 4) as (x, y, z, w) with w >= 0."""
    q = Rotation.from_matrix(R).as_quat()
    return np.where(q[..., 3:4] < 0, -q, q)


def R_from_quat(q_xyzw) -> np.ndarray:
    """Quaternion (x, y, z, w), normalised here, -> rotation matrix."""
    return Rotation.from_quat(np.asarray(q_xyzw, dtype=float)).as_matrix()


def R_from_rotvec(rotvec_rad) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(rotvec_rad, dtype=float)).as_matrix()


def rotvec_from_R(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_rotvec()


def ned_R_frd_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Aerospace (MAVLink ATTITUDE) Euler angles -> rotation of body FRD into local NED."""
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)


def euler_from_ned_R_frd(ned_R_frd: np.ndarray) -> tuple[float, float, float]:
    """Rotation of body FRD into NED -> (roll, pitch, yaw) in radians (ZYX aerospace order)."""
    yaw, pitch, roll = Rotation.from_matrix(ned_R_frd).as_euler('ZYX')
    return float(roll), float(pitch), float(yaw)


def enu_R_flu_from_ned_R_frd(ned_R_frd: np.ndarray) -> np.ndarray:
    """Aerospace attitude (FRD in NED) -> ROS attitude (FLU in ENU), per REP-103."""
    return ENU_R_NED @ ned_R_frd @ FLU_R_FRD


# Attitude messages arrive at 10-50 Hz per vehicle: the quaternion versions below are plain float
# algebra on (x, y, z, w) tuples, no arrays, and agree with the matrix versions above to 1e-15.
_H = math.sqrt(0.5)
_Q_ENU_NED = (_H, _H, 0.0, 0.0)      # 180 deg about (x + y) / sqrt(2): swaps x/y, flips z (ENU_R_NED)
_Q_FRD_FLU = (1.0, 0.0, 0.0, 0.0)    # 180 deg about x (FLU_R_FRD, its own inverse)


def quat_mul(a_xyzw, b_xyzw) -> tuple:
    """Hamilton product a * b of two (x, y, z, w) quaternions (the rotation b, then a)."""
    ax, ay, az, aw = a_xyzw
    bx, by, bz, bw = b_xyzw
    return (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)


def quat_ned_frd_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple:
    """Aerospace ZYX Euler angles -> quaternion (x, y, z, w) of body FRD in NED (ned_R_frd_from_euler)."""
    cr, sr = math.cos(roll_rad / 2), math.sin(roll_rad / 2)
    cp, sp = math.cos(pitch_rad / 2), math.sin(pitch_rad / 2)
    cy, sy = math.cos(yaw_rad / 2), math.sin(yaw_rad / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def quat_enu_flu_from_quat_ned_frd(q_ned_frd_xyzw) -> tuple:
    """Quaternion of FRD in NED -> quaternion of FLU in ENU (REP-103), w >= 0 (enu_R_flu_from_ned_R_frd)."""
    q = quat_mul(quat_mul(_Q_ENU_NED, q_ned_frd_xyzw), _Q_FRD_FLU)
    return q if q[3] >= 0 else tuple(-v for v in q)


def opk_from_map_R_cam(map_R_cam: np.ndarray) -> tuple[float, float, float]:
    """Optical camera attitude in an ENU/projected frame -> omega, phi, kappa (radians).

    Convention of survey software (Pix4D, OpenDroneMap): R = Rx(omega) Ry(phi) Rz(kappa) rotates
    the photogrammetric camera (x right, y up, z back) into the world frame.
    """
    map_R_photo = map_R_cam @ OPTICAL_R_PHOTO
    omega, phi, kappa = Rotation.from_matrix(map_R_photo).as_euler('XYZ')
    return float(omega), float(phi), float(kappa)


def map_R_cam_from_opk(omega_rad: float, phi_rad: float, kappa_rad: float) -> np.ndarray:
    return rot_x(omega_rad) @ rot_y(phi_rad) @ rot_z(kappa_rad) @ OPTICAL_R_PHOTO


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert_T(a_T_b: np.ndarray) -> np.ndarray:
    R = a_T_b[:3, :3]
    t = a_T_b[:3, 3]
    return make_T(R.T, -R.T @ t)


def transform_points(a_T_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    return np.asarray(points_b, dtype=float) @ a_T_b[:3, :3].T + a_T_b[:3, 3]


def angle_between_R(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Geodesic angle (rad) between two rotations."""
    c = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))
