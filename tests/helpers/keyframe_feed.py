"""Simulated keyframe records as the tracker node would publish them (bundle_node tests)."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import NavSatFix, NavSatStatus

from photogram_ros import msgs
from photogram_ros.core.tracker import FEATURE_DTYPE


def fix_msg(record, status: int = NavSatStatus.STATUS_GBAS_FIX) -> NavSatFix:
    """The record's GNSS fix as keyframes/fix: diagonal ENU covariance, ellipsoidal height."""
    f = record.fix
    return msgs.navsatfix_msg(record.stamp_ns, f.lat_deg, f.lon_deg, f.h_m, status, np.diag(f.cov_enu_m2),
                              NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN)


def feature_table(record, camera) -> np.ndarray:
    """The record's tracks as the keyframes/features table (track id, pixel, normalised coordinates)."""
    obs = np.zeros(len(record.track_ids), FEATURE_DTYPE)
    obs['track_id'], obs['u'], obs['v'] = record.track_ids, record.uv[:, 0], record.uv[:, 1]
    xn = camera.pixel_to_normalized(record.uv)
    obs['xn'], obs['yn'] = xn[:, 0], xn[:, 1]
    return obs
