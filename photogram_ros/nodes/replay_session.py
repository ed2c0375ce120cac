"""Replay a flight (a bag, a folder of photos or a video with its GNSS log) through the whole mapping
graph, then export and report.

A bag is played by the player node; a photo folder or a video by the camera node (nodes/camera_node.py:
EXIF time order, EXIF GPS and intrinsics for photos, a fix log for a video), driven frame by frame
from here with the same waits. Either way the replay ends by itself at the source's end.

The player feeds the graph as fast as it keeps up (or at a set rate): after each image it waits
until the tracker has taken that frame, so a fast replay never drops frames the way a live camera
overload would, and while a node after the tracker (possibly in the child process) is more than
`max_lag_keyframes` behind, so the queues between them, and the memory, stay bounded. When the bag
ends the graph drains (keyframes -> bundle -> stereo -> map), the bundle runs its final adjustment,
the map flushes, and the exports and the report are written.

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

from photogram_ros.core.incremental import AUTO_CANDIDATES, PASS_GROWTH_RATIO
from photogram_ros.io.bag_px4 import SENSOR_GPS, VEHICLE_ATTITUDE
from photogram_ros.io.control_file import ControlInput
from photogram_ros.io.progress import Progress, Steps, say_stdout
from photogram_ros.nodes import qos
from photogram_ros.nodes.diagnostics import PROBLEM_SEPARATOR
from photogram_ros.nodes.graph import NODES, Graph, GraphSpec, WorkWatch, set_by_command
from photogram_ros.nodes.player_node import MAVROS_INPUTS, PlayerNode, mavros_remaps

IMAGE_TOPICS = ('/camera/image_raw', '/camera/image_raw/compressed')


@dataclass
class ReplayOptions:
    bag: str                     # a rosbag2 folder / .db3 / .mcap / ROS 1 .bag, a photo folder or a video file
    out: str
    params_file: str | None = None
    rate: float = 0.0
    frame_timeout_s: float = 30.0
    drain_timeout_s: float = 300.0
    progress: bool = True        # progress lines on stdout (io/progress.py): frames, then the end-of-flight steps
    progress_every_s: float = 2.0
    extra: dict = field(default_factory=dict)
    # Roles run in a child process, on the second core (the tracker, which paces the player, and the
    # MAVLink decoder stay in this one): () runs everything in one process.
    child_roles: tuple = ()
    quiet_s: float = 1.0   # the graph has drained once nothing happened for this long (and nothing is queued)
    # Work counted in flight between nodes while no counter moved and no node was busy for this long was
    # lost on the way: not waited for (Graph.drain), said in the run's `drain_gave_up`.
    stall_s: float = 30.0
    # The player also waits while a node after the tracker is more than this many keyframes (or pair
    # clouds) behind it; 0 = never. Without it a fast tracker outruns a slower child process: the
    # backlog grew the memory with the flight's length, and past stereo's max_keyframes (80) stereo
    # dropped keyframe images before their poses came, so whole stretches got no cloud.
    max_lag_keyframes: int = 30
    # That wait ends early when the lagging nodes have stalled: no mapping counter moved, no node busy
    # and the second process not computing for this long (else a stalled node costs frame_timeout_s at
    # each new keyframe: minutes at the end of a flight).
    lag_stall_s: float = 5.0
    # The replay stops (StorageError) when the disk of `out` has less than this free, and does not
    # start: a full disk fails every write of the map and the products, and the backpressure would
    # then wait frame_timeout_s on every frame for a map that cannot keep up.
    min_free_mb: float = 20.0
    # Photo folders and videos (camera_node's parameters of the same names; "" = not set).
    calibration_file: str = ''   # needed for a video; a photo folder takes its camera from the EXIF
    gnss_log: str = ''           # a video's fixes (io/image_source.read_fix_log)
    video_start_unix_s: float = 0.0
    # The flight's control file as the command read it (io/control_file.ControlInput; --gcp): handed to the
    # bundle node's stage through the graph (GraphSpec.control). None: the parameter file's control_file, if any.
    control: ControlInput | None = None


BAG_SUFFIXES = ('.db3', '.mcap', '.bag')


def source_kind(path) -> str:
    """'bag' (a rosbag2 folder, a .db3/.mcap file, a ROS 1 .bag), 'photos' (any other folder) or 'video'
    (any other file); a ConfigError when `path` does not exist."""
    from photogram_ros.errors import ConfigError
    p = Path(path)
    if p.is_dir():
        bag = (p / 'metadata.yaml').exists() or any(p.glob('*.db3')) or any(p.glob('*.mcap'))
        return 'bag' if bag else 'photos'
    if p.is_file():
        return 'bag' if p.suffix.lower() in BAG_SUFFIXES else 'video'
    raise ConfigError(f'{path} is neither a flight bag, a folder of photos nor a video file')


class DiagnosticsLog:
    """Keeps the latest values and every distinct problem of each node, with replay-relative times."""

    def __init__(self, node: Node):
        self.t0 = time.monotonic()
        self.nodes: dict = {}
        self._lock = threading.Lock()
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on, qos.reliable(100))

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
                        # The level each problem came with: the report names the reasons of a node's worst.
                        levels = d.setdefault('problem_levels', {})
                        levels[text] = max(levels.get(text, 0), level)

    def add(self, counts: dict, graph_names: dict) -> None:
        """The nodes' last counters (Graph.counts(), read after the flight: /diagnostics is up to a period
        behind), over the values heard; `graph_names`: role -> the node's /diagnostics name."""
        with self._lock:
            for role, c in counts.items():
                name = graph_names.get(role, role)
                d = self.nodes.setdefault(name, {'values': {}, 'problems': [], 'level': 0})
                d['values'].update(c)

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


CHILD_ROLES_ALLOWED = ('bundle', 'stereo', 'map')


def start_clock(pub, nodes: list, start_ns: int, timeout_s: float = 10.0) -> bool:
    """Publish the bag's start on /clock (`pub`) until every node of `nodes` has it: under use_sim_time
    a node's clock reads 0 until its first /clock, and the first recorded messages must not meet that (the
    MAVLink decoder would take 0 for their arrival time). Returns whether all did within `timeout_s`.
    `pub` is made before the executor spins and kept: destroying it while another thread waits on the
    node's entities kills that thread (rclpy's InvalidHandle)."""
    from rosgraph_msgs.msg import Clock

    from photogram_ros.msgs import time_from_ns
    deadline = time.monotonic() + timeout_s
    while any(n.get_clock().now().nanoseconds == 0 for n in nodes):
        if time.monotonic() > deadline:
            return False
        pub.publish(Clock(clock=time_from_ns(start_ns)))
        time.sleep(0.01)
    return True


def check_free_space(out: Path, min_free_mb: float, when: str) -> None:
    """A StorageError unless the disk holding `out` has `min_free_mb` free."""
    import shutil

    from photogram_ros.errors import StorageError
    free_mb = shutil.disk_usage(out).free / 1e6
    if free_mb < min_free_mb:
        raise StorageError(f'the disk of {out} has {free_mb:.1f} MB free {when} (a replay needs at least '
                           f'{min_free_mb:.0f} MB for the map and the products): free space, or choose another '
                           '--out', 28)


def _bag_setup(opts: ReplayOptions, extra: dict):
    """Roles, the player's exclusions and the bag's start time for a bag replay (topics checked)."""
    from photogram_ros.errors import BagError
    from photogram_ros.io.bag import BagReader
    with BagReader(opts.bag) as bag:
        topics = bag.topics()
        start_ns = bag.start_ns
        warnings = list(bag.warnings)
        for line in bag.health():     # before the first frame: the user knows what will be mapped
            print(line, flush=True)
    if not any(t in topics for t in IMAGE_TOPICS):
        raise BagError(f'{opts.bag} has no camera images ({" or ".join(IMAGE_TOPICS)}): nothing to map; '
                       f'it has {sorted(topics)}')
    exclude = []
    if '/mavlink/from_fcu' in topics:
        # The MAVLink node decodes the raw stream; the recorded /gps/fix would be a second source.
        exclude.append('/gps/fix')
        extra.setdefault('mavlink', {}).update({'url': '', 'input_topic': '/mavlink/from_fcu'})
        roles = ('mavlink', 'tracker', 'bundle', 'stereo', 'map')
    else:
        roles = ('tracker', 'bundle', 'stereo', 'map')
        if SENSOR_GPS in {i.msgtype for i in topics.values()}:
            # The player publishes PX4's fixes as /gps/fix (nodes/player_node.Px4Playback): a recorded one would
            # be a second source.
            exclude += [t for t in ('/gps/fix', '/gps/fix_type') if t in topics]
    if not bag_has_attitude(topics, player_plays_mavros(opts, extra, roles)):
        no_body_lever_arm(opts, extra, roles, 'the bag records no attitude (no /mavlink/from_fcu, no mavlink/attitude, '
                          'no PX4 VehicleAttitude)')
    return roles, exclude, topics, start_ns, warnings


MAVROS_FIX_TOPIC = next(src for src, dst in MAVROS_INPUTS.items() if dst == '/gps/fix')


def player_plays_mavros(opts: ReplayOptions, extra: dict, roles: tuple) -> bool:
    """Whether the player plays a bag's MAVROS topics under the mapper's names (player_node `mavros`): not when
    tracker_node is set to take MAVROS's fix by its own name (`fix_topic`, docs/nodes.md), which the renamed
    topic would no longer reach."""
    from photogram_ros.nodes.graph import GraphSpec, role_values
    tracker = role_values(GraphSpec(roles=roles, params_file=opts.params_file, extra=extra), 'tracker')
    return str(tracker.get('fix_topic', '')).lstrip('/') != MAVROS_FIX_TOPIC.lstrip('/')


def bag_has_attitude(topics, mavros_played: bool = True) -> bool:
    """The bag's topics (BagReader.topics()) carry the body's attitude: raw MAVLink (ATTITUDE), mavlink_node's
    output, MAVROS's imu/data when the player plays it as /mavlink/attitude (`mavros_played`), or PX4's
    VehicleAttitude."""
    return ('/mavlink/from_fcu' in topics or any(t.endswith('mavlink/attitude') for t in topics)
            or (mavros_played and '/mavlink/attitude' in mavros_remaps(topics, {}).values())
            or any(getattr(i, 'msgtype', '') == VEHICLE_ATTITUDE for i in topics.values()))


def no_body_lever_arm(opts: ReplayOptions, extra: dict, roles: tuple, why: str) -> bool:
    """A body lever arm turns with the body's attitude: without one it is not applied (a note says so).
    Returns whether one was set (and is now zero in `extra`)."""
    from photogram_ros.nodes.graph import GraphSpec, role_values
    bundle = role_values(GraphSpec(roles=roles, params_file=opts.params_file, extra=extra), 'bundle')
    arm = bundle.get('lever_arm_body_frd_m')
    if arm is not None and any(float(v) for v in arm):
        extra.setdefault('bundle', {})['lever_arm_body_frd_m'] = [0.0, 0.0, 0.0]
        print(f'note: {opts.params_file}: the body lever arm {list(arm)} m is not applied: {why} to turn it with',
              flush=True)
        return True
    return False


def _camera_setup(opts: ReplayOptions, extra: dict) -> tuple:
    """Roles for a photo folder or a video played by the camera node, driven from the replay."""
    cam = extra.setdefault('camera', {})
    cam.update({'source': str(opts.bag), 'autostart': False})
    for key in ('calibration_file', 'gnss_log'):
        if getattr(opts, key):
            cam[key] = str(Path(getattr(opts, key)).resolve())
    if opts.video_start_unix_s:
        cam['video_start_unix_s'] = float(opts.video_start_unix_s)
    # The replay waits for the tracker on every frame: a reliable subscription loses none.
    extra.setdefault('tracker', {}).setdefault('reliable_input', True)
    roles = ('camera', 'tracker', 'bundle', 'stereo', 'map')
    no_body_lever_arm(opts, extra, roles, 'a photo folder or a video has no attitude')
    if source_kind(opts.bag) == 'photos' and not opts.calibration_file:
        bundle = extra.setdefault('bundle', {})
        for k, v in EXIF_LENS_BUNDLE.items():
            bundle.setdefault(k, v)
    return roles


# A photo folder's EXIF camera (no calibration file) gives the focal length, not the lens's distortion: the final
# adjustment self-calibrates k1, k2 stepwise (each kept only when it pays), as `triangulate` does for such a camera,
# and so does the pass from pass_min_keyframes on, at each 1.5-fold growth (a block bends away from its geotags
# without, and the in-flight poses turn with it). For replay and run alike (commands/run.py exif_lens_setup).
EXIF_LENS_BUNDLE = {'final_self_calibration': 'auto', 'pass_self_calibration': ','.join(AUTO_CANDIDATES),
                    'growth_ratio': PASS_GROWTH_RATIO}


def run_replay(opts: ReplayOptions, context=None) -> dict:
    """Run the whole replay into OUT/map; returns the run summary, the diagnostics log and the map folder."""
    from photogram_ros.errors import ConfigError, DataError
    from photogram_ros.nodes.player_node import PlaySummary
    out = Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    check_free_space(out, opts.min_free_mb, 'before the replay')
    map_dir = out / 'map'
    kind = source_kind(opts.bag)
    extra = {role: dict(v) for role, v in opts.extra.items()}
    extra.setdefault('map', {})['map_dir'] = str(map_dir)
    topics, bag_warnings, exclude = {}, [], []
    if kind == 'bag':
        roles, exclude, topics, bag_start_ns, bag_warnings = _bag_setup(opts, extra)
    else:
        roles = _camera_setup(opts, extra)
    for role in roles:
        extra.setdefault(role, {})['use_sim_time'] = True
    bad = [r for r in opts.child_roles if r not in CHILD_ROLES_ALLOWED]
    if bad:
        raise ConfigError(f'replay: {bad} cannot run in the child process; choose among {CHILD_ROLES_ALLOWED} '
                          '(the tracker and MAVLink decoder pace the player and stay in the main process)')
    graph = Graph(GraphSpec(roles=roles, params_file=opts.params_file, extra=extra,
                            child_roles=tuple(opts.child_roles), control=opts.control), context=context)
    kwargs = {'context': context} if context is not None else {}
    player = camera = None
    if kind == 'bag':
        player = PlayerNode(overrides={'bag': str(opts.bag), 'rate': float(opts.rate), 'exclude': ','.join(exclude),
                                       'mavros': player_plays_mavros(opts, extra, roles)},
                            parameter_overrides=[Parameter('use_sim_time', value=True)], **kwargs)
        player_clock = player.get_clock()
    else:
        camera = graph.nodes['camera']
        bag_start_ns = camera.peek_stamp_ns()
        if bag_start_ns is None:
            graph.shutdown()
            raise DataError(f'{opts.bag}: no frame could be read (see the camera node\'s messages above)')
    listener = Node('replay_monitor', **kwargs)
    from rosgraph_msgs.msg import Clock
    clock_pub = listener.create_publisher(Clock, '/clock', qos.clock())
    diag_log = DiagnosticsLog(listener)
    graph.executor.add_node(listener)
    # The player only publishes: not spinning it keeps its entities out of the executor's wait set,
    # which the Python executor rebuilds on every wake-up (its largest CPU cost in a replay).
    try:
        graph.start()
    except Exception:
        graph.shutdown()
        raise
    start_clock(clock_pub, list(graph.nodes.values()), bag_start_ns)
    tracker = graph.nodes['tracker']
    images_sent = [0]
    t_start = time.monotonic()
    say = say_stdout if opts.progress else None
    frames = Progress('replay', frame_total(topics) if kind == 'bag' else frame_total_of_source(camera.source),
                      'frames', say, opts.progress_every_s)

    mavlink = graph.nodes.get('mavlink')
    packets_sent = [0]
    lag_slack = [0]      # keyframes a node will never count (lost, failed without a count): not waited for
    lag_wait_s = [0.0]

    def wait_for(done, deadline_s):
        deadline = time.monotonic() + deadline_s
        while not done() and time.monotonic() < deadline:
            time.sleep(0.002)

    lost = {'packets': 0, 'frames': 0}   # never arrived (waited for once, frame_timeout_s): not waited for again

    def wait_counted(key, got, sent):
        """Until got() catches up with sent() (less what was lost). One that never arrives costs one
        frame_timeout_s, once: the wait then counts it lost instead of waiting on every later frame."""
        wait_for(lambda: got() >= sent() - lost[key], opts.frame_timeout_s)
        lost[key] = max(lost[key], sent() - got())

    def before_frame():
        # Telemetry up to a frame's time must be decoded before the tracker sees the frame, as it
        # would be live; otherwise the fix a keyframe needs may still sit in a queue.
        if mavlink is not None:
            wait_counted('packets', lambda: mavlink.messages_in, lambda: packets_sent[0])
        # The tracker must have taken the previous frame. Waiting here rather than right after that
        # frame lets the messages recorded with it (its camera_info) reach the tracker meanwhile.
        wait_counted('frames', lambda: tracker.frames_done, lambda: images_sent[0])
        check_free_space(out, opts.min_free_mb, f'after {images_sent[0]} frames (the map so far is in {map_dir})')
        if opts.max_lag_keyframes > 0:
            wait_downstream()

    def before_message(m):
        if m.topic in IMAGE_TOPICS:
            before_frame()

    def wait_downstream():
        """Hold the player while a later node lags the tracker by more than max_lag_keyframes. A lag
        that does not shrink within frame_timeout_s, or while the graph does nothing for lag_stall_s, is
        accepted from then on (a keyframe that never shows in a counter, or a stalled node, must not
        stall every later frame)."""
        if downstream_lag(graph.counts()) - lag_slack[0] <= opts.max_lag_keyframes:
            return
        t0 = time.monotonic()
        watch = WorkWatch(graph)
        wait_for(lambda: downstream_lag(graph.counts()) - lag_slack[0] <= opts.max_lag_keyframes
                 or watch.idle_s() > opts.lag_stall_s, opts.frame_timeout_s)
        lag = downstream_lag(graph.counts())
        if lag - lag_slack[0] > opts.max_lag_keyframes:
            lag_slack[0] = lag - opts.max_lag_keyframes
        lag_wait_s[0] += time.monotonic() - t0

    def progress(stamp_ns):
        frames.update(images_sent[0], lambda: counts_text(graph.counts()))

    def on_message(m):
        player_clock.set_ros_time_override(Time(nanoseconds=m.stamp_ns, clock_type=ClockType.ROS_TIME))
        if m.topic == '/mavlink/from_fcu':
            packets_sent[0] += 1
        elif m.topic in IMAGE_TOPICS:
            images_sent[0] += 1
        progress(m.stamp_ns)

    def play_camera() -> PlaySummary:
        """The camera node's frames one at a time, with the bag's waits, to the source's end."""
        from rosgraph_msgs.msg import Clock

        from photogram_ros.msgs import time_from_ns
        clock = listener.create_publisher(Clock, '/clock', qos.clock())
        summary, t0, last_ns = PlaySummary(), time.monotonic(), bag_start_ns
        while (stamp_ns := camera.peek_stamp_ns()) is not None:
            if opts.rate > 0:   # the flight's timing, sped up by `rate`
                time.sleep(max(0.0, t0 + (stamp_ns - bag_start_ns) * 1e-9 / opts.rate - time.monotonic()))
            before_frame()
            clock.publish(Clock(clock=time_from_ns(stamp_ns)))
            camera.publish_next()
            last_ns = stamp_ns
            # Frames that failed to publish (said on /diagnostics) are not waited for.
            images_sent[0] = camera.diag.counts().get('frames', 0)
            progress(stamp_ns)
        camera.publish_next()   # the end: the gnss_log's fixes after the last frame, 'finished' on /diagnostics
        summary.counts = {IMAGE_TOPICS[0]: images_sent[0]}
        summary.bag_s, summary.wall_s = (last_ns - bag_start_ns) * 1e-9, time.monotonic() - t0
        return summary

    drain_left = []
    end_steps = Steps('replay: end of flight', len(END_STEPS) + 1, say)

    def drain():
        """Until the graph has drained (Graph.drain: waits on the data; work lost on the way is not waited for)."""
        left = graph.drain(quiet_s=opts.quiet_s, timeout_s=opts.drain_timeout_s, stall_s=opts.stall_s,
                           say=(lambda text: print(text, flush=True)) if opts.progress else None)
        if left:
            drain_left.append(left)

    try:
        if player is not None:
            summary = player.play(on_message=on_message, before_message=before_message)
        else:
            summary = play_camera()
        frames.finish(lambda: counts_text(graph.counts()))
        end_steps.start('the last frames through the graph')
        drain()
        steps = [name for role, name in END_STEPS if role in roles]
        end_steps.total = len(steps) + 1
        if steps:
            end_steps.start(steps[0])

        def settle():   # Graph.finish_flight: after each node's end-of-flight step, in END_STEPS' order
            drain()
            if len(end_steps.times) <= len(steps):
                end_steps.start(steps[len(end_steps.times) - 1])

        end = graph.finish_flight(settle=settle, say=(lambda text: print(text, flush=True)) if opts.progress else None)
        end_steps.finish()
        wall_s = time.monotonic() - t_start
        counts = graph.counts()
        names = {role: getattr(getattr(graph.nodes.get(role), 'diag', None), 'name', f'/{NODES[role][2]}')
                 for role in roles}
    finally:   # whatever happened, the map node flushes what it fused
        graph.shutdown()
        if player is not None:
            player.destroy_node()
        listener.destroy_node()
    diag_log.add(counts, names)
    _record_flight_end(map_dir, end.as_dict())
    run = {'bag': str(opts.bag), 'source': kind, 'frames': images_sent[0], 'bag_s': summary.bag_s, 'wall_s': wall_s,
           'real_time_factor': summary.bag_s / max(wall_s, 1e-9), 'messages': summary.total,
           'bag_errors': summary.errors, 'skipped_topics': summary.skipped,
           'waited_for_downstream_s': round(lag_wait_s[0], 1),
           'bag_read': {t: [i.count, i.expected] for t, i in topics.items()}, 'bag_warnings': bag_warnings,
           'final_adjustment': end.final_adjustment, 'end_of_flight_errors': end.errors, 'counts': counts,
           'params_file': str(opts.params_file) if opts.params_file else None, 'parameter_overrides': set_by_command(graph.spec)}
    if summary.px4_skipped:
        run['px4_records_not_published'] = dict(summary.px4_skipped)
    if drain_left:
        run['drain_gave_up'] = drain_left
    if any(lost.values()):
        run['lost_between_nodes'] = dict(lost)
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


# Graph.finish_flight's steps, in its order: (role, what the step does).
END_STEPS = (('tracker', 'the tracker\'s last keyframes'), ('bundle', 'final adjustment'),
             ('stereo', 'the last stereo pairs'), ('map', 'closing the map\'s coverage'))


def frame_total(topics: dict) -> int | None:
    """Camera frames of a bag, from its topics (io/bag.py TopicInfo: the readable count); None: not known."""
    n = sum(topics[t].count for t in IMAGE_TOPICS if t in topics and topics[t].count is not None)
    return n or None


def frame_total_of_source(source) -> int | None:
    """Frames of the camera node's source: a photo folder's listing, a video file's frame count (None when
    the container does not say, or for a device)."""
    try:
        return len(source) or None
    except TypeError:
        pass
    cap = getattr(source, 'cap', None)
    if cap is None or getattr(source, 'is_device', False):
        return None
    import cv2
    n = cap.get(cv2.CAP_PROP_FRAME_COUNT)
    return int(n) if n and n > 0 else None


def counts_text(counts: dict) -> str:
    """What the nodes have done so far (Graph.counts()), for a progress line."""
    parts = []
    for role, c in counts.items():
        key = {'tracker': 'keyframes', 'bundle': 'keyframes_adjusted', 'stereo': 'pairs_done',
               'map': 'points_fused'}.get(role)
        if key and key in c:
            parts.append(f'{role} {key.replace("_", " ")} {c[key]}')
    return ', '.join(parts)
