"""Recorder: subscribes to topics as raw CDR and writes them to a bag (MCAP by default, as ROS 2 Jazzy)
with their receive times and the publishers' QoS profiles.

Whatever the storage, what was received is made durable every `checkpoint_s` (2 s): a recording cut
short by kill -9 or a power loss keeps everything but its last seconds (io/bag.py BagWriter)."""

from __future__ import annotations

import threading
import time

import rclpy
from rclpy.node import Node
from rclpy.qos import ReliabilityPolicy

from photogram_ros.errors import BagError
from photogram_ros.io.bag import BagWriter, msg_class
from photogram_ros.nodes import qos


class Recorder:
    def __init__(self, out: str, topics: list[str], storage: str = 'mcap', node_name: str = 'recorder',
                 checkpoint_s: float = 2.0):
        self.node = Node(node_name)
        self.topics = topics
        self.writer = BagWriter(out, storage=storage, checkpoint_s=checkpoint_s)
        self.writer.__enter__()
        self._lock = threading.Lock()
        self._subs = {}
        self.count = 0

    def _subscribe_discovered(self) -> None:
        for name, types in self.node.get_topic_names_and_types():
            if name in self.topics and name not in self._subs:
                msgtype = types[0]
                publishers = self.node.get_publishers_info_by_topic(name)
                self.writer.add_topic(name, msgtype, qos=[i.qos_profile for i in publishers])
                # Reliable loses nothing, but a reliable subscription does not match best-effort
                # publishers (sensor-data QoS), so those are recorded best-effort.
                reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in publishers)
                profile = qos.reliable(1000) if reliable else qos.best_effort(1000)
                self._subs[name] = self.node.create_subscription(
                    msg_class(msgtype), name, lambda data, t=name: self._on_message(t, data), profile, raw=True)

    def _on_message(self, topic: str, data: bytes) -> None:
        with self._lock:
            self.writer.write_raw(topic, time.time_ns(), data)
            self.count += 1

    def run(self, duration_s: float = 0.0, max_count: int = 0, discovery_timeout_s: float = 10.0,
            stop: threading.Event | None = None) -> int:
        """Record until `duration_s`, `max_count` messages, `stop` set (a signal) or Ctrl-C; returns the count."""
        stop = stop or threading.Event()
        start = time.monotonic()
        while len(self._subs) < len(self.topics) and not stop.is_set():
            self._subscribe_discovered()
            if time.monotonic() - start > discovery_timeout_s:
                missing = sorted(set(self.topics) - set(self._subs))
                if not self._subs:
                    raise BagError(f'none of the topics {missing} appeared within {discovery_timeout_s} s')
                self.node.get_logger().warning(f'recording without {missing}: not published yet')
                break
            rclpy.spin_once(self.node, timeout_sec=0.05)
        start = time.monotonic()
        try:
            while rclpy.ok() and not stop.is_set():
                rclpy.spin_once(self.node, timeout_sec=0.05)
                if duration_s and time.monotonic() - start >= duration_s:
                    break
                if max_count and self.count >= max_count:
                    break
                if len(self._subs) < len(self.topics):
                    self._subscribe_discovered()
                with self._lock:   # also when nothing more arrives
                    self.writer.checkpoint_if_due()
        except KeyboardInterrupt:
            pass
        return self.count

    def close(self) -> None:
        self.writer.__exit__(None, None, None)
        self.node.destroy_node()
