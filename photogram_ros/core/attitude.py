"""Body attitude over time, and the GNSS antenna offset it gives for a gimballed camera.

A gimbal holds the camera near nadir while the body pitches into the wind and rolls in turns, so
the antenna (fixed to the body) is not at a fixed place in the camera frame: at 5 m/s a multirotor
flies about 5 degrees nose down, and a 20 cm mast then puts the antenna 1.7 cm further along the
course than the camera-frame lever arm says: an error that flips with every line, which the
adjustment can only absorb by tilting the cameras. With the autopilot's attitude the offset is
exact: antenna - camera centre = ENU_R_FLU(t) @ lever_FLU, the lever arm measured in the body.

Attitudes are REP-103 (body FLU in ENU), as mavlink_node publishes them; lever arms are given in
body FRD (the autopilot's frame, how integrators measure them) and converted here.

The same attitude gives the camera's orientation before any adjustment (`camera_prior_map_R_cam`): a camera
fixed to the body turns with it (body attitude x the camera's mount); a gimballed camera is held at its set
angles from nadir whatever the body does, turning with the body's yaw only. The mount is given as roll, pitch,
yaw (deg) about the body's forward, right, down axes from the nominal mount (core/frames.py: nadir, image top
toward the nose), turning the camera as the same body angles would turn the body: pitch > 0 (nose up) looks
ahead of nadir, roll > 0 (right side down) looks to the left.
"""

from __future__ import annotations

import bisect

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

FLU_FROM_FRD = np.diag([1.0, -1.0, -1.0])
# Body FRD <- camera optical for the nominal nadir mount, image top forward: optical x = body right, optical
# y = body backward, optical z = body down (core/frames.py BASE_T_OPTICAL_NADIR, in FRD).
FRD_R_OPTICAL_NADIR = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def antenna_offset_enu(enu_R_flu: np.ndarray, lever_arm_frd_m) -> np.ndarray:
    """Antenna minus camera centre in ENU (m) for a lever arm in body FRD (m) and a body attitude."""
    return np.asarray(enu_R_flu, float) @ (FLU_FROM_FRD @ np.asarray(lever_arm_frd_m, float))


def flu_R_cam_of_mount(mount_rpy_deg=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Body FLU <- camera optical (3x3) for a camera turned by roll, pitch, yaw (deg, about body forward, right,
    down, applied yaw-pitch-roll) from the nominal nadir mount."""
    frd_R_mount = Rotation.from_euler('ZYX', np.asarray(mount_rpy_deg, float)[::-1], degrees=True).as_matrix()
    return FLU_FROM_FRD @ frd_R_mount @ FRD_R_OPTICAL_NADIR


def level_with_yaw(enu_R_flu: np.ndarray) -> np.ndarray:
    """The body attitude without its roll and pitch: a rotation about up by the heading of the body's nose."""
    R = np.asarray(enu_R_flu, float)
    yaw = np.arctan2(R[1, 0], R[0, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def camera_prior_map_R_cam(enu_R_flu: np.ndarray, flu_R_cam: np.ndarray, gimbal: bool) -> np.ndarray:
    """The camera's orientation in map ENU (camera optical -> map) from the body attitude (FLU in ENU) and
    the mount (`flu_R_cam_of_mount`): turned by the whole attitude for a camera fixed to the body, by the
    body's yaw alone for a gimballed one (the gimbal holds its set angles against roll and pitch)."""
    body = level_with_yaw(enu_R_flu) if gimbal else np.asarray(enu_R_flu, float)
    return body @ flu_R_cam


class AttitudeHistory:
    """Recent body attitudes by stamp; `at(stamp)` interpolates between the two around it.

    Keeps `max_age_ns` of history behind the newest sample (keyframes reach the bundle adjuster a
    few seconds after their exposure). A stamp further than `max_gap_ns` from a sample on either
    side (an attitude outage, or a keyframe older than the history) has no attitude: None. Within
    `hold_ns` beyond the first or the newest sample the end sample holds: clock mapping puts an
    attitude taken with the exposure a fraction of a millisecond to either side of its stamp.
    """

    def __init__(self, max_age_ns: int = 30_000_000_000, max_gap_ns: int = 200_000_000, hold_ns: int = 20_000_000):
        self.max_age_ns, self.max_gap_ns, self.hold_ns = int(max_age_ns), int(max_gap_ns), int(hold_ns)
        self._t: list[int] = []
        self._q: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._t)

    @property
    def newest_ns(self) -> int | None:
        return self._t[-1] if self._t else None

    def add(self, stamp_ns: int, q_xyzw) -> None:
        q = np.asarray(q_xyzw, float)
        n = float(np.linalg.norm(q))
        if not np.isfinite(n) or n < 1e-6:
            return
        stamp_ns = int(stamp_ns)
        k = bisect.bisect_left(self._t, stamp_ns)
        if k < len(self._t) and self._t[k] == stamp_ns:
            self._q[k] = q / n
        else:
            self._t.insert(k, stamp_ns)
            self._q.insert(k, q / n)
        cut = bisect.bisect_left(self._t, self._t[-1] - self.max_age_ns)
        if cut:
            del self._t[:cut], self._q[:cut]

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """ENU_R_FLU at `stamp_ns`, or None without a sample within max_gap_ns on both sides."""
        t = self._t
        k = bisect.bisect_left(t, int(stamp_ns))
        if k < len(t) and t[k] == stamp_ns:
            return Rotation.from_quat(self._q[k]).as_matrix()
        if k == 0 or k == len(t):
            end = 0 if k == 0 else len(t) - 1
            if t and abs(t[end] - stamp_ns) <= self.hold_ns:
                return Rotation.from_quat(self._q[end]).as_matrix()
            return None
        t0, t1 = t[k - 1], t[k]
        if stamp_ns - t0 > self.max_gap_ns or t1 - stamp_ns > self.max_gap_ns:
            return None
        s = Slerp([0.0, float(t1 - t0)], Rotation.from_quat([self._q[k - 1], self._q[k]]))
        return s([float(stamp_ns - t0)]).as_matrix()[0]
