"""Replay a flight bag through the whole mapping graph in one process, then export and report.

The player feeds the graph as fast as it keeps up (or at a set rate): after each image it waits
until the tracker has taken that frame, so a fast replay never drops frames the way a live camera
overload would, and while a node after the tracker (possibly in the child process) is more than
`max_lag_keyframes` behind, so the queues between them, and the memory, stay bounded. When the bag ends the graph drains (keyframes -> bundle -> stereo -> map), the bundle
runs its final adjustment, the map flushes, and the exports and the report are written.

One time base: every node runs with use_sim_time and takes the bag's time from the player's /clock,
so what a node stamps itself (/diagnostics, the map's streams) lies in the bag's time span like the
recorded data. The player is not spun (it only publishes): the replay sets its clock to each message's time.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.time import Time

from photogram_ros.nodes.diagnostics import PROBLEM_SEPARATOR
from photogram_ros.nodes.graph import Graph, GraphSpec
from photogram_ros.nodes.player_node import PlayerNode

IMAGE_TOPICS = ('/camera/image_raw', '/camera/image_raw/compressed')


@dataclass
class ReplayOptions:
    bag: str
    out: str
    params_file: str | None = None
    rate: float = 0.0
    frame_timeout_s: float = 30.0
    drain_timeout_s: float = 300.0
    progress: bool = True
    extra: dict = field(default_factory=dict)
    # Roles run in a child process, on the second core (the tracker, which paces the player, and the
    # MAVLink decoder stay in this one): () runs everything in one process.
    child_roles: tuple = ()
    quiet_s: float = 1.0   # the graph has drained once nothing happened for this long (and nothing is queued)
    # The player also waits while a node after the tracker is more than this many keyframes (or pair
    # clouds) behind it; 0 = never. Without it a fast tracker outruns a slower child process: the
    # backlog grew the memory with the flight's length, and past stereo's max_keyframes (80) stereo
    # dropped keyframe images before their poses came, so whole stretches got no cloud.
    max_lag_keyframes: int = 30
    # The replay stops (StorageError) when the disk of `out` has less than this free, and does not
    # start: a full disk fails every write of the map and the products, and the backpressure would
    # then wait frame_timeout_s on every frame for a map that cannot keep up.
    min_free_mb: float = 20.0


class DiagnosticsLog:
    """Keeps the latest values and every distinct problem of each node, with replay-relative times."""

    def __init__(self, node: Node):
        self.t0 = time.monotonic()
        self.nodes: dict = {}
        self._lock = threading.Lock()
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on, 100)

    def _on(self, msg: DiagnosticArray) -> None:
        t = time.monotonic() - self.t0
        with self._lock:
            for st in msg.status:
                d = self.nodes.setdefault(st.name, {'values': {}, 'problems': [], 'level': 0})
                d['values'] = {kv.key: _num(kv.value) for kv in st.values}
                level = st.level if isinstance(st.level, int) else int.from_bytes(st.level, 'little')
                d['level'] = max(d['level'], level)
                if level > 0:
                    for text in st.message.split(PROBLEM_SEPARATOR):
                        if not d['problems'] or d['problems'][-1][1] != text:
                            d['problems'].append((round(t, 2), text))

    def snapshot(self) -> dict:
        with self._lock:
            return json.loads(json.dumps(self.nodes))


def _num(v: str):
    try:
        f = float(v)
        return int(f) if f.is_integer() and 'e' not in v and '.' not in v else f
    except ValueError:
        return v


def downstream_lag(counts: dict) -> int:
    """How far the nodes after the tracker are behind it, from the graph's diagnostic counters: the
    most keyframes one of them has not finished with (bundle: adjusted or given up; stereo and map:
    image taken), or the pair clouds the map has not fused yet. A node whose counter has not
    appeared yet (nothing done yet, or a feature turned off) is not waited for."""
    kf = counts.get('tracker', {}).get('keyframes', 0)
    lags = [0]
    b = counts.get('bundle', {})
    if 'keyframes_received' in b:
        lags.append(kf - sum(b.get(k, 0) for k in ('keyframes_oriented', 'keyframes_not_oriented', 'keyframes_failed')))
    if 'images' in counts.get('stereo', {}):
        lags.append(kf - counts['stereo']['images'])
    m = counts.get('map', {})
    if 'keyframes_saved' in m:
        lags.append(kf - m['keyframes_saved'])
    if 'stereo' in counts and 'map' in counts:
        lags.append(counts['stereo'].get('pairs_done', 0) - m.get('clouds', 0) - m.get('clouds_dropped', 0))
    return max(lags)


def _activity(graph: Graph) -> int:
    """A number that grows while any node is still working (sum of its diagnostic counters)."""
    return int(sum(v for c in graph.counts().values() for v in c.values() if isinstance(v, (int, float))))


CHILD_ROLES_ALLOWED = ('bundle', 'stereo', 'map')


def start_clock(node: Node, nodes: list, start_ns: int, timeout_s: float = 10.0) -> bool:
    """Publish the bag's start on /clock (from `node`) until every node of `nodes` has it: under use_sim_time
    a node's clock reads 0 until its first /clock, and the first recorded messages must not meet that (the
    MAVLink decoder would take 0 for their arrival time). Returns whether all did within `timeout_s`."""
    from rosgraph_msgs.msg import Clock

    from photogram_ros.msgs import time_from_ns
    pub = node.create_publisher(Clock, '/clock', 10)
    deadline = time.monotonic() + timeout_s
    try:
        while any(n.get_clock().now().nanoseconds == 0 for n in nodes):
            if time.monotonic() > deadline:
                return False
            pub.publish(Clock(clock=time_from_ns(start_ns)))
            time.sleep(0.01)
        return True
    finally:
        node.destroy_publisher(pub)


def check_free_space(out: Path, min_free_mb: float, when: str) -> None:
    """A StorageError unless the disk holding `out` has `min_free_mb` free."""
    import shutil

    from photogram_ros.errors import StorageError
    free_mb = shutil.disk_usage(out).free / 1e6
    if free_mb < min_free_mb:
        raise StorageError(f'the disk of {out} has {free_mb:.1f} MB free {when} (a replay needs at least '
                           f'{min_free_mb:.0f} MB for the map and the products): free space, or choose another '
                           '--out', 28)


def run_replay(opts: ReplayOptions, context=None) -> dict:
    """Run the whole replay into OUT/map; returns the run summary, the diagnostics log and the map folder."""
    from photogram_ros.errors import BagError, ConfigError
    from photogram_ros.io.bag import BagReader
    out = Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    check_free_space(out, opts.min_free_mb, 'before the replay')
    map_dir = out / 'map'
    with BagReader(opts.bag) as bag:
        topics = bag.topics()
        bag_start_ns = bag.start_ns
        bag_warnings = list(bag.warnings)
        for line in bag.health():     # before the first frame: the user knows what will be mapped
            print(line, flush=True)
    if not any(t in topics for t in IMAGE_TOPICS):
        raise BagError(f'{opts.bag} has no camera images ({" or ".join(IMAGE_TOPICS)}): nothing to map; '
                       f'it has {sorted(topics)}')
    exclude = []
    extra = {role: dict(v) for role, v in opts.extra.items()}
    extra.setdefault('map', {})['map_dir'] = str(map_dir)
    if '/mavlink/from_fcu' in topics:
        # The MAVLink node decodes the raw stream; the recorded /gps/fix would be a second source.
        exclude.append('/gps/fix')
        extra.setdefault('mavlink', {}).update({'url': '', 'input_topic': '/mavlink/from_fcu'})
        roles = ('mavlink', 'tracker', 'bundle', 'stereo', 'map')
    else:
        roles = ('tracker', 'bundle', 'stereo', 'map')
    for role in roles:
        extra.setdefault(role, {})['use_sim_time'] = True
    bad = [r for r in opts.child_roles if r not in CHILD_ROLES_ALLOWED]
    if bad:
        raise ConfigError(f'replay: {bad} cannot run in the child process; choose among {CHILD_ROLES_ALLOWED} '
                          '(the tracker and MAVLink decoder pace the player and stay in the main process)')
    graph = Graph(GraphSpec(roles=roles, params_file=opts.params_file, extra=extra,
                            child_roles=tuple(opts.child_roles)), context=context)
    kwargs = {'context': context} if context is not None else {}
    player = PlayerNode(overrides={'bag': str(opts.bag), 'rate': float(opts.rate), 'exclude': ','.join(exclude)},
                        parameter_overrides=[Parameter('use_sim_time', value=True)], **kwargs)
    player_clock = player.get_clock()
    listener = Node('replay_monitor', **kwargs)
    diag_log = DiagnosticsLog(listener)
    graph.executor.add_node(listener)
    # The player only publishes: not spinning it keeps its entities out of the executor's wait set,
    # which the Python executor rebuilds on every wake-up (its largest CPU cost in a replay).
    try:
        graph.start()
    except Exception:
        graph.shutdown()
        raise
    start_clock(listener, list(graph.nodes.values()), bag_start_ns)
    tracker = graph.nodes['tracker']
    images_sent = [0]
    t_start = time.monotonic()
    last_print = [0.0]

    mavlink = graph.nodes.get('mavlink')
    packets_sent = [0]
    lag_slack = [0]      # keyframes a node will never count (lost, failed without a count): not waited for
    lag_wait_s = [0.0]

    def wait_for(done, deadline_s):
        deadline = time.monotonic() + deadline_s
        while not done() and time.monotonic() < deadline:
            time.sleep(0.002)

    def before_message(m):
        if m.topic not in IMAGE_TOPICS:
            return
        # Telemetry up to a frame's time must be decoded before the tracker sees the frame, as it
        # would be live; otherwise the fix a keyframe needs may still sit in a queue.
        if mavlink is not None:
            wait_for(lambda: mavlink.messages_in >= packets_sent[0], opts.frame_timeout_s)
        # The tracker must have taken the previous frame. Waiting here rather than right after that
        # frame lets the messages recorded with it (its camera_info) reach the tracker meanwhile.
        wait_for(lambda: tracker.frames_done >= images_sent[0], opts.frame_timeout_s)
        check_free_space(out, opts.min_free_mb, f'after {images_sent[0]} frames (the map so far is in {map_dir})')
        if opts.max_lag_keyframes > 0:
            wait_downstream()

    def wait_downstream():
        """Hold the player while a later node lags the tracker by more than max_lag_keyframes. A lag
        that does not shrink within frame_timeout_s is accepted from then on (a keyframe that never
        shows in a counter must not stall every later frame)."""
        if downstream_lag(graph.counts()) - lag_slack[0] <= opts.max_lag_keyframes:
            return
        t0 = time.monotonic()
        wait_for(lambda: downstream_lag(graph.counts()) - lag_slack[0] <= opts.max_lag_keyframes,
                 opts.frame_timeout_s)
        lag = downstream_lag(graph.counts())
        if lag - lag_slack[0] > opts.max_lag_keyframes:
            lag_slack[0] = lag - opts.max_lag_keyframes
        lag_wait_s[0] += time.monotonic() - t0

    def on_message(m):
        player_clock.set_ros_time_override(Time(nanoseconds=m.stamp_ns, clock_type=ClockType.ROS_TIME))
        if m.topic == '/mavlink/from_fcu':
            packets_sent[0] += 1
        elif m.topic in IMAGE_TOPICS:
            images_sent[0] += 1
        if opts.progress and time.monotonic() - last_print[0] > 2.0:
            last_print[0] = time.monotonic()
            _print_progress(graph, images_sent[0], m.stamp_ns, t_start)

    def clouds_in_flight() -> int:
        """Pair clouds stereo has published that the map has not fused yet (fusing one can take seconds)."""
        counts = graph.counts()
        if 'stereo' not in counts or 'map' not in counts:
            return 0
        fused = counts['map']
        return (counts['stereo'].get('pairs_done', 0)
                - fused.get('clouds', 0) - fused.get('clouds_dropped', 0))

    def keyframes_in_flight() -> int:
        """Keyframes the tracker published that the bundle adjuster has not received yet."""
        counts = graph.counts()
        if 'tracker' not in counts or 'bundle' not in counts:
            return 0
        return max(0, counts['tracker'].get('keyframes', 0) - counts['bundle'].get('keyframes_received', 0))

    def drain():
        """Wait until every keyframe reached the adjuster and is adjusted, every cloud is fused, and no
        node has done anything for a moment (a pose on its way to stereo shows in no counter)."""
        quiet_since, last = time.monotonic(), _activity(graph)
        deadline = time.monotonic() + opts.drain_timeout_s
        while time.monotonic() < deadline:
            time.sleep(0.1)
            now = _activity(graph)
            if now != last or clouds_in_flight() > 0 or keyframes_in_flight() > 0 or graph.busy():
                quiet_since, last = time.monotonic(), now
            elif time.monotonic() - quiet_since > opts.quiet_s:
                return

    try:
        summary = player.play(on_message=on_message, before_message=before_message)
        drain()
        end = graph.finish_flight(settle=drain)
        wall_s = time.monotonic() - t_start
    finally:   # whatever happened, the map node flushes what it fused
        graph.shutdown()
        player.destroy_node()
        listener.destroy_node()
    _record_flight_end(map_dir, end.as_dict())
    run = {'bag': str(opts.bag), 'frames': images_sent[0], 'bag_s': summary.bag_s, 'wall_s': wall_s,
           'real_time_factor': summary.bag_s / max(wall_s, 1e-9), 'messages': summary.total,
           'bag_errors': summary.errors, 'skipped_topics': summary.skipped,
           'waited_for_downstream_s': round(lag_wait_s[0], 1),
           'bag_read': {t: [i.count, i.expected] for t, i in topics.items()}, 'bag_warnings': bag_warnings,
           'final_adjustment': end.final_adjustment, 'end_of_flight_errors': end.errors}
    if end.reason:
        run['final_adjustment_reason'] = end.reason
    return {'run': run, 'diagnostics': diag_log.snapshot(), 'map_dir': str(map_dir), 'flight_end': end}


def _record_flight_end(map_dir: Path, end: dict) -> None:
    """flight_end.json in the map folder (after the map node is gone: it writes map.json itself)."""
    from photogram_ros.errors import PhotogramError
    from photogram_ros.io.map_store import MapStore
    try:
        MapStore(map_dir).save_flight_end(end)
    except (PhotogramError, OSError) as exc:
        print(f'note: {map_dir} could not record how the flight ended: {exc}', flush=True)


def _print_progress(graph: Graph, frames: int, stamp_ns: int, t_start: float) -> None:
    parts = [f'frames {frames}']
    for role, c in graph.counts().items():
        key = {'tracker': 'keyframes', 'bundle': 'keyframes_adjusted', 'stereo': 'pairs_done',
               'map': 'points_fused'}.get(role)
        if key and key in c:
            parts.append(f'{role} {key.replace("_", " ")} {c[key]}')
    print(f'[replay {time.monotonic() - t_start:6.1f} s] ' + ', '.join(parts), flush=True)
