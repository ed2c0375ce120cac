"""The adjusted trajectory as a ROS 2 recording: /tf, /tf_static and map/path in an MCAP (a replay's trajectory/).

RViz, Foxglove and `ros2 bag play` place the camera, the clouds and the drone with it: the frame tree of
core/frames.py (map -> odom -> base_link -> camera_optical, REP-103/105), one odom -> base_link per keyframe
at its stamp, map -> odom and base_link -> camera_optical on /tf_static (latched), and the nav_msgs/Path
of the camera poses as the bundle node publishes it (map/path). The messages are built from rosbags' ROS 2
Jazzy type store, so no tf2_msgs Python package is needed (the PyPI wheels have none).

`TfBuffer` reads /tf and /tf_static back from a bag and looks a transform up at a time (tf2's rules:
static transforms at any time, dynamic ones interpolated between their two neighbours, refused outside
them): what a test or a user checks a recording with, without tf2.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from photogram_ros.core.frames import BASE_T_OPTICAL_NADIR, frame_names, map_T_base
from photogram_ros.core.rotations import R_from_quat, quat_from_R
from photogram_ros.errors import BagError

TOPIC_TF = '/tf'
TOPIC_TF_STATIC = '/tf_static'
TOPIC_PATH = 'map/path'
TF_TYPE = 'tf2_msgs/msg/TFMessage'


def _time(types, stamp_ns: int):
    return types['builtin_interfaces/msg/Time'](sec=int(stamp_ns) // 1_000_000_000, nanosec=int(stamp_ns) % 1_000_000_000)


def _header(types, stamp_ns: int, frame_id: str):
    return types['std_msgs/msg/Header'](stamp=_time(types, stamp_ns), frame_id=frame_id)


def _transform_stamped(types, parent_T_child: np.ndarray, stamp_ns: int, parent: str, child: str):
    T = np.asarray(parent_T_child, float)
    t, q = T[:3, 3], quat_from_R(T[:3, :3])
    tf = types['geometry_msgs/msg/Transform'](
        translation=types['geometry_msgs/msg/Vector3'](x=float(t[0]), y=float(t[1]), z=float(t[2])),
        rotation=types['geometry_msgs/msg/Quaternion'](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
    return types['geometry_msgs/msg/TransformStamped'](header=_header(types, stamp_ns, parent), child_frame_id=child,
                                                       transform=tf)


def _pose_stamped(types, map_T: np.ndarray, stamp_ns: int, frame_id: str):
    T = np.asarray(map_T, float)
    t, q = T[:3, 3], quat_from_R(T[:3, :3])
    pose = types['geometry_msgs/msg/Pose'](
        position=types['geometry_msgs/msg/Point'](x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=types['geometry_msgs/msg/Quaternion'](x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                          w=float(q[3])))
    return types['geometry_msgs/msg/PoseStamped'](header=_header(types, stamp_ns, frame_id), pose=pose)


def write_trajectory_mcap(path: str | Path, stamps_ns, map_T_cams, namespace: str = '',
                          base_T_cam: np.ndarray = BASE_T_OPTICAL_NADIR) -> Path:
    """Write the frame tree of the adjusted keyframes (stamps, camera poses in map) as a rosbag2 folder
    (MCAP, zstd chunks) at `path` (which must not exist). Returns the folder."""
    from photogram_ros.io.bag import BagWriter, latched_qos
    stamps = [int(s) for s in stamps_ns]
    Ts = [np.asarray(T, float) for T in map_T_cams]
    if len(stamps) != len(Ts) or not stamps:
        raise BagError(f'{path}: {len(stamps)} stamps for {len(Ts)} poses: no trajectory to record')
    order = np.argsort(stamps, kind='stable')
    stamps, Ts = [stamps[k] for k in order], [Ts[k] for k in order]
    f = frame_names(namespace)
    with BagWriter(path, storage='mcap') as bag:
        types = bag.types.types
        bag.add_topic(TOPIC_TF_STATIC, TF_TYPE, qos=[latched_qos(depth=1)])
        static = [_transform_stamped(types, np.eye(4), stamps[0], f['map'], f['odom']),
                  _transform_stamped(types, base_T_cam, stamps[0], f['base_link'], f['camera_optical'])]
        bag.write_typed(TOPIC_TF_STATIC, stamps[0], types[TF_TYPE](transforms=static))
        for stamp, T in zip(stamps, Ts):
            # map -> odom is the identity: odom -> base_link is the body's adjusted pose in map.
            tf = _transform_stamped(types, map_T_base(T, base_T_cam), stamp, f['odom'], f['base_link'])
            bag.write_typed(TOPIC_TF, stamp, types[TF_TYPE](transforms=[tf]))
        path_msg = types['nav_msgs/msg/Path'](header=_header(types, stamps[-1], f['map']),
                                              poses=[_pose_stamped(types, T, s, f['map']) for s, T in zip(stamps, Ts)])
        bag.write_typed(TOPIC_PATH, stamps[-1], path_msg)
    return Path(path)


class TfBuffer:
    """Transforms read from /tf and /tf_static, looked up as tf2 does (see the module)."""

    def __init__(self):
        self._static: dict[str, tuple[str, np.ndarray]] = {}         # child -> (parent, parent_T_child)
        self._dynamic: dict[str, tuple[str, list, list]] = {}         # child -> (parent, stamps, transforms)

    @classmethod
    def from_bag(cls, path: str | Path) -> 'TfBuffer':
        from rosbags.typesys import Stores, get_typestore
        from photogram_ros.io.bag import BagReader
        store = get_typestore(Stores.ROS2_JAZZY)
        buf = cls()
        bag = BagReader(path)
        for m in bag.messages(topics=[TOPIC_TF, TOPIC_TF_STATIC]):
            msg = store.deserialize_cdr(m.data, m.msgtype)
            for t in msg.transforms:
                tr, rot = t.transform.translation, t.transform.rotation
                T = np.eye(4)
                T[:3, :3] = R_from_quat([rot.x, rot.y, rot.z, rot.w])
                T[:3, 3] = [tr.x, tr.y, tr.z]
                stamp = t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec
                buf.add(t.header.frame_id, t.child_frame_id, T, stamp, static=m.topic == TOPIC_TF_STATIC)
        return buf

    def add(self, parent: str, child: str, parent_T_child: np.ndarray, stamp_ns: int, static: bool = False) -> None:
        if static:
            self._static[child] = (parent, np.asarray(parent_T_child, float))
            return
        p, stamps, Ts = self._dynamic.setdefault(child, (parent, [], []))
        if p != parent:
            raise BagError(f'frame {child} has two parents, {p} and {parent}: not a tree')
        k = int(np.searchsorted(stamps, stamp_ns))
        if k < len(stamps) and stamps[k] == stamp_ns:
            Ts[k] = np.asarray(parent_T_child, float)
        else:
            stamps.insert(k, int(stamp_ns))
            Ts.insert(k, np.asarray(parent_T_child, float))

    def frames(self) -> set[str]:
        return set(self._static) | set(self._dynamic) | {p for p, _ in self._static.values()} | \
            {v[0] for v in self._dynamic.values()}

    def _to_parent(self, child: str, stamp_ns: int) -> tuple[str, np.ndarray]:
        if child in self._static:
            return self._static[child]
        parent, stamps, Ts = self._dynamic[child]
        k = int(np.searchsorted(stamps, stamp_ns))
        if k < len(stamps) and stamps[k] == stamp_ns:
            return parent, Ts[k]
        if k == 0 or k == len(stamps):
            raise BagError(f'{parent} -> {child} is not known at {stamp_ns} ns (from {stamps[0]} to {stamps[-1]} ns): '
                           'tf does not extrapolate')
        from scipy.spatial.transform import Rotation, Slerp
        a = (stamp_ns - stamps[k - 1]) / (stamps[k] - stamps[k - 1])
        T = np.eye(4)
        T[:3, 3] = (1 - a) * Ts[k - 1][:3, 3] + a * Ts[k][:3, 3]
        T[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix([Ts[k - 1][:3, :3], Ts[k][:3, :3]]))(a).as_matrix()
        return parent, T

    def _chain(self, frame: str, stamp_ns: int) -> list[tuple[str, np.ndarray]]:
        """[(ancestor, ancestor_T_frame)] from `frame` itself (identity) up to the root of its tree."""
        out, T = [(frame, np.eye(4))], np.eye(4)
        while frame in self._static or frame in self._dynamic:
            parent, p_T_f = self._to_parent(frame, stamp_ns)
            T = p_T_f @ T
            frame = parent
            out.append((frame, T.copy()))
            if len(out) > 64:
                raise BagError('the transforms form a loop')
        return out

    def lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        """target_T_source (4x4) at `stamp_ns`: a point in `source` to `target` coordinates."""
        up_source = {f: T for f, T in self._chain(source, stamp_ns)}      # f_T_source
        for f, f_T_target in self._chain(target, stamp_ns):
            if f in up_source:
                return np.linalg.inv(f_T_target) @ up_source[f]
        raise BagError(f'{target} and {source} are not connected (frames: {sorted(self.frames())})')
