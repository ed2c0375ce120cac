"""Bag player: publishes a recorded flight onto its topics with the recorded timing.

Messages go out as the CDR bytes stored in the bag (no deserialization), scaled in time by `rate`.
`/clock` follows the bag time so nodes can run with use_sim_time. A damaged bag plays up to the
damage and the damage is reported.

rate 0 plays as fast as subscribers acknowledge, and loses nothing to the subscribers that exist
when it starts: it first waits until DDS discovery has matched them (a publisher that starts at once
sends the first seconds of a bag to nobody; the subscriber's own side of the match can come later still on a
loaded machine, so a consumer that must have every message holds the first one back, through `play`'s
`before_message`, until its subscriptions count a publisher), then publishes `ack_window` messages per topic and waits
until every subscriber has acknowledged them. A reliable KEEP_LAST subscriber keeps only its last
`depth` unread messages and acknowledges what it stored, not what its callback took, so nothing but
the pace protects it: one window per acknowledgement round trip (Fast DDS answers in about 5 ms) is
about 1,000-2,000 messages/s a topic with the default window of 10 (measured here), slower than an rclpy callback takes
them. The writer's history is the window itself (KEEP_LAST ack_window): its piggybacked heartbeat
then asks for the acknowledgement at once; a KEEP_ALL writer waits for the periodic heartbeat (3 s).
Now and then (one wait in thirty on a sparse topic beside a busy one) the acknowledgement still
comes only with the periodic heartbeat although the subscriber has the messages: a wait ends after
`ack_timeout_s` and the player goes on (counted as `late_acks`), which lost nothing in the tests.

PX4 uXRCE-DDS topics (px4_msgs/SensorGps, VehicleAttitude) are not played as recorded (px4_msgs has no PyPI
wheel): they go out as what px4_adapter publishes live, /gps/fix_type, /gps/fix and /mavlink/attitude (read
through io/bag_px4.py and core/px4.py's conversions).

MAVROS topics go out under the names the mapper subscribes to (`mavros`, on by default), as their messages are:
/mavros/global_position/raw/fix (NavSatFix, ellipsoidal height) as /gps/fix and /mavros/imu/data (Imu, base_link
FLU in ENU, the convention of mavlink/attitude) as /mavlink/attitude, each only when the bag does not record the
mapper's own topic; an explicit `remap` of a MAVROS topic wins.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from rclpy.duration import Duration
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from photogram_ros.errors import BagError, ConfigError
from photogram_ros.io.bag import BagReader, msg_class, serialize
from photogram_ros.io.bag_px4 import SENSOR_GPS, VEHICLE_ATTITUDE, Px4Records, px4_topics
from photogram_ros.msgs import time_from_ns
from photogram_ros.nodes import qos
from photogram_ros.nodes.diagnostics import ERROR, Diagnostics
from photogram_ros.nodes.node_main import run_job
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param


END_ACK_TIMEOUT_S = 5.0     # rate 0: the last messages of the bag are waited for this long


@dataclass
class PlayerParams:
    bag: str = param('', 'Path of the rosbag2 folder (sqlite3 or MCAP) to play')
    rate: float = param(1.0, 'Playback speed factor; 0 publishes as fast as subscribers acknowledge, ack_window '
                        'messages a round trip', min=0.0, max=10000.0)
    topics: str = param('', 'Comma-separated topics to play; empty plays every topic')
    exclude: str = param('', 'Comma-separated topics not to play')
    remap: str = param('', 'Comma-separated renames, e.g. "/fix:=/gps/fix,/cam:=/camera/image_raw"')
    mavros: bool = param(True, 'Play MAVROS\'s /mavros/global_position/raw/fix as /gps/fix and /mavros/imu/data as '
                         '/mavlink/attitude (each when the bag does not record that topic itself)')
    loop: bool = param(False, 'Start again from the beginning when the bag ends')
    publish_clock: bool = param(True, 'Publish /clock with the bag time')
    qos_depth: int = param(200, 'History depth of the reliable publishers when rate > 0', min=1, max=100000)
    wait_for_subscribers: int = param(0, 'Wait until this many subscribers match before playing', min=0,
                                      max=1000)
    wait_timeout_s: float = param(10.0, 'How long to wait for subscribers, s', min=0.0, max=3600.0)
    ack_window: int = param(10, 'rate 0: messages a topic publishes before waiting for every subscriber to '
                            'acknowledge them (about 5 ms a wait: 10 gives 1,000-2,000 messages/s, which rclpy '
                            'subscribers keep up with; larger is faster and can overrun KEEP_LAST subscribers)',
                            min=1, max=100000)
    ack_timeout_s: float = param(0.1, 'rate 0: longest wait for one window\'s acknowledgements before going on, s '
                                 '(Fast DDS now and then answers only at its next periodic heartbeat, 3 s later, '
                                 'although the subscriber has the messages); the end of the bag waits up to 5 s',
                                 min=0.001, max=3600.0)
    discovery_s: float = param(3.5, 'rate 0: before playing, wait until the matched subscriptions have not changed '
                               'for this long, s (0.25 s once every topic has one), so subscribers that already '
                               'exist are matched (DDS discovery between processes takes up to 3 s here)',
                               min=0.0, max=60.0)

    def topic_list(self, s: str) -> list[str]:
        return [t.strip() for t in s.split(',') if t.strip()]

    def remaps(self) -> dict[str, str]:
        out = {}
        for item in self.topic_list(self.remap):
            if ':=' not in item:
                raise ConfigError(f'remap {item!r} must look like /from:=/to')
            a, b = (v.strip() for v in item.split(':=', 1))
            if not a or not b:
                raise ConfigError(f'remap {item!r} must look like /from:=/to (both topics named)')
            out[a] = b
        return out

    def check(self) -> None:
        self.remaps()


# MAVROS's topic -> the mapper's topic that carries the same message with the same conventions.
MAVROS_INPUTS = {'/mavros/global_position/raw/fix': '/gps/fix', '/mavros/imu/data': '/mavlink/attitude'}


def mavros_remaps(recorded: dict, remaps: dict) -> dict:
    """The renames that play a bag's MAVROS topics as the mapper's (MAVROS_INPUTS), from the bag's topics
    (BagReader.topics()): a MAVROS topic recorded is renamed unless `remaps` renames it already or the bag holds
    another source of the same thing (the mapper's topic itself, raw MAVLink that mavlink_node decodes, or PX4's
    record that the player turns into it)."""
    types = {getattr(i, 'msgtype', '') for i in recorded.values()}
    other = {'/gps/fix': '/mavlink/from_fcu' in recorded or SENSOR_GPS in types,
             '/mavlink/attitude': '/mavlink/from_fcu' in recorded or VEHICLE_ATTITUDE in types}
    return {src: dst for src, dst in MAVROS_INPUTS.items()
            if src in recorded and dst not in recorded and src not in remaps and not other[dst]}


@dataclass
class PlaySummary:
    counts: dict = field(default_factory=dict)       # output topic -> messages
    bytes: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)      # topic -> reason
    errors: list = field(default_factory=list)
    wall_s: float = 0.0
    bag_s: float = 0.0
    subscribers: dict = field(default_factory=dict)  # rate 0: topic -> subscriptions matched before playing
    px4_skipped: dict = field(default_factory=dict)  # PX4 records not published: reason -> count

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def lines(self) -> list[str]:
        out = [f'played {self.total} messages ({sum(self.bytes.values()) / 1e6:.1f} MB) of {self.bag_s:.1f} s '
               f'of bag in {self.wall_s:.1f} s (x{self.bag_s / max(self.wall_s, 1e-9):.1f} real time)']
        for t in sorted(self.counts):
            subs = f', {self.subscribers[t]} subscribers' if t in self.subscribers else ''
            out.append(f'  {t}: {self.counts[t]} messages, {self.bytes[t] / 1e6:.2f} MB{subs}')
        for t, why in sorted(self.skipped.items()):
            out.append(f'  skipped {t}: {why}')
        out += [f'  PX4 records not published: {n}, {why}' for why, n in sorted(self.px4_skipped.items())]
        out += [f'  error: {e}' for e in self.errors]
        return out


PX4_OUTPUTS = {'/gps/fix_type': 'std_msgs/msg/UInt8', '/gps/fix': 'sensor_msgs/msg/NavSatFix',
               '/mavlink/attitude': 'sensor_msgs/msg/Imu'}


class Px4Playback:
    """Recorded PX4 messages -> [(output topic, CDR)] as px4_adapter publishes them, with its default frames and
    attitude sigmas; what cannot be used is counted in `skipped` (reason -> count)."""

    def __init__(self, topics: dict, definitions: dict | None = None):
        from photogram_ros.nodes.px4_adapter import Px4AdapterParams
        self.topics = dict(topics)            # recorded topic -> px4_msgs type
        self.records = Px4Records(definitions)     # msgtype -> the .msg text the bag recorded
        self.p = Px4AdapterParams()
        self.skipped: dict = {}

    def outputs(self) -> dict:
        """Output topic -> message type, for the topics this bag's PX4 records give."""
        types = set(self.topics.values())
        keep = ('/gps/fix_type', '/gps/fix') if SENSOR_GPS in types else ()
        keep += ('/mavlink/attitude',) if types - {SENSOR_GPS} else ()
        return {t: PX4_OUTPUTS[t] for t in keep}

    def messages(self, m) -> list:
        from photogram_ros.nodes.px4_adapter import attitude_message, fix_messages
        kind, stamp_ns, value = self.records.read(m.msgtype, m.stamp_ns, m.data)
        if kind == 'fix':
            fix_type, navsat = fix_messages(value, stamp_ns, self.p.frame_id)
            return [('/gps/fix_type', serialize(fix_type)), ('/gps/fix', serialize(navsat))]
        if kind == 'attitude':
            var = (self.p.attitude_sigma_rp_rad ** 2, self.p.attitude_sigma_rp_rad ** 2,
                   self.p.attitude_sigma_yaw_rad ** 2)
            return [('/mavlink/attitude', serialize(attitude_message(stamp_ns, value, var, self.p.attitude_frame_id)))]
        self.skipped[value] = self.skipped.get(value, 0) + 1
        return []


class PlayerNode(Node):
    def __init__(self, overrides: dict | None = None, **kwargs):
        super().__init__('player', **kwargs)
        self.params = declare(self, PlayerParams, overrides)
        self.diag = Diagnostics(self)
        self._clock_pub = self.create_publisher(Clock, '/clock', qos.clock())
        self._pubs = {}
        self._px4 = None
        self.stop_requested = False

    def _publisher(self, out_topic: str, msgtype: str):
        if out_topic not in self._pubs:
            # rate 0: the history is one acknowledgement window (see the module docstring).
            depth = self.params.ack_window if self.params.rate == 0 else self.params.qos_depth
            self._pubs[out_topic] = self.create_publisher(msg_class(msgtype), out_topic, qos.reliable(depth))
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

    def _wait_for_discovery(self) -> dict:
        """rate 0: wait until the matched subscriptions stop changing; topic -> subscriptions matched."""
        p = self.params
        deadline = time.monotonic() + p.wait_timeout_s
        counts = {t: pub.get_subscription_count() for t, pub in self._pubs.items()}
        since = time.monotonic()
        while time.monotonic() < deadline:
            time.sleep(0.05)
            now = {t: pub.get_subscription_count() for t, pub in self._pubs.items()}
            if now != counts:
                counts, since = now, time.monotonic()
            settle = min(0.25, p.discovery_s) if counts and all(counts.values()) else p.discovery_s
            if time.monotonic() - since >= settle:
                break
        return counts

    def _wait_acked(self, topic: str, pub, at_end: bool = False) -> None:
        if pub.get_subscription_count() == 0:
            return
        timeout = max(self.params.ack_timeout_s, END_ACK_TIMEOUT_S) if at_end else self.params.ack_timeout_s
        t0 = time.monotonic()
        ok = pub.wait_for_all_acked(Duration(seconds=timeout))
        self.diag.count('ack_waits')
        self.diag.count('ack_wait_ms', int(1000 * (time.monotonic() - t0)))
        if not ok:
            self.diag.count('late_acks')
            if at_end:
                self.diag.problem(f'{topic}: a subscriber did not acknowledge the last messages within {timeout} s '
                                  '(it may have lost them)')

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
            if p.mavros:
                remaps.update(mavros_remaps(infos, remaps))
            chosen = p.topic_list(p.topics) or sorted(infos)
            missing = [t for t in chosen if t not in infos]
            if missing:
                raise BagError(f'topics {missing} are not in {p.bag}; it has {sorted(infos)}')
            chosen = [t for t in chosen if t not in set(p.topic_list(p.exclude))]
            px4 = px4_topics({t: infos[t] for t in chosen})
            self._px4 = Px4Playback(px4, {m: bag.message_definition(t) for t, m in px4.items()}) if px4 else None
            playable = list(px4)
            for out, msgtype in (self._px4.outputs().items() if self._px4 else ()):
                self._publisher(remaps.get(out, out), msgtype)
            for t in (t for t in chosen if t not in px4):
                try:
                    self._publisher(remaps.get(t, t), infos[t].msgtype)
                    playable.append(t)
                except BagError as exc:
                    summary.skipped[t] = str(exc)
                    self.diag.problem(str(exc), ERROR)
            self._wait_for_subscribers()
            if p.rate == 0:
                summary.subscribers = self._wait_for_discovery()
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
        if self._px4 is not None:
            summary.px4_skipped = dict(self._px4.skipped)
            self.diag.count('px4_records_skipped', sum(self._px4.skipped.values()))
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
            if before_message is not None:
                before_message(m)
            if self._px4 is not None and m.topic in self._px4.topics:
                outs = self._px4.messages(m)
            else:
                outs = [(m.topic, m.data)]
            for topic, data in outs:
                self._publish(remaps.get(topic, topic), data, summary)
            if on_message is not None:
                on_message(m)
        if p.rate == 0:
            for topic, pub in self._pubs.items():
                self._wait_acked(topic, pub, at_end=True)

    def _publish(self, out: str, data: bytes, summary: PlaySummary) -> None:
        pub = self._pubs[out]
        pub.publish(data)
        n_out = summary.counts.get(out, 0) + 1
        summary.counts[out] = n_out
        if self.params.rate == 0 and n_out % self.params.ack_window == 0:
            self._wait_acked(out, pub)
        summary.bytes[out] = summary.bytes.get(out, 0) + len(data)
        self.diag.count('published')


def _play(node) -> int:
    summary = node.play()
    print('\n'.join(summary.lines()))
    return 1 if summary.errors or summary.skipped else 0


def main(argv=None) -> int:
    """Console script `player_node`: plays the bag named by the `bag` parameter."""
    return run_job(PlayerNode, _play, argv)
