"""Simulated keyframe records as the tracker node would publish them (bundle_node tests)."""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, NavSatFix, NavSatStatus, PointCloud2

from photogram_ros import msgs
from photogram_ros.core.control import TARGET_DTYPE
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


RELIABLE = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def tracker_feeder(context, name: str):
    """A node publishing what the tracker would: (node, camera_info, keyframes/features, keyframes/fix
    publishers)."""
    node = Node(name, context=context)
    return (node, node.create_publisher(CameraInfo, 'camera/camera_info', QoSProfile(depth=5)),
            node.create_publisher(PointCloud2, 'keyframes/features', RELIABLE),
            node.create_publisher(NavSatFix, 'keyframes/fix', RELIABLE))


def start_bundle_node(ex, node, pub_info, pub_feat, camera, stamp_ns: int) -> None:
    """Wait for the node's subscriptions, give it the calibration, wait until it is ready for keyframes."""
    spin_until(ex, lambda: pub_info.get_subscription_count() > 0 and pub_feat.get_subscription_count() > 0, 5)
    pub_info.publish(msgs.camera_info_msg(camera, stamp_ns))
    if not spin_until(ex, lambda: node.at is not None, 5):
        raise AssertionError('bundle_node did not take the camera_info')


def run_bundle(ctx, sk, marker_of: dict, overrides: dict, records=None, min_oriented_in_flight: int | None = None):
    """Feed every keyframe (features + target rows, fix) of simulated keyframes `sk` (or `records`) to a
    bundle_node over real topics, as the tracker would; (node, final poses by stamp, georeference msgs).
    At least `min_oriented_in_flight` (default: all but the first 3) must orient as they come."""
    from photogram_ros.nodes.bundle_node import BundleNode
    node = BundleNode(overrides={'lever_arm_cam_m': [float(v) for v in sk.lever_arm_cam_m], **overrides},
                      context=ctx)
    feeder, pub_info, pub_feat, pub_fix = tracker_feeder(ctx, 'gcp_feeder')
    poses, georef, n_msgs = {}, [], [0]

    def on_pose(m):
        poses[msgs.ns_from_time(m.header.stamp)] = m
        n_msgs[0] += 1
    feeder.create_subscription(PoseWithCovarianceStamped, 'map/keyframe_pose', on_pose, RELIABLE)
    feeder.create_subscription(NavSatFix, 'map/georeference', georef.append, LATCHED)
    ex = executor_with(ctx, node, feeder)
    try:
        start_bundle_node(ex, node, pub_info, pub_feat, sk.camera, sk.records[0].stamp_ns)
        records = sk.records if records is None else records
        for k, r in enumerate(records):
            pub_fix.publish(fix_msg(r, NavSatStatus.STATUS_FIX))
            obs = feature_table(r, sk.camera)
            # What the tracker sends: the markers it found, and now and then one no survey knows.
            names = list(r.target_uv) + (['stray'] if k % 4 == 0 else [])
            tg = np.zeros(len(names), TARGET_DTYPE)
            for i, n in enumerate(names):
                tg[i]['marker_id'] = marker_of.get(n, 42)
                tg[i]['u'], tg[i]['v'] = r.target_uv.get(n, (320.0, 240.0))
            pub_feat.publish(msgs.keyframe_features_msg(obs, r.stamp_ns, targets=tg))
            spin_until(ex, lambda: False, 0.05)
        n = len(records)
        c = node.diag.counts
        assert spin_until(ex, lambda: c().get('keyframes_oriented', 0) + c().get('keyframes_not_oriented', 0) >= n, 90)
        # The first ones wait for a wide enough pair.
        assert c()['keyframes_oriented'] >= (n - 3 if min_oriented_in_flight is None else min_oriented_in_flight)
        before = n_msgs[0]
        node.finish()
        # The final adjustment republishes every oriented keyframe: wait for all of them (GCPs are
        # checked before they are used, so poses published in flight may predate them).
        n_final = len(node.at.registered)
        assert spin_until(ex, lambda: n_msgs[0] >= before + n_final and georef, 20)
        last = [-1]

        def quiet():   # messages published in flight before finish() may still have been on their way
            seen, last[0] = last[0], n_msgs[0]
            return seen == n_msgs[0]
        while not spin_until(ex, lambda: False, 0.5) and not quiet():
            pass
    finally:
        ex.shutdown()
        feeder.destroy_node()
    return node, poses, georef
