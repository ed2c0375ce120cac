"""/tf and /tf_static of a drone's frame tree (core/frames.py: map -> odom -> base_link -> camera_optical,
REP-103/105) from the bundle node's adjusted keyframe poses, where tf2_msgs is importable (a ROS 2 install or
a colcon workspace). The PyPI wheels have no tf2_msgs: then nothing is published and /diagnostics says so
(`tf: ...`); a replay records the same tree into trajectory/ (io/tf_bag.py) either way.
"""

from __future__ import annotations

import numpy as np

from photogram_ros.core.frames import BASE_T_OPTICAL_NADIR, frame_names, map_T_base
from photogram_ros.core.rotations import quat_from_R
from photogram_ros.msgs import time_from_ns
from photogram_ros.nodes import qos

NOT_AVAILABLE = ('not published: tf2_msgs is not importable (the PyPI wheels have none; a ROS 2 install has it); '
                 'a replay writes the tree to trajectory/ (MCAP)')


def tf2_available() -> bool:
    import importlib.util
    return importlib.util.find_spec('tf2_msgs') is not None


def transform_msg(parent_T_child: np.ndarray, stamp_ns: int, parent: str, child: str):
    """4x4 -> geometry_msgs/TransformStamped (child in parent)."""
    from geometry_msgs.msg import TransformStamped
    T = np.asarray(parent_T_child, float)
    q = quat_from_R(T[:3, :3])
    msg = TransformStamped()
    msg.header.stamp = time_from_ns(stamp_ns)
    msg.header.frame_id = parent
    msg.child_frame_id = child
    t = msg.transform.translation
    t.x, t.y, t.z = (float(v) for v in T[:3, 3])
    r = msg.transform.rotation
    r.x, r.y, r.z, r.w = (float(v) for v in q)
    return msg


class TfPublisher:
    """Publishes the tree of the node's namespace; `available` False (and nothing published) without tf2_msgs."""

    def __init__(self, node, base_T_cam: np.ndarray = BASE_T_OPTICAL_NADIR):
        self.frames = frame_names(node.get_namespace())
        self.base_T_cam = base_T_cam
        self.available = tf2_available()
        self._static_sent = False
        if not self.available:
            return
        from tf2_msgs.msg import TFMessage
        self._msg = TFMessage
        self._tf = node.create_publisher(TFMessage, '/tf', qos.tf())
        self._static = node.create_publisher(TFMessage, '/tf_static', qos.tf_static())

    def poses(self, poses) -> None:
        """(map_T_cam, stamp_ns, covariance) of adjusted keyframes -> odom -> base_link at each stamp; the
        static part (map -> odom, base_link -> camera_optical) once, stamped with the first."""
        if not self.available:
            return
        f = self.frames
        items = list(poses)
        if items and not self._static_sent:
            stamp = items[0][1]
            self._static.publish(self._msg(transforms=[
                transform_msg(np.eye(4), stamp, f['map'], f['odom']),
                transform_msg(self.base_T_cam, stamp, f['base_link'], f['camera_optical'])]))
            self._static_sent = True
        if items:
            self._tf.publish(self._msg(transforms=[
                transform_msg(map_T_base(T, self.base_T_cam), stamp, f['odom'], f['base_link'])
                for T, stamp, _ in items]))
