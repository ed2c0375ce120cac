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


def spin_until(ex, cond, timeout_s: float) -> bool:
    """Spin the executor until cond() holds or timeout_s passes; returns cond()."""
    import time
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s and not cond():
        ex.spin_once(timeout_sec=0.05)
    return cond()


def executor_with(context, *nodes):
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=context)
    for n in nodes:
        ex.add_node(n)
    return ex


def start_bundle_node(ex, node, pub_info, pub_feat, camera, stamp_ns: int) -> None:
    """Wait for the node's subscriptions, give it the calibration, wait until it is ready for keyframes."""
    spin_until(ex, lambda: pub_info.get_subscription_count() > 0 and pub_feat.get_subscription_count() > 0, 5)
    pub_info.publish(msgs.camera_info_msg(camera, stamp_ns))
    if not spin_until(ex, lambda: node.at is not None, 5):
        raise AssertionError('bundle_node did not take the camera_info')
