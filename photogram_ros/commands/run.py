"""photogram-ros run: start the whole mapper (live, on the companion computer).

SIGINT or SIGTERM ends the flight, and so does the end of a camera_node's photo folder or video file
(not a device, not `loop`) once the tracker has taken its last frame. A signal stops every source at
once (the camera's frames, the MAVLink link: a camera on the ground would go on producing), then the
tracker emits its last keyframes, the bundle adjuster makes the final adjustment and republishes every
pose, stereo pairs what waits, the map flushes, and the products are matched again from the final
poses, each step with a progress line. All of it runs while rclpy is still up (see
nodes/node_main.py). A second signal, or the end of flight passing `--end-timeout-s` (or
`--end-max-rss-mb`), skips the steps left and writes what exists: the in-flight map's products and the
report. A flight stopped by a signal has `--stop-budget-s` (45 s) for its end: the tracker's queued frames, the
waiting keyframes, stereo's waiting pairs and the products' dense matching each leave out what does not fit in
it, said in the log and the report (the final adjustment runs in any case; `export MAPDIR --densify` makes the
full products later; 0: no budget). The exit status is not 0 when the final adjustment or the exports failed, or when the flight
mapped nothing (the report's Verdict: a line "MAPPING FAILED: why", exit 5 as in `replay`).

A map folder left by a crash is resumed: the adjuster anchors `map` at its origin, and the keyframes it holds
without a pose (taken before the crash, not yet oriented) go through the tracker and adjuster first, from their
stored images, stamps and fixes (camera_node resume_keyframes_of), so that the report counts them oriented.
`--heights` is the products' height datum, as in `replay` and `export` (commands/common_args.py).
"""

from __future__ import annotations

import time

from photogram_ros.commands import common_args

HELP = 'start every mapping node (mavlink, tracker, bundle, stereo, map) with one parameter file'

# Exit statuses besides 0 (and 2, a configuration error): the map on disk is safe in every case.
EXIT_EXPORT_FAILED = 3
EXIT_FINISH_FAILED = 4
EXIT_NOT_MAPPED = 5

# The default --stop-budget-s: bench/results/faults_stop_<commit>.jsonl (toledo looping, SIGTERM after 60 s, 2
# loaded cores): the end-of-flight steps in about this, the in-flight map's products in about 20 s more.
STOP_BUDGET_S = 45.0
# A stopped flight's products are matched again from the final poses when the budget left after the steps holds
# this many seconds per keyframe oriented (else they come from the in-flight map): toledo's 68 keyframes took 90 s
# (1.3 s each) on 2 cores at load 5 (bench/faults_stop.py at 987d5df, the run log's "export: dense matching").
DENSIFY_S_PER_KEYFRAME = 1.5


def add_arguments(p) -> None:
    p.add_argument('--params', default=None, help='ROS 2 parameter file, e.g. config/onboard_rtk.yaml')
    p.add_argument('--namespace', default='', help='namespace of this drone, e.g. /drone1')
    p.add_argument('--separate', action='store_true', help='one process per node instead of one process')
    p.add_argument('--nodes', default='', help='comma-separated subset of camera,mavlink,tracker,bundle,stereo,map '
                                              '(default: all but camera; camera too when the file configures it)')
    p.add_argument('--out', default='products', help='where the survey products go when the mapper stops (SIGINT or '
                                                    'SIGTERM): clouds, DSM, orthomosaic, trajectory, report')
    p.add_argument('--crs', default='', help='CRS of the products (default: UTM zone of the map origin)')
    common_args.add_heights(p)
    common_args.add_exif_altitude(p, 'For camera_node\'s photo folder (its exif_altitude; not given: the parameter '
                                     'file\'s)')
    common_args.add_live_control(p)
    common_args.add_processes(p)
    p.add_argument('--no-export', action='store_true', help='only flush the map when stopping (export later with '
                                                            'photogram-ros export MAPDIR --densify)')
    p.add_argument('--live-map', action='store_true', help='export the in-flight map instead of matching the '
                                                           'keyframes again from the final adjustment')
    p.add_argument('--end-timeout-s', type=float, default=600.0,
                   help='bound on the end-of-flight steps after the stop (final adjustment, stereo, map flush): '
                        'past it the steps left are skipped and the products come from the in-flight map '
                        '(as after a second SIGINT/SIGTERM); default 600')
    p.add_argument('--stop-budget-s', type=float, default=STOP_BUDGET_S,
                   help='a flight stopped by SIGINT/SIGTERM: the seconds its end-of-flight steps share (the tracker\'s '
                        'queued frames, the final adjustment, stereo\'s waiting pairs; each leaves out what does not '
                        'fit and says so) and the products\' dense matching from the final poses (when it does not fit '
                        'in what is left, the products come from the in-flight map: photogram-ros export MAPDIR '
                        f'--densify makes the full ones later); 0 = no budget (every step to its end); 0 to 3600 s, '
                        f'default {STOP_BUDGET_S:g}')
    p.add_argument('--end-max-rss-mb', type=float, default=0.0,
                   help='bound on the mapping processes\' memory (this one and its --processes 2 child) during the '
                        'end-of-flight steps, MB: past it they are cut short the same way; 0 = no bound (default)')
    reuse = p.add_mutually_exclusive_group()
    reuse.add_argument('--resume', action='store_true',
                       help='the map folder holds a finished flight: continue that map (the products in --out are '
                            'replaced)')
    reuse.add_argument('--overwrite', action='store_true',
                       help='delete the previous flight\'s map folder and products first (without --resume or '
                            '--overwrite a finished flight\'s map or a non-empty --out is refused; a map left by '
                            'a crash, without flight_end.json, is resumed)')


def run(a) -> int:
    import rclpy

    from photogram_ros.commands.products import check_output_crs
    from photogram_ros.errors import ConfigError
    from photogram_ros.nodes.graph import NODES, Graph, GraphSpec, check_params, roles_for, set_by_command
    from photogram_ros.nodes.node_main import init_ros
    roles = tuple(r.strip() for r in a.nodes.split(',') if r.strip()) or roles_for(a.params)
    bad = [r for r in roles if r not in NODES]
    if bad:
        raise ConfigError(f'unknown nodes {bad}; choose from {list(NODES)}')
    if not a.end_timeout_s > 0 or not a.end_max_rss_mb >= 0:   # also refuses nan
        raise ConfigError('--end-timeout-s must be above 0 s (e.g. 600) and --end-max-rss-mb 0 (no bound) or more '
                          '(e.g. 3000)')
    if not 0 <= a.stop_budget_s <= 3600:
        raise ConfigError(f'--stop-budget-s must be 0 (no budget) to 3600 s, e.g. {STOP_BUDGET_S:g}')
    if a.namespace:
        check_namespace(a.namespace)
    camera = common_args.exif_altitude_overrides(a)
    control = common_args.live_control(a)   # a bad control file is said before any node starts
    if control is not None and 'bundle' not in roles:
        raise ConfigError(f'--gcp {a.gcp}: the control file goes to the bundle node, which --nodes leaves out')
    extra = {'camera': camera} if camera and 'camera' in roles else None
    spec = GraphSpec(roles=roles, params_file=a.params, namespace=a.namespace, extra=extra,
                     child_roles=() if a.separate else common_args.child_roles(a, roles), control=control)
    check_params(spec)     # every mistake before the first frame, not at the end of the flight
    exporting = not a.no_export and 'map' in roles
    if exporting and a.crs:
        check_output_crs(a.crs)
    if a.separate and camera_plays_a_file(spec):
        # One process per node cannot hold a folder or file to the tracker: the camera process would publish
        # its frames (at rate 0 all at once) while the tracker process starts, end, and so end the flight
        # before the tracker took one ("the tracker took no keyframe").
        raise ConfigError('--separate with camera_node playing a photo folder or a video file: only the one-process '
                          'run holds the camera to the tracker and ends the flight when the tracker has taken the '
                          'last frame; leave out --separate (it is for a live camera device)')
    _locks = claim_folders(a, roles, exporting)   # held (flock) until the command returns
    before = keyframes_before(map_dir_of(a.params)) if 'map' in roles else None
    if before is not None:
        spec = in_the_map_origin(spec, map_dir_of(a.params))
        spec = feed_unposed_keyframes(spec, map_dir_of(a.params), before)
    signals = RunSignals(skippable=not a.separate)
    if a.separate:
        return _run_separate(a, spec, signals, before)
    spec = exif_lens_setup(spec)
    paced = pace_camera(spec)
    spec, paced = paced, paced is not spec
    held = not paced and hold_camera(spec)
    spec = held or spec
    init_ros()
    graph = monitor = None
    try:
        graph = Graph(spec)
        from rclpy.node import Node

        from photogram_ros.nodes.replay_session import DiagnosticsLog
        monitor = Node('run_monitor', **({'namespace': a.namespace} if a.namespace else {}))
        diag_log = DiagnosticsLog(monitor)
        graph.executor.add_node(monitor)
        graph.start()
        t0 = time.monotonic()
        child = (f'; {", ".join(spec.child_roles)} in a second process (pid {graph.child_pid()})'
                 if spec.child_roles else '')
        print(f'photogram_ros running: {", ".join(spec.roles)}{child} (SIGINT or SIGTERM ends the flight: final '
              f'adjustment, map flush' + (f', products in {a.out}/)' if exporting else ')'), flush=True)
        pacer = CameraPacer(graph, signals.stop) if paced else None
        if held:   # the second process listens now: the camera's first frames reach the adjuster
            graph.nodes['camera'].start()
        memory = PeakMemory(graph.child_pid())
        signals.wait(alive=lambda: memory.sample() and not source_ended(graph))
        flight_s = time.monotonic() - t0
        say = (lambda text: print(text, flush=True))
        if pacer is not None:
            pacer.stop()
        if signals.signal_name:   # nothing more comes in: the end of flight works on what was taken
            stopped = graph.stop_sources()
            say(f'{signals.signal_name}: stopped ' + (', '.join(stopped) or 'no source in this process')
                + f' after {flight_s:.0f} s of flight (RSS {memory.now_mb:.0f} MB, peak {memory.peak_mb:.0f} MB)')
        else:   # the source ended: what it sent goes through the graph first
            print('end of the camera source: waiting for the tracker, bundle, stereo and map to take every '
                  'frame', flush=True)
            graph.drain(timeout_s=600.0, say=say, work_only=True, abort=signals.stop)
            graph.stop_sources()
        print(f'{signals.signal_name or "end of the camera source"}: ending the flight (final adjustment, stereo, '
              f'map flush; at most {a.end_timeout_s:g} s, a second signal skips to the products of what exists)',
              flush=True)
        budget_s = a.stop_budget_s if signals.signal_name else 0.0
        if budget_s:
            say(f'end of flight: a stopped flight: the steps share --stop-budget-s {budget_s:g} s (0: no budget)')
        t_end = time.monotonic()
        end = finish_within_bounds(graph, signals.skip, a.end_timeout_s, a.end_max_rss_mb, say, memory, budget_s)
        budget_left_s = budget_s - (time.monotonic() - t_end)
        counts = graph.counts()
        names = {role: getattr(getattr(graph.nodes.get(role), 'diag', None), 'name', f'/{NODES[role][2]}')
                 for role in spec.roles}
    finally:
        if graph is not None:
            graph.shutdown()
        if monitor is not None:
            monitor.destroy_node()
        rclpy.try_shutdown()
    # The flight's nodes (tracker images, the map's tiles in memory, the bundle's problem) go before the products
    # are made: held, they would add to what the dense matching and the rasters need.
    graph = monitor = pacer = None
    memory.sample()
    print(f'end of flight: the nodes\' memory released for the products (RSS {memory.now_mb:.0f} -> '
          f'{release_memory():.0f} MB)', flush=True)
    diag_log.add(counts, names)
    if signals.skip.is_set() and not a.live_map:
        a.live_map = True
        print('end of flight cut short: the products come from the in-flight map', flush=True)
    elif budget_s and not a.live_map and exporting:
        n = counts.get('bundle', {}).get('keyframes_oriented', counts.get('tracker', {}).get('keyframes', 0))
        if n * DENSIFY_S_PER_KEYFRAME > budget_left_s:
            a.live_map = True
            end.skipped.append(f'the dense matching of {n} keyframes from the final poses (about '
                               f'{n * DENSIFY_S_PER_KEYFRAME:.0f} s, {max(budget_left_s, 0):.0f} s of the budget '
                               'left): the products come from the in-flight map')
    if end.skipped:
        print(f'end of flight within --stop-budget-s {budget_s:g}: left out: ' + '; '.join(end.skipped)
              + f'. The full result: photogram-ros export {map_dir_of(a.params)} --densify --params '
              f'{a.params or "PARAMS"} --crs {a.crs or products_crs(map_dir_of(a.params))} --out OUT (or run '
              '--stop-budget-s 0)', flush=True)
    wall_s = time.monotonic() - t0
    frames = max(counts.get('tracker', {}).get('frames_received', 0), counts.get('camera', {}).get('frames', 0))
    run_info = {'source': 'run', 'frames': frames, 'bag_s': flight_s, 'wall_s': wall_s,
                'real_time_factor': flight_s / max(wall_s, 1e-9), 'counts': counts,
                'ended_by': signals.signal_name or 'end of the camera source',
                'final_adjustment': end.final_adjustment, 'end_of_flight_errors': end.errors,
                'stop_budget_s': budget_s, 'end_of_flight_skipped': end.skipped,
                'params_file': a.params, 'parameter_overrides': set_by_command(spec)}
    if before is not None:
        run_info['resumed'] = count_keyframes_before(counts, before, map_dir_of(a.params))
    return _after_flight(a, spec, end.as_dict(), run_info, with_end_of_flight(diag_log.snapshot(), end, wall_s))


def products_crs(map_dir: str) -> str:
    """The CRS `run` gives the products without --crs: UTM of the map's origin ("EPSG:..." when it has none)."""
    from photogram_ros.core.geodesy import utm_epsg
    from photogram_ros.io.map_store import MapStore
    try:
        origin = MapStore(map_dir).origin
    except Exception:   # only a hint in a message: the export says what is wrong with the map
        origin = None
    return f'EPSG:{utm_epsg(origin.lat_deg, origin.lon_deg)}' if origin is not None else 'EPSG:...'


def with_end_of_flight(diagnostics: dict, end, t_s: float) -> dict:
    """`diagnostics` (the nodes' /diagnostics snapshot the report lists) with what a stopped flight's budget left
    out (end.skipped) as the problems (WARN) of an entry 'run (end of flight)': the report says it with the
    nodes' own."""
    if not end.skipped:
        return diagnostics
    texts = [f'end of flight: left out by --stop-budget-s: {s}' for s in end.skipped]
    texts.append('the full result: photogram-ros export MAPDIR --densify (matches every pair from the final poses)')
    return {**diagnostics, 'run (end of flight)': {'values': {}, 'problems': [(round(t_s, 2), t) for t in texts],
                                                   'level': 1, 'problem_levels': {t: 1 for t in texts}}}


class RunSignals:
    """SIGINT and SIGTERM for `run`: the first sets `stop` (the flight ends: sources stopped, end-of-flight
    steps); the second sets `skip` (the steps left are skipped: the products of what exists are written);
    later ones say that kill -9 stops at once. Works also when a shell started `run` in the background
    with SIGINT ignored (a supervisor's SIGINT means stop)."""

    def __init__(self, skippable: bool = True):
        import signal
        import threading
        self.stop, self.skip = threading.Event(), threading.Event()
        self.signal_name = ''
        self.skippable = skippable   # run --separate: each node process ends its own flight
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)

    def _on_signal(self, signum, _frame) -> None:
        import signal
        import sys
        name = signal.Signals(signum).name
        if not self.stop.is_set():
            self.signal_name = name
            self.stop.set()
        elif not self.skip.is_set() and self.skippable:
            self.skip.set()
            print(f'{name} again: skipping the end-of-flight steps left; writing the products of what exists '
                  '(the in-flight map)', file=sys.stderr, flush=True)
        else:
            print(f'{name} again: still stopping; kill -9 stops at once (the map on disk stays '
                  'consistent: photogram-ros export MAPDIR --densify makes the products later)', file=sys.stderr,
                  flush=True)

    def wait(self, period_s: float = 0.5, alive=lambda: True) -> None:
        """Until a signal came (or `alive()` turns false)."""
        while not self.stop.wait(period_s) and alive():
            pass


def release_memory() -> float:
    """Collect unreachable objects (reference cycles hold the nodes) and give malloc's free pages back to the
    system (process_memory.trim_heap); returns this process's RSS after, MB."""
    import gc

    from photogram_ros.nodes.graph import rss_mb
    from photogram_ros.nodes.process_memory import trim_heap
    gc.collect()
    trim_heap()
    return rss_mb()


class PeakMemory:
    """The mapping processes' resident memory over the flight (this one's and the graph's child's, `child_pid`):
    `sample()` (True, to sit in a wait's alive check) records their current and peak RSS together, MB (a child
    that ended counts 0)."""

    def __init__(self, child_pid: int | None = None):
        self.child_pid = child_pid
        self.now_mb = self.peak_mb = 0.0
        self.sample()

    def sample(self) -> bool:
        from photogram_ros.nodes.graph import rss_mb
        self.now_mb = rss_mb() + (rss_mb(self.child_pid) if self.child_pid else 0.0)
        self.peak_mb = max(self.peak_mb, self.now_mb)
        return True


def finish_within_bounds(graph, skip, timeout_s: float, max_rss_mb: float, say, memory: PeakMemory | None = None,
                         budget_s: float = 0.0):
    """graph.finish_flight in a worker thread, watched from here every 0.5 s (the heap trimmed each time, so
    RSS is what the steps hold): a line every 10 s; past `timeout_s`, or the mapping processes' RSS (`memory`:
    this one's and the child's; without it this one's) above `max_rss_mb` (0: no bound), or once `skip` is set
    (a second signal), the steps left are skipped and
    the step running is waited for at most 10 s more. `budget_s` > 0 (a stopped flight, --stop-budget-s): the
    steps share it (Graph.finish_flight). Returns the FlightEnd (the final adjustment 'failed' with the reason
    when it was cut short before it ended)."""
    import threading

    from photogram_ros.nodes.graph import FlightEnd
    from photogram_ros.nodes.process_memory import trim_heap
    memory = memory or PeakMemory()
    result: dict = {}

    def rss_mb() -> float:
        memory.sample()
        return memory.now_mb

    def work():
        settle = (lambda timeout_s=60.0: graph.drain(timeout_s=timeout_s, say=say, work_only=True, abort=skip))
        try:
            result['end'] = graph.finish_flight(settle=settle, say=say, abort=skip, announce=True,
                                                **({'budget_s': budget_s} if budget_s else {}))
        except Exception as exc:   # said and recorded; the products of what exists are still written
            result['error'] = f'end of flight failed: {type(exc).__name__}: {exc}'

    thread = threading.Thread(target=work, daemon=True, name='end-of-flight')
    t0 = last_said = time.monotonic()
    thread.start()
    why = ''
    while thread.is_alive():
        thread.join(0.5)
        trim_heap()   # what the steps free goes back at once, not at the in-flight trimmer's next turn
        now, rss = time.monotonic(), rss_mb()
        if not why and not skip.is_set() and now - t0 > timeout_s:
            why = f'not done after {timeout_s:g} s (--end-timeout-s)'
        if not why and not skip.is_set() and max_rss_mb and rss > max_rss_mb:
            why = f'RSS {rss:.0f} MB above --end-max-rss-mb {max_rss_mb:g}'
        if why and not skip.is_set():
            say(f'end of flight: {why}: skipping the steps left')
            skip.set()
        if skip.is_set():
            thread.join(10.0)
            break
        if now - last_said >= 10.0:
            last_said = now
            say(f'end of flight: {now - t0:.0f} s (RSS {rss:.0f} MB)')
    if 'end' in result:
        end = result['end']
    else:
        cut = why or 'a second signal'
        end = FlightEnd('failed', f'cut short by {cut} before the final adjustment ended',
                        [result.get('error') or f'end of flight cut short by {cut} while a step was running'])
    if why and not any(why in e for e in end.errors):
        end.errors.append(f'end of flight cut short: {why}')
    say(f'end of flight: steps done in {time.monotonic() - t0:.0f} s (RSS {rss_mb():.0f} MB)')
    return end


def check_namespace(namespace: str) -> None:
    """A ConfigError (exit 2, one line) for a namespace ROS 2 refuses, before any node starts."""
    from rclpy.exceptions import InvalidNamespaceException
    from rclpy.validate_namespace import validate_namespace

    from photogram_ros.errors import ConfigError
    try:
        validate_namespace('/' + namespace.lstrip('/') if namespace != '/' else namespace)
    except InvalidNamespaceException as exc:
        why = str(exc).splitlines()[0].split(': ', 1)[-1].rstrip(':')
        raise ConfigError(f'--namespace {namespace!r} is not a ROS 2 namespace ({why}): use letters, digits, '
                          '"_" and "/", e.g. /drone1') from None


def camera_plays_a_file(spec) -> bool:
    """The graph has a camera node whose source is a photo folder or a video file (not a device)."""
    from photogram_ros.nodes.graph import role_values
    if 'camera' not in spec.roles:
        return False
    source = str(role_values(spec, 'camera').get('source', '')).strip()
    return bool(source) and not source.isdigit() and not source.startswith('/dev/')


def pace_camera(spec):
    """A camera node at rate 0 (a photo folder or a file, "as fast as the tracker takes them") is driven
    from here, one frame at a time (CameraPacer), as a replay does: published as fast as DDS acknowledges
    them, the frames outran the tracker, which dropped most of them."""
    from photogram_ros.nodes.camera_node import CameraParams
    from photogram_ros.nodes.graph import role_values
    from photogram_ros.params import from_dict
    if 'camera' not in spec.roles or 'tracker' not in spec.roles:
        return spec
    values = role_values(spec, 'camera')
    cam = from_dict(CameraParams, {k: v for k, v in values.items() if k != 'use_sim_time'}, where='camera_node')
    if cam.rate != 0 or cam.loop:
        return spec
    import dataclasses
    extra = {r: dict(v) for r, v in (spec.extra or {}).items()}
    extra.setdefault('camera', {})['autostart'] = False
    extra.setdefault('tracker', {}).setdefault('reliable_input', True)
    return dataclasses.replace(spec, extra=extra)


def exif_lens_setup(spec):
    """A camera node playing a photo folder without a calibration file takes its camera from the EXIF: the bundle
    node then self-calibrates the lens as replay has it (replay_session.EXIF_LENS_BUNDLE), each key unless the
    parameter file sets it. Returns the spec (the same one when nothing applies)."""
    from photogram_ros.errors import PhotogramError
    from photogram_ros.nodes.graph import role_values
    from photogram_ros.nodes.replay_session import EXIF_LENS_BUNDLE, source_kind
    if 'camera' not in spec.roles or 'bundle' not in spec.roles or not camera_plays_a_file(spec):
        return spec
    camera = role_values(spec, 'camera')
    try:
        photos = source_kind(str(camera.get('source', '')).strip()) == 'photos'
    except PhotogramError:   # camera_node names a bad source itself, at its start
        return spec
    if not photos or str(camera.get('calibration_file', '')).strip():
        return spec
    bundle = role_values(spec, 'bundle')
    add = {k: v for k, v in EXIF_LENS_BUNDLE.items() if k not in bundle}
    if not add:
        return spec
    import dataclasses
    extra = {r: dict(v) for r, v in (spec.extra or {}).items()}
    extra.setdefault('bundle', {}).update(add)
    return dataclasses.replace(spec, extra=extra)


def hold_camera(spec):
    """A spec whose camera node waits for `start()` (autostart false) when the graph has a second process: a
    camera on its timer would publish while that process starts (its nodes not yet listening, so the first
    keyframes never reach the adjuster) and take the CPU the start needs. None when nothing needs holding."""
    if 'camera' not in spec.roles or not spec.child_roles:
        return None
    import dataclasses
    extra = {r: dict(v) for r, v in (spec.extra or {}).items()}
    extra.setdefault('camera', {})['autostart'] = False
    return dataclasses.replace(spec, extra=extra)


class CameraPacer:
    """Publishes the graph's camera frames one at a time: the next once the tracker has taken the previous
    one and no node after it lags by more than `max_lag_keyframes`, until the source ends or `stop` is set."""

    def __init__(self, graph, stop, max_lag_keyframes: int = 30, frame_timeout_s: float = 30.0):
        import threading
        self.graph, self._stop, self._done = graph, stop, threading.Event()
        self.max_lag, self.timeout_s = max_lag_keyframes, frame_timeout_s
        self._thread = threading.Thread(target=self._run, daemon=True, name='camera-pacer')
        self._thread.start()

    def _wait(self, done) -> bool:
        deadline = time.monotonic() + self.timeout_s
        while not done():
            if self._stop.is_set() or self._done.is_set() or time.monotonic() > deadline:
                return False
            time.sleep(0.005)
        return True

    def _run(self) -> None:
        from photogram_ros.nodes.replay_session import downstream_lag
        camera, tracker = self.graph.nodes['camera'], self.graph.nodes['tracker']
        lost = 0
        while not self._stop.is_set() and not self._done.is_set():
            sent = camera.diag.counts().get('frames', 0)
            if not self._wait(lambda: tracker.frames_done >= sent - lost):
                lost = max(lost, sent - tracker.frames_done)
            self._wait(lambda: downstream_lag(self.graph.counts()) <= self.max_lag)
            if self._stop.is_set() or not camera.publish_next():
                return
            if camera.waiting:   # a watched folder (watch_quiet_s) waits for its next photo
                self._stop.wait(0.2)

    def stop(self) -> None:
        self._done.set()
        self._thread.join(timeout=5.0)


def claim_folders(a, roles, exporting: bool) -> list:
    """Lock the map folder and --out for this run (io/out_dir.py): a folder another photogram-ros writes is
    refused; so is a finished flight's map or a non-empty --out, unless --resume or --overwrite. A map
    left by a crash (no flight_end.json) is resumed, as the map node reloads it."""
    from pathlib import Path

    from photogram_ros.io.out_dir import claim_output
    mode = 'resume' if a.resume else 'overwrite' if a.overwrite else 'new'
    locks = []
    if 'map' in roles:
        map_dir = Path(map_dir_of(a.params))
        crashed = (map_dir / 'map.json').exists() and not (map_dir / 'flight_end.json').exists()
        locks.append(claim_output(map_dir, 'resume' if mode == 'new' and crashed else mode, 'run',
                                  'map folder (map_node.map_dir)'))
        if crashed and mode == 'new':
            print(f'note: {map_dir} holds a map whose flight did not end (a crash): resuming it', flush=True)
    if exporting:
        locks.append(claim_output(a.out, mode, 'run', '--out'))
    return locks


def keyframes_before(map_dir) -> dict | None:
    """The keyframes a map folder holds before this run (a resumed flight: taken before a crash or a restart):
    {'posed': stamps with a pose, 'unposed': stamps of the images saved without one, 'at': when they were listed
    (Unix s)}; None for a new map."""
    from pathlib import Path

    from photogram_ros.io.map_store import MapStore
    if not (Path(map_dir) / 'map.json').exists():
        return None
    store = MapStore(map_dir)
    return {'posed': sorted(int(k['stamp_ns']) for k in store.keyframes()),
            'unposed': sorted(int(p.stem) for p in store.unposed_keyframe_images()), 'at': time.time()}


def in_the_map_origin(spec, map_dir):
    """A resumed map that has its origin: the bundle adjuster anchors `map` there (use_origin_params and origin_*
    over the parameters file, said on the console), so the poses of this run are in the frame of the map's tiles
    and earlier keyframes (from its own first fix they would be tens of metres off, and the map keeps its old
    origin). A configured origin (bundle_node use_origin_params) is left as it is."""
    import dataclasses

    from photogram_ros.io.map_store import MapStore
    from photogram_ros.nodes.graph import role_values
    if 'bundle' not in spec.roles or role_values(spec, 'bundle').get('use_origin_params'):
        return spec
    origin = MapStore(map_dir).origin
    if origin is None:
        return spec
    extra = {r: dict(v) for r, v in (spec.extra or {}).items()}
    extra.setdefault('bundle', {}).update({'use_origin_params': True, 'origin_lat_deg': float(origin.lat_deg),
                                           'origin_lon_deg': float(origin.lon_deg), 'origin_h_m': float(origin.h_m)})
    print(f'resumed map: the adjuster anchors map at its origin ({origin.lat_deg:.7f}, {origin.lon_deg:.7f}, '
          f'{origin.h_m:.2f} m)', flush=True)
    return dataclasses.replace(spec, extra=extra)


def feed_unposed_keyframes(spec, map_dir, before: dict):
    """A resumed map that holds keyframes saved without a pose (taken before the crash, not yet oriented): the
    camera node plays their stored images first, with their stamps and fixes (camera_node resume_keyframes_of),
    so that this run's tracker and adjuster orient them. Without a camera node in this run (a camera driver
    publishing the images) nothing can feed them: said, and the report counts them as not oriented."""
    import dataclasses
    if not before['unposed']:
        return spec
    if 'camera' not in spec.roles or 'tracker' not in spec.roles:
        print(f"resumed map: {len(before['unposed'])} keyframes saved before the restart without a pose cannot be "
              'fed again (no camera_node and tracker in this run): they stay not oriented', flush=True)
        return spec
    extra = {r: dict(v) for r, v in (spec.extra or {}).items()}
    extra.setdefault('camera', {})['resume_keyframes_of'] = str(map_dir)
    print(f"resumed map: the {len(before['unposed'])} keyframes saved before the restart without a pose go through "
          'the tracker and the adjuster first (their stored images, stamps and fixes)', flush=True)
    return dataclasses.replace(spec, extra=extra)


def count_keyframes_before(counts: dict, before: dict, map_dir) -> dict:
    """A resumed flight's accounting: the keyframes of the map from before this run are taken too. One whose image
    this run saved again is this run's (fed again from the map's store, feed_unposed_keyframes, or a photo folder
    played from its start) and counted by this run's tracker and adjuster; the others are added to the tracker
    and bundle counters of `counts` (role -> Graph.counts(), what the report's keyframe accounting reads):
    `keyframes` and `keyframes_received` each by all of them, and those still without a pose as
    `not_oriented_taken_before_the_restart_without_a_pose`, so the report counts them as taken but not
    oriented. Said on the console; returns {'keyframes', 'posed', 'unposed', 'still_unposed', 'taken_again',
    'taken_again_oriented'} for the report's run section: `keyframes`, `posed`, `unposed` and `still_unposed`
    count the ones not taken again; `taken_again` the keyframes without a pose before this run that it took again,
    `taken_again_oriented` how many of those now have one."""
    from photogram_ros.io.map_store import MapStore
    store = MapStore(map_dir)

    def kept(stamps):   # not saved again by this run
        out = []
        for s in stamps:
            try:
                if store.keyframe_image_path(s).stat().st_mtime < before['at']:
                    out.append(s)
            except OSError:
                out.append(s)   # gone since: still one taken before
        return out
    posed, unposed = kept(before['posed']), kept(before['unposed'])
    again = sorted(set(before['unposed']) - set(unposed))
    n = len(posed) + len(unposed)
    unposed_now = {int(p.stem) for p in store.unposed_keyframe_images()}
    still = sum(1 for s in unposed if s in unposed_now)
    again_oriented = sum(1 for s in again if s not in unposed_now)
    tracker, bundle = counts.setdefault('tracker', {}), counts.setdefault('bundle', {})
    tracker['keyframes'] = tracker.get('keyframes', 0) + n
    bundle['keyframes_received'] = bundle.get('keyframes_received', 0) + n
    if still:
        key = 'not_oriented_taken_before_the_restart_without_a_pose'
        bundle[key] = bundle.get(key, 0) + still
    out = {'keyframes': n, 'posed': len(posed), 'unposed': len(unposed), 'still_unposed': still,
           'taken_again': len(again), 'taken_again_oriented': again_oriented}
    if n or again:
        print(f"resumed map: {n + len(again)} keyframes taken before this run ({out['posed']} oriented then"
              + (f'; {len(again)} without a pose then taken again by this run, {again_oriented} of them oriented now'
                 if again else '')
              + (f", {still} without a pose, not oriented: this run did not take them again (not fed to its "
                 "tracker, or not made keyframes by it); the report counts them as taken, not oriented"
                 if still else '')
              + ')', flush=True)
    return out


def source_ended(graph) -> bool:
    """The graph's camera node played its folder or file to the end and the tracker has taken every frame
    (a device or a looping source never ends; without a camera node the flight ends on a signal)."""
    camera, tracker = graph.nodes.get('camera'), graph.nodes.get('tracker')
    if camera is None or not camera.finished:
        return False
    return tracker is None or tracker.frames_done >= camera.diag.counts().get('frames', 0)


def _run_separate(a, spec, signals, before: dict | None = None) -> int:
    """One process per node; at the stop each is ended and waited for in data-flow order, so the final
    adjustment (bundle_node's exit), stereo's last pairs and the map's flush follow one another."""
    import signal

    from photogram_ros.nodes.graph import set_by_command, start_separate
    procs = start_separate(spec)
    monitor = SeparateMonitor(spec)   # the nodes' /diagnostics: the report's accounting
    t0 = time.monotonic()
    print(f'photogram_ros running: {", ".join(spec.roles)}, one process each', flush=True)
    signals.wait(alive=lambda: all(p.poll() is None for p in procs))
    flight_s = time.monotonic() - t0
    rcs = []
    try:
        for role, p in zip(spec.roles, procs):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
            try:
                rcs.append(p.wait(timeout=600))
            except Exception:
                p.kill()
                rcs.append(p.wait())
    finally:
        counts, diagnostics = monitor.close()
    failed = [f'{r} exited with status {rc}' for r, rc in zip(spec.roles, rcs) if rc]
    end = {'final_adjustment': 'unknown' if 'bundle' in spec.roles else 'none',
           'reason': 'run --separate: bundle_node adjusts at its own exit', 'errors': failed}
    wall_s = time.monotonic() - t0
    frames = max(counts.get('tracker', {}).get('frames_received', 0), counts.get('camera', {}).get('frames', 0))
    run_info = {'source': 'run', 'frames': frames, 'bag_s': flight_s, 'wall_s': wall_s,
                'real_time_factor': flight_s / max(wall_s, 1e-9), 'counts': counts,
                'ended_by': signals.signal_name or 'a node process ended', 'final_adjustment': end['final_adjustment'],
                'end_of_flight_errors': failed, 'params_file': a.params, 'parameter_overrides': set_by_command(spec)}
    if before is not None:
        run_info['resumed'] = count_keyframes_before(counts, before, map_dir_of(a.params))
    return _after_flight(a, spec, end, run_info, diagnostics)


class SeparateMonitor:
    """`run --separate`: listens to the nodes' /diagnostics from this process for the run's accounting
    (their last counters: frames, keyframes, pairs; a node's last period before its exit may be missing)."""

    def __init__(self, spec):
        import threading

        import rclpy
        from rclpy.node import Node

        from photogram_ros.nodes.node_main import init_ros
        from photogram_ros.nodes.replay_session import DiagnosticsLog
        init_ros()
        self.spec = spec
        self.node = Node('run_monitor', **({'namespace': spec.namespace} if spec.namespace else {}))
        self.log = DiagnosticsLog(self.node)
        self._stop = threading.Event()

        def spin():
            while not self._stop.is_set() and rclpy.ok():
                rclpy.spin_once(self.node, timeout_sec=0.1)
        self._thread = threading.Thread(target=spin, daemon=True, name='run-monitor')
        self._thread.start()

    def close(self) -> tuple[dict, dict]:
        """(role -> the node's last numeric counters, the /diagnostics snapshot); stops listening."""
        import rclpy

        from photogram_ros.nodes.graph import NODES
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.node.destroy_node()
        rclpy.try_shutdown()
        snap = self.log.snapshot()
        counts = {}
        for role in self.spec.roles:
            for name, d in snap.items():
                if name.rstrip('/').endswith('/' + NODES[role][2]) or name == NODES[role][2]:
                    counts[role] = {k: v for k, v in d['values'].items()
                                    if isinstance(v, (int, float)) and not isinstance(v, bool)}
        return counts, snap


def _after_flight(a, spec, end: dict, run_info: dict | None = None, diagnostics: dict | None = None) -> int:
    """Record how the flight ended in the map folder, export, and say what failed (`spec`: the flight's
    GraphSpec: its roles, and the control the report takes its check points from). `run_info`: the
    flight's accounting from the nodes' counters (frames, keyframes, Graph.counts()) for the report;
    `diagnostics`: what the nodes said on /diagnostics."""
    from photogram_ros.errors import PhotogramError
    from photogram_ros.io.map_store import MapStore
    if 'map' in spec.roles:
        try:
            MapStore(map_dir_of(a.params)).save_flight_end(end)
        except (PhotogramError, OSError) as exc:
            print(f'note: the map folder could not record how the flight ended: {exc}', flush=True)
    rc = _export_at_stop(a, spec.roles, run_info, diagnostics, spec.control)
    if end['final_adjustment'] == 'failed':
        print(f"the final adjustment failed ({end['reason']}): poses and products are the in-flight ones",
              flush=True)
    for e in end['errors']:
        print(f'end of flight: {e}', flush=True)
    if end['final_adjustment'] == 'failed' or end['errors']:
        return rc or EXIT_FINISH_FAILED
    return rc


def map_dir_of(params_file: str | None) -> str:
    """The map node's map_dir in a parameter file (its default without one)."""
    from photogram_ros.nodes.map_node import MapParams
    from photogram_ros.params import from_dict, load_params_file
    sections = load_params_file(params_file) if params_file else {}
    return from_dict(MapParams, sections.get('map_node', {}), f'{params_file} map_node').map_dir


def flight_control(a, control=None):
    """The flight's control file for the report's check points (core/control.ControlSet): `control`'s (the
    io/control_file.ControlInput the command read from --gcp), else the parameter file's bundle_node control_file;
    None without one."""
    if control is not None:
        return control.targets
    from photogram_ros.params import load_params_file
    bundle = (load_params_file(a.params) if a.params else {}).get('bundle_node', {})
    if not bundle.get('control_file'):
        return None
    from photogram_ros.io.control_file import read_control_file
    return read_control_file(bundle['control_file'], str(bundle.get('check_names', '')).split(','),
                             bundle.get('control_heights', 'auto'))


def _export_at_stop(a, roles, run_info=None, diagnostics=None, control=None) -> int:
    """The products and the report at the stop; `control`: the io/control_file.ControlInput the command read
    (flight_control)."""
    if a.no_export or 'map' not in roles:
        return 0
    from photogram_ros.commands.products import export_products
    from photogram_ros.errors import PhotogramError
    from photogram_ros.io.flight_verdict import keyframes_line
    try:
        res = export_products(map_dir_of(a.params), a.out, a.params, a.crs, a.live_map, a.heights, run=run_info,
                              diagnostics=diagnostics, progress=True,
                              control=flight_control(a, control))
    except (PhotogramError, OSError) as exc:   # the map itself is safe on disk: say how to export it later
        print(f'exports failed ({exc}); the map is on disk: photogram-ros export MAPDIR --densify', flush=True)
        return EXIT_EXPORT_FAILED
    for n in res.get('notes', []):
        print(f'note: {n}', flush=True)
    if res.get('files'):
        print(f"products in {a.out}/ ({res['crs']}): " + ', '.join(sorted(res['files'])) + ', report', flush=True)
    if 'keyframes_taken' in res.get('figures', {}):
        print(keyframes_line(res['figures']), flush=True)
    verdict = res.get('figures', {}).get('mapping')
    if verdict and not verdict['mapped']:
        print('MAPPING FAILED: ' + '; '.join(verdict['failures']), flush=True)
        return EXIT_NOT_MAPPED
    return 0
