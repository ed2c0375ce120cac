"""The project's QoS profiles, in one place, and their per-topic overrides from the parameters file.

Each function returns a new QoSProfile (rclpy changes a profile in place when it applies an override, so none is
shared between two entities):
- `sensor_data(depth)`: best effort, keep last (rclpy's qos_profile_sensor_data is depth 5): what a driver or an
  autopilot bridge streams, and what a radio link may drop (camera info, PX4's uXRCE-DDS topics, the ground
  station's fixes, clouds and tiles);
- `best_effort(depth)`: the same, with the depth the stream needs;
- `reliable(depth)`: reliable, keep last: the pipeline's own streams (fixes, attitude, triggers, keyframes), which
  also match best-effort subscribers;
- `keyframes(depth)`: reliable, keep last 20 unless told: a keyframe and its fix, features and images;
- `keep_all()`: reliable, keep all: a stream that must lose nothing while its reader catches up;
- `latched()`: reliable, transient local, depth 1: a state a late subscriber still gets (the map's origin,
  coverage, control points, the final camera, a node's status);
- `diagnostics()`: reliable, keep last 10: /diagnostics, as diagnostic_updater publishes it;
- `clock()`: reliable, keep last 10: /clock.

Overrides, the ros2/demos way (quality_of_service_demo's qos_overrides_talker / listener): a publisher or
subscription made with `publisher(...)` / `subscription(...)` here declares the read-only ROS parameters
`qos_overrides.<TOPIC>.publisher.<policy>` (or `.subscription.`) for history, depth and reliability, and takes their
values from the parameters file or `--ros-args -p` at start, e.g.

    mavlink_node:
      ros__parameters:
        qos_overrides:
          /gps/fix:
            publisher:
              reliability: best_effort
              depth: 20

`ros2 param dump NODE` lists them with the values in use; nodes/ros_params.py `declare` lets these names through.
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions

# The parameter prefix of rclpy's QoS overrides (rclpy/qos_overriding_options.py).
OVERRIDES_PREFIX = 'qos_overrides.'


def sensor_data(depth: int = 5) -> QoSProfile:
    """Best effort, keep last `depth`, volatile (rclpy's qos_profile_sensor_data at depth 5)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT)


def best_effort(depth: int) -> QoSProfile:
    """Best effort, keep last `depth`."""
    return sensor_data(depth)


def reliable(depth: int = 10) -> QoSProfile:
    """Reliable, keep last `depth`, volatile."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def keyframes(depth: int = 20) -> QoSProfile:
    """A keyframe's topics (image, features, fix): reliable, keep last `depth`."""
    return reliable(depth)


def keep_all() -> QoSProfile:
    """Reliable, keep all: nothing is dropped while the reader catches up (memory grows instead)."""
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1, reliability=ReliabilityPolicy.RELIABLE)


def latched() -> QoSProfile:
    """Reliable, transient local, depth 1: the last message reaches a subscriber that comes later."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def tf() -> QoSProfile:
    """/tf: reliable, keep last 100 (tf2's TransformBroadcaster default)."""
    return reliable(100)


def tf_static() -> QoSProfile:
    """/tf_static: latched (tf2's StaticTransformBroadcaster: reliable, transient local, depth 1)."""
    return latched()


def diagnostics() -> QoSProfile:
    """/diagnostics: reliable, keep last 10."""
    return reliable(10)


def clock() -> QoSProfile:
    """/clock: reliable, keep last 10."""
    return reliable(10)


def overridable(entity_id: str | None = None) -> QoSOverridingOptions:
    """History, depth and reliability overridable from parameters (`entity_id`: tells apart two publishers or two
    subscriptions of one node on one topic)."""
    return QoSOverridingOptions.with_default_policies(entity_id=entity_id)


def publisher(node, msg_type, topic: str, profile: QoSProfile, **kwargs):
    """node.create_publisher with `profile`, overridable per topic from the parameters (module docstring)."""
    return node.create_publisher(msg_type, topic, profile, qos_overriding_options=overridable(), **kwargs)


def subscription(node, msg_type, topic: str, callback, profile: QoSProfile, **kwargs):
    """node.create_subscription with `profile`, overridable per topic from the parameters (module docstring)."""
    return node.create_subscription(msg_type, topic, callback, profile, qos_overriding_options=overridable(),
                                    **kwargs)


def is_override(name: str) -> bool:
    """Whether a parameter name is one of rclpy's QoS overrides (declared when the entity is made, not by the
    node's parameter dataclass)."""
    return name.startswith(OVERRIDES_PREFIX)
