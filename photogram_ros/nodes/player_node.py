"""Bag player: publishes a recorded flight onto its topics with the recorded timing.

Messages go out as the CDR bytes stored in the bag (no deserialization), scaled in time by `rate`
(0 = as fast as reliable subscribers acknowledge). `/clock` follows the bag time so nodes can run
with use_sim_time. A damaged bag plays up to the damage and the damage is reported.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from photogram_ros.errors import BagError, ConfigError
from photogram_ros.io.bag import BagReader, msg_class
from photogram_ros.msgs import time_from_ns
from photogram_ros.nodes.diagnostics import ERROR, Diagnostics
from photogram_ros.nodes.node_main import run_job
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param


@dataclass
class PlayerParams:
    bag: str = param('', 'Path of the rosbag2 folder (sqlite3 or MCAP) to play')
    rate: float = param(1.0, 'Playback speed factor; 0 publishes as fast as reliable subscribers acknowledge',
                        min=0.0, max=10000.0)
    topics: str = param('', 'Comma-separated topics to play; empty plays every topic')
    exclude: str = param('', 'Comma-separated topics not to play')
    remap: str = param('', 'Comma-separated renames, e.g. "/fix:=/gps/fix,/cam:=/camera/image_raw"')
    loop: bool = param(False, 'Start again from the beginning when the bag ends')
    publish_clock: bool = param(True, 'Publish /clock with the bag time')
    qos_depth: int = param(200, 'History depth of the reliable publishers when rate > 0', min=1, max=100000)
    wait_for_subscribers: int = param(0, 'Wait until this many subscribers match before playing', min=0,
                                      max=1000)
    wait_timeout_s: float = param(10.0, 'How long to wait for subscribers, s', min=0.0, max=3600.0)

    def topic_list(self, s: str) -> list[str]:
        return [t.strip() for t in s.split(',') if t.strip()]

    def remaps(self) -> dict[str, str]:
        out = {}
        for item in self.topic_list(self.remap):
            if ':=' not in item:
                raise ConfigError(f'remap {item!r} must look like /from:=/to')
            a, b = item.split(':=', 1)
            out[a.strip()] = b.strip()
        return out

    def check(self) -> None:
        self.remaps()


@dataclass
class PlaySummary:
    counts: dict = field(default_factory=dict)       # output topic -> messages
    bytes: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)      # topic -> reason
    errors: list = field(default_factory=list)
    wall_s: float = 0.0
    bag_s: float = 0.0

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def lines(self) -> list[str]:
        out = [f'played {self.total} messages ({sum(self.bytes.values()) / 1e6:.1f} MB) of {self.bag_s:.1f} s '
               f'of bag in {self.wall_s:.1f} s (x{self.bag_s / max(self.wall_s, 1e-9):.1f} real time)']
        for t in sorted(self.counts):
            out.append(f'  {t}: {self.counts[t]} messages, {self.bytes[t] / 1e6:.2f} MB')
        for t, why in sorted(self.skipped.items()):
            out.append(f'  skipped {t}: {why}')
        out += [f'  error: {e}' for e in self.errors]
        return out


class PlayerNode(Node):
    def __init__(self, overrides: dict | None = None, **kwargs):
        super().__init__('player', **kwargs)
        self.params = declare(self, PlayerParams, overrides)
        self.diag = Diagnostics(self)
        self._clock_pub = self.create_publisher(Clock, '/clock', 10)
        self._pubs = {}
        self.stop_requested = False

    def _publisher(self, out_topic: str, msgtype: str):
        if out_topic not in self._pubs:
            # As fast as possible: KEEP_ALL makes a reliable writer wait for acknowledgements
            # instead of overwriting unacknowledged samples, which would drop messages.
            history = HistoryPolicy.KEEP_ALL if self.params.rate == 0 else HistoryPolicy.KEEP_LAST
            qos = QoSProfile(history=history, depth=self.params.qos_depth, reliability=ReliabilityPolicy.RELIABLE)
            self._pubs[out_topic] = self.create_publisher(msg_class(msgtype), out_topic, qos)
        return self._pubs[out_topic]

    def _wait_for_subscribers(self) -> None:
        want = self.params.wait_for_subscribers
        if want <= 0:
            return
        deadline = time.monotonic() + self.params.wait_timeout_s
        while time.monotonic() < deadline:
            if sum(p.get_subscription_count() for p in self._pubs.values()) >= want:
                return
            time.sleep(0.05)
        self.diag.problem(f'only {sum(p.get_subscription_count() for p in self._pubs.values())} of {want} '
                          'subscribers matched before playing')

    def play(self, on_message=None, before_message=None) -> PlaySummary:
        """Play the bag to its end (or until stop_requested); returns what was published.

        `before_message(m)` and `on_message(m)` are called around each publication: an in-process
        consumer uses them to hold the player back until it has caught up.
        """
        p = self.params
        if not p.bag:
            raise ConfigError('player: set the parameter "bag" to the bag folder to play')
        summary = PlaySummary()
        remaps = p.remaps()
        with BagReader(p.bag) as bag:
            infos = bag.topics()
            chosen = p.topic_list(p.topics) or sorted(infos)
            missing = [t for t in chosen if t not in infos]
            if missing:
                raise BagError(f'topics {missing} are not in {p.bag}; it has {sorted(infos)}')
            chosen = [t for t in chosen if t not in set(p.topic_list(p.exclude))]
            playable = []
            for t in chosen:
                try:
                    self._publisher(remaps.get(t, t), infos[t].msgtype)
                    playable.append(t)
                except BagError as exc:
                    summary.skipped[t] = str(exc)
                    self.diag.problem(str(exc), ERROR)
            self._wait_for_subscribers()
            summary.bag_s = bag.duration_ns * 1e-9
            t_wall0 = time.monotonic()
            while True:
                self._play_once(bag, playable, remaps, summary, on_message, before_message)
                summary.errors += bag.errors
                for e in bag.errors:
                    self.diag.problem(e, ERROR)
                bag.errors.clear()
                if not p.loop or self.stop_requested or summary.errors:
                    break
        summary.wall_s = time.monotonic() - t_wall0
        self.diag.publish()
        return summary

    def _play_once(self, bag: BagReader, topics, remaps, summary: PlaySummary, on_message, before_message) -> None:
        p = self.params
        start_ns = bag.start_ns
        wall0 = time.monotonic()
        last_clock_ns = None
        for i, m in enumerate(bag.messages(topics)):
            if self.stop_requested:
                return
            if p.rate > 0:
                delay = wall0 + (m.stamp_ns - start_ns) * 1e-9 / p.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if p.publish_clock and (last_clock_ns is None or m.stamp_ns - last_clock_ns >= 10_000_000):
                self._clock_pub.publish(Clock(clock=time_from_ns(m.stamp_ns)))
                last_clock_ns = m.stamp_ns
            out = remaps.get(m.topic, m.topic)
            pub = self._pubs[out]
            if before_message is not None:
                before_message(m)
            pub.publish(m.data)
            summary.counts[out] = summary.counts.get(out, 0) + 1
            summary.bytes[out] = summary.bytes.get(out, 0) + len(m.data)
            self.diag.count('published')
            if on_message is not None:
                on_message(m)
        if p.rate == 0:
            for pub in self._pubs.values():
                pub.wait_for_all_acked(Duration(seconds=5))


def _play(node) -> int:
    summary = node.play()
    print('\n'.join(summary.lines()))
    return 1 if summary.errors or summary.skipped else 0


def main(argv=None) -> int:
    """Console script `player_node`: plays the bag named by the `bag` parameter."""
    return run_job(PlayerNode, _play, argv)
