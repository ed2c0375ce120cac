"""A provisional pose, as its covariance says it (map/keyframe_pose).

Before the first turn the block is georeferenced on a straight line of fixes, and the roll about that line
is an assumption (a near-nadir camera; core/incremental.py `assume_nadir`): the adjustment stage publishes
those poses early and labels them provisional. The label is in each pose's covariance, where a ROS consumer
of geometry_msgs/PoseWithCovarianceStamped looks: the rotation block (rx, ry, rz about the map's axes) carries
PROVISIONAL_ROLL_SIGMA_RAD^2 about the line's horizontal direction on top of the pose's own angle variances
(1e-6 rad^2 per axis for a final pose). A pose is provisional when the trace of its rotation block exceeds
PROVISIONAL_TRACE_RAD2 (`is_provisional`; msgs.pose_is_provisional reads it off a message). Once the turn
fixes the roll, every pose is published again with its final covariance, replacing the provisional one
(same stamp).
"""

from __future__ import annotations

import numpy as np

PROVISIONAL_ROLL_SIGMA_RAD = 0.1      # about 6 degrees: a near-nadir camera's roll about its line, not measured (seneca_part's fixed wing: 5.5)
PROVISIONAL_TRACE_RAD2 = 0.5 * PROVISIONAL_ROLL_SIGMA_RAD ** 2


def line_direction(centres_map: np.ndarray) -> np.ndarray:
    """Unit horizontal direction (3,) of the line the camera centres (N, 3) lie along; east for fewer than 2."""
    C = np.asarray(centres_map, float)[:, :2]
    if len(C) < 2:
        return np.array([1.0, 0.0, 0.0])
    _, _, Vt = np.linalg.svd(C - C.mean(0), full_matrices=False)
    return np.array([Vt[0, 0], Vt[0, 1], 0.0])


def provisional_covariance(covariance: np.ndarray, line_dir_map: np.ndarray) -> np.ndarray:
    """The 6x6 pose covariance (x, y, z, rx, ry, rz) with the provisional roll about the line added."""
    C = np.array(covariance, float).reshape(6, 6)
    d = np.asarray(line_dir_map, float)
    d = d / max(np.linalg.norm(d), 1e-12)
    C[3:, 3:] += PROVISIONAL_ROLL_SIGMA_RAD ** 2 * np.outer(d, d)
    return C


def is_provisional(covariance) -> bool:
    """Whether a 6x6 pose covariance carries the provisional label."""
    C = np.asarray(covariance, float).reshape(6, 6)
    return bool(np.trace(C[3:, 3:]) > PROVISIONAL_TRACE_RAD2)
