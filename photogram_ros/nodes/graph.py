"""The mapping graph: every node of photogram_ros composed in one process, or one process per node.

One process (the default) shares a MultiThreadedExecutor, so images travel between nodes without
leaving the process's DDS participant. `--separate` starts the console scripts instead, with the same
parameter file, for integrators who want to restart or pin nodes individually.

A Python process runs on about one core (the GIL), so a graph can also put some roles in one child
process (`GraphSpec.child_roles`, the same node code): the child reports its nodes' counters on
`graph/child/status` and takes end-of-flight calls (stereo flush, bundle finish) and its stop on
`graph/child/command`, so the parent drives the whole graph as if the nodes were its own. The
child ignores SIGINT (a terminal's Ctrl-C reaches the whole process group: the parent decides) and
stops when its parent is gone, even after a kill -9 of the parent (it watches a pipe from it).

Every node takes its parameters (the file's, then `extra`); the bundle node also takes the flight's control file as
a command read it (`GraphSpec.control`, `replay`/`run --gcp`: make_node), an object its adjustment stage uses whole;
a child process gets it as its read values (child_argument). A ROS user names the file in the parameters instead.

A role's `use_sim_time` (in the parameter file or `extra`) is rclpy's own parameter: the node's clock then
follows /clock. `replay` sets it for every node (one time base: the bag's); `run` leaves the system clock.

`finish_flight` says whether the final adjustment was made (`FlightEnd`): the products and the
report must not claim final poses that are not there.
"""

from __future__ import annotations

import functools
import importlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING

from photogram_ros.errors import ConfigError, PhotogramError
from photogram_ros.params import load_params_file
from photogram_ros.nodes.node_main import WATCH_PARENT_ENV, init_ros, watch_parent
from photogram_ros.nodes.process_memory import DEFAULT_ARENAS, limit_malloc_arenas, start_heap_trimmer
from photogram_ros.stages.end_budget import EndBudget

if TYPE_CHECKING:
    from photogram_ros.io.control_file import ControlInput

# role -> (module, class, console script); the order is the data-flow order.
NODES = {
    'camera': ('photogram_ros.nodes.camera_node', 'CameraNode', 'camera_node'),
    'mavlink': ('photogram_ros.nodes.mavlink_node', 'MavlinkNode', 'mavlink_node'),
    'tracker': ('photogram_ros.nodes.tracker_node', 'TrackerNode', 'tracker_node'),
    'bundle': ('photogram_ros.nodes.bundle_node', 'BundleNode', 'bundle_node'),
    'stereo': ('photogram_ros.nodes.stereo_node', 'StereoNode', 'stereo_node'),
    'map': ('photogram_ros.nodes.map_node', 'MapNode', 'map_node'),
}


# role -> the parameter dataclass its node declares (in the node's module).
PARAMS = {'camera': 'CameraParams', 'mavlink': 'MavlinkParams', 'tracker': 'TrackerNodeParams',
          'bundle': 'BundleNodeParams', 'stereo': 'StereoNodeParams', 'map': 'MapParams'}


# The camera node is for cameras without a ROS driver (video devices, photo folders): started only
# when the parameter file has a camera_node section.
DEFAULT_ROLES = ('mavlink', 'tracker', 'bundle', 'stereo', 'map')


def roles_for(params_file: str | None) -> tuple:
    sections = load_params_file(params_file) if params_file else {}
    wants_camera = any(name.split('/')[-1] == 'camera_node' for name in sections)
    return (('camera',) if wants_camera else ()) + DEFAULT_ROLES


def node_class(role: str):
    module, cls, _ = NODES[role]
    return getattr(importlib.import_module(module), cls)


@dataclass
class GraphSpec:
    roles: tuple = DEFAULT_ROLES
    params_file: str | None = None
    namespace: str = ''
    extra: dict | None = None      # role -> {param: value}, applied over the file
    child_roles: tuple = field(default_factory=tuple)   # roles run in one child process (a second core)
    # The flight's control file as the command read it (--gcp): the bundle node's stage takes it whole (make_node),
    # in place of the parameter file's control_file; a child process gets its values (child_argument).
    control: ControlInput | None = None


@dataclass
class FlightEnd:
    """What the end of flight (Graph.finish_flight) achieved."""

    final_adjustment: str = 'none'   # 'done'; 'failed'; 'none': nothing to adjust (no keyframe oriented, no bundle)
    reason: str = ''                 # why it failed, or why there was none
    errors: list = field(default_factory=list)   # '<role>: <method> failed: <why>'
    skipped: list = field(default_factory=list)  # what a stopped flight's budget left out (Graph.finish_flight)

    @property
    def ok(self) -> bool:
        return self.final_adjustment != 'failed' and not self.errors

    def as_dict(self) -> dict:
        return {'final_adjustment': self.final_adjustment, 'reason': self.reason, 'errors': list(self.errors),
                'skipped': list(self.skipped)}


def _final_adjustment_outcome(before: dict, after: dict, problems: list[str], error: str) -> tuple[str, str]:
    """'done' / 'failed' / 'none' and the reason, from the bundle node's counters around its finish()."""
    if after.get('full_adjustments', 0) > before.get('full_adjustments', 0):
        return 'done', ''
    if error:
        return 'failed', error
    failed = [p for p in problems if p.startswith('full adjustment failed')]
    if failed:
        return 'failed', failed[-1]
    if after.get('keyframes_oriented', 0) == 0:
        return 'none', 'no keyframe was oriented'
    return 'failed', 'the bundle adjuster made no final adjustment'


def _sections(spec: GraphSpec) -> dict:
    """Parameter values per node name from the params file (ROS format) plus overrides."""
    sections = load_params_file(spec.params_file) if spec.params_file else {}
    # Sections of nodes this graph does not start (e.g. mavlink for a bag without MAVLink) are allowed.
    known = {script for _, _, script in NODES.values()}
    unknown = [s for s in sections if s != '**' and s.split('/')[-1] not in known]
    if unknown:
        raise ConfigError(f'{spec.params_file}: sections {unknown} name no node of this graph; nodes are '
                          f'{sorted(known)}')
    return sections


def role_values(spec: GraphSpec, role: str, sections: dict | None = None) -> dict:
    """The parameter values `role` gets: the file's '**' section, its own section, then spec.extra."""
    sections = _sections(spec) if sections is None else sections
    script = NODES[role][2]
    values = dict(sections.get('**', {}))
    for name, section in sections.items():
        if name.split('/')[-1] == script:
            values.update(section)
    values.update((spec.extra or {}).get(role, {}))
    if role == 'tracker' and not values.get('control_file'):
        # The tracker searches for the adjuster's surveyed targets only where they can be (target_search).
        bundle = spec.control.parameters() if spec.control is not None else role_values(spec, 'bundle', sections)
        for key in ('control_file', 'control_heights'):
            if bundle.get(key):
                values[key] = bundle[key]
    return values


def make_node(role: str, values: dict, spec: GraphSpec, **kwargs):
    """The node of `role` with its parameter values; the bundle node also with the flight's control as the command
    read it (spec.control), which its adjustment stage takes whole."""
    if role == 'bundle':
        from photogram_ros.nodes.bundle_node import BundleNode
        return BundleNode(overrides=values, control=spec.control.targets if spec.control is not None else None,
                          **kwargs)
    return node_class(role)(overrides=values, **kwargs)


def set_by_command(spec: GraphSpec) -> dict:
    """role -> {parameter: value} the command set over the parameter file, for the run's record (the report's
    Parameters): spec.extra, and the control file the command read, as the bundle node's parameters name it."""
    out = {r: dict(v) for r, v in (spec.extra or {}).items()}
    if spec.control is not None:
        out.setdefault('bundle', {}).update(spec.control.parameters())
    return out


def child_argument(spec: GraphSpec) -> str:
    """`spec` as the JSON a child process rebuilds it from (child_spec): the control as its read values."""
    doc = asdict(replace(spec, control=None))
    doc['control'] = spec.control.as_dict() if spec.control is not None else None
    return json.dumps(doc)


def child_spec(argument: str) -> GraphSpec:
    """The GraphSpec of child_argument, run in this process (no child of its own)."""
    from photogram_ros.io.control_file import ControlInput
    doc = json.loads(argument)
    control = ControlInput.from_dict(doc.pop('control')) if doc.get('control') else None
    return GraphSpec(**{**doc, 'roles': tuple(doc['roles']), 'child_roles': (), 'control': control})


def ros_time_kwargs(values: dict, where: str) -> dict:
    """use_sim_time among a node's parameter values -> the rclpy Node keyword that sets it (the node's clock
    then follows /clock); {} when it is not given. It is rclpy's parameter, not one of the node's dataclass."""
    if 'use_sim_time' not in values:
        return {}
    value = values['use_sim_time']
    if not isinstance(value, bool):
        raise ConfigError(f'{where}: use_sim_time must be true or false, got {value!r}')
    from rclpy.parameter import Parameter
    return {'parameter_overrides': [Parameter('use_sim_time', value=value)]}


def check_params(spec: GraphSpec, roles=None) -> None:
    """Validate every parameter the nodes of `roles` (default: all of spec) will get, names and ranges,
    without starting them: a mistake is a ConfigError now rather than when a node (perhaps in another
    process) starts."""
    from photogram_ros.params import from_dict
    sections = _sections(spec)
    for role in spec.roles if roles is None else roles:
        cls = getattr(importlib.import_module(NODES[role][0]), PARAMS[role])
        values = role_values(spec, role, sections)
        where = f'{spec.params_file or "parameters"}: {NODES[role][2]}'
        ros_time_kwargs(values, where)
        from_dict(cls, {k: v for k, v in values.items() if k != 'use_sim_time'}, where=where)


class Graph:
    """All nodes in one process, spun by a multi-threaded executor in a background thread."""

    def __init__(self, spec: GraphSpec, context=None):
        from rclpy.executors import MultiThreadedExecutor
        # Before the executor's threads (flat memory over long flights); the callers that start
        # rclpy themselves (cli.main, child_main) cap earlier, before the DDS threads.
        limit_malloc_arenas()
        self.spec = spec
        sections = _sections(spec)
        # The child's nodes start in another process: check their parameters here, at once.
        check_params(spec, [r for r in spec.roles if r in spec.child_roles])
        self.nodes = {}
        kwargs = {'namespace': spec.namespace} if spec.namespace else {}
        if context is not None:
            kwargs['context'] = context
        self.child = None
        for role in spec.roles:
            if role in spec.child_roles:
                continue
            values = role_values(spec, role, sections)
            self.nodes[role] = make_node(role, values, spec, **kwargs, **ros_time_kwargs(values, NODES[role][2]))
        self.executor = MultiThreadedExecutor(num_threads=4, context=context)
        for n in self.nodes.values():
            self.executor.add_node(n)
        self._thread = None
        child = tuple(r for r in spec.roles if r in spec.child_roles)
        if child:
            self.child = ChildGraph(GraphSpec(roles=child, params_file=spec.params_file, namespace=spec.namespace,
                                              extra={r: v for r, v in (spec.extra or {}).items() if r in child},
                                              control=spec.control if 'bundle' in child else None),
                                    kwargs)
            self.executor.add_node(self.child.node)

    def start(self, child_timeout_s: float = 60.0, watch_period_s: float = 5.0) -> None:
        self._thread = threading.Thread(target=self._spin, daemon=True, name='graph-executor')
        self._thread.start()
        self._trimmer = start_heap_trimmer()
        self._watch_stop = threading.Event()
        if watch_period_s > 0:
            threading.Thread(target=self._watch_duplicates, args=(watch_period_s,), daemon=True,
                             name='graph-duplicates').start()
        if self.child is not None:
            self.child.wait_ready(list(self.nodes.values()), child_timeout_s)

    def _spin(self) -> None:
        """Spin until shutdown. An error in the executor itself (rclpy raises InvalidHandle when an entity is
        destroyed while it waits) is printed and spinning goes on: a dead executor thread would leave every
        node deaf while the replay waits on them."""
        for _ in range(100):
            try:
                self.executor.spin()
                return
            except Exception as exc:
                if self.executor.context is None or not self.executor.context.ok():
                    return
                print(f'graph: executor error, spinning on: {type(exc).__name__}: {exc}', file=sys.stderr, flush=True)
                time.sleep(0.05)

    def _watch_duplicates(self, period_s: float) -> None:
        """Every `period_s`: each topic one of this process's nodes publishes, also published by another
        node of the same name and namespace (a second mapper on this ROS 2 domain: another `run`, or a
        replay sharing the domain), is a WARN on that node's /diagnostics with the reason, while it lasts."""
        while not self._watch_stop.wait(period_s):
            for role, n in list(self.nodes.items()):
                diag = getattr(n, 'diag', None)
                if diag is None:
                    continue
                try:
                    for what in duplicate_publishers(n):
                        diag.problem(what)
                except Exception:   # the node is being destroyed, or the context is gone
                    return

    def child_pid(self) -> int | None:
        """The child process's pid (GraphSpec.child_roles), None without one."""
        return self.child.proc.pid if self.child is not None else None

    def counts(self) -> dict:
        """role -> the node's diagnostic counters, for the nodes of this process and of the child."""
        out = {r: n.diag.counts() for r, n in self.nodes.items() if getattr(n, 'diag', None) is not None}
        if self.child is not None:
            out.update(self.child.counts())
        return out

    def busy(self) -> bool:
        """A node working in its own thread (the bundle adjuster) says so: its counters stand still meanwhile."""
        local = any(callable(getattr(n, 'busy', None)) and n.busy() for n in self.nodes.values())
        return local or (self.child is not None and self.child.busy())

    def in_flight(self) -> dict:
        """Work the counters say is between nodes: keyframes the tracker published that the bundle
        adjuster has not received, pair clouds stereo published that the map has not fused (a fuse can
        take seconds). {} when nothing is."""
        counts = self.counts()
        out = {}
        tr, b, st, m = (counts.get(r) for r in ('tracker', 'bundle', 'stereo', 'map'))
        if tr is not None and b is not None:
            n = tr.get('keyframes', 0) - b.get('keyframes_received', 0)
            if n > 0:
                out['keyframes not yet at the bundle adjuster'] = n
        if st is not None and m is not None:
            n = st.get('pairs_done', 0) - m.get('clouds', 0) - m.get('clouds_dropped', 0)
            if n > 0:
                out['pair clouds not yet fused by the map'] = n
        return out

    def activity(self, work_only: bool = False) -> int:
        """A number that grows while any node is still working: the sum of the nodes' diagnostic
        counters; `work_only`: only the counters of the mapping work (WORK_COUNTERS), not those a live
        input moves whatever the graph does (MAVLink packets, camera frames, GNSS fixes)."""
        total = 0
        for role, c in self.counts().items():
            for k, v in c.items():
                if isinstance(v, (int, float)) and (not work_only or k in WORK_COUNTERS.get(role, ())
                                                    or k.startswith(('pairs_skipped_', 'keyframes_not_oriented'))):
                    total += v
        return int(total)

    def stop_sources(self) -> list[str]:
        """Stop every input of the graph at once (the camera's frames, the MAVLink link): what the end of
        flight works on is what was taken before. Returns the roles stopped."""
        stopped = []
        for role in SOURCE_ROLES:
            if self.child is not None and role in self.child.spec.roles:
                try:
                    self.child.call(role, 'stop_input', timeout_s=10.0, stall_s=10.0)
                except RuntimeError as exc:
                    print(f'graph: {role} could not be stopped: {exc}', file=sys.stderr, flush=True)
                    continue
            elif callable(getattr(self.nodes.get(role), 'stop_input', None)):
                self.nodes[role].stop_input()
            else:
                continue
            stopped.append(role)
        return stopped

    def drain(self, quiet_s: float = 1.0, timeout_s: float = 300.0, stall_s: float = 30.0, say=None,
              work_only: bool = False, abort=None) -> dict:
        """Wait until the data in the graph has gone through it: nothing in flight between nodes
        (`in_flight`), no node busy, and no counter moved for `quiet_s`. Waits on the data, not on a
        clock: work counted in flight while nothing moves at all (no counter, no busy node) for
        `stall_s` was lost on the way and is not waited for; `timeout_s` bounds the whole wait.
        `say(text)` gets a line every 10 s of waiting (what is waited for). `work_only`: a live graph's
        inputs keep moving their counters: only the mapping work's count (activity). `abort` (an Event)
        ends the wait when set. Returns what was still in flight when the wait ended ({} when the graph
        drained)."""
        t0 = time.monotonic()
        moved_at = quiet_since = t0
        last, last_said = self.activity(work_only), t0
        while True:
            time.sleep(0.1)
            now_t, now = time.monotonic(), self.activity(work_only)
            flight, busy = self.in_flight(), self.busy()
            if now != last or busy:
                moved_at = now_t
            if now != last or busy or flight:
                quiet_since = now_t
            last = now
            if now_t - quiet_since > quiet_s:
                return {}
            if abort is not None and abort.is_set():
                return flight or ({'busy': 1} if busy else {})
            if flight and now_t - moved_at > stall_s:
                if say is not None:
                    say(f'end of flight: nothing moved for {stall_s:.0f} s with '
                        + ', '.join(f'{v} {k}' for k, v in flight.items()) + ': lost on the way, not waited for')
                return flight
            if now_t - t0 > timeout_s:
                if say is not None:
                    say(f'end of flight: still working after {timeout_s:.0f} s; going on')
                return flight or {'busy': 1}
            if say is not None and now_t - last_said > 10.0:
                last_said = now_t
                doing = [f'{v} {k}' for k, v in flight.items()]
                doing += ['a node is computing (the bundle adjuster)'] if busy else []
                say(f'end of flight: {now_t - t0:.0f} s: waiting for ' + ('; '.join(doing) or 'the nodes to settle'))

    def problems(self, role: str) -> list[str]:
        """The last problems a node reported (in this process or the child)."""
        if self.child is not None and role in self.child.spec.roles:
            return self.child.problems(role)
        diag = getattr(self.nodes.get(role), 'diag', None)
        return diag.recent_problems() if diag is not None else []

    def finish_flight(self, settle=lambda timeout_s=2.0: time.sleep(min(timeout_s, 2.0)), say=None, abort=None,
                      announce: bool = False, budget_s: float = 0.0) -> FlightEnd:
        """End of flight, in data-flow order: the tracker emits the keyframes it still holds, the
        bundle adjuster runs its final adjustment and republishes the poses, stereo pairs the
        keyframes still waiting, the map closes its coverage (every survey cell counts as passed, so
        the last gaps go out); `settle(timeout_s=)` lets the downstream nodes consume each step's output; `say`
        gets a line every 10 s while a step in the child process takes long, and with `announce` one at
        each step (with its time and this process's memory). `abort` (an Event): once set, the steps not begun are skipped
        (a second signal, or the end of flight's time bound), and said in `errors`. `budget_s` > 0 (a stopped
        flight, run --stop-budget-s): the steps share it in this order, each handed its part of what is left
        (STEP_BUDGET): the tracker's queued frames past its part are dropped, the adjuster takes the keyframes
        waiting while its final adjustment still fits, stereo pairs while time is left; each says what it left out.
        Returns whether the final adjustment was made, and every step that failed."""
        end = FlightEnd(reason='no bundle node' if 'bundle' not in self.spec.roles else '')
        t0 = time.monotonic()
        budget = EndBudget(budget_s)
        if budget.bounded:   # the adjuster's worker keeps to the budget from now (its batch in progress)
            call_if_there(self, 'bundle', 'end_budget', say, budget_s=step_budget('bundle', 'finish', budget)['budget_s'])
        for role, method in FINISH_STEPS:
            kwargs = step_budget(role, method, budget) if budget.bounded else {}
            if self.child is not None and role in self.child.spec.roles:
                fn = functools.partial(self.child.call, role, method, say=say, kwargs=kwargs)
            elif callable(getattr(self.nodes.get(role), method, None)):
                fn = functools.partial(getattr(self.nodes[role], method), **kwargs)
            else:
                continue
            if abort is not None and abort.is_set():
                end.errors.append(f'{role}: {method} skipped (the end of flight was cut short)')
                if role == 'bundle':
                    end.final_adjustment, end.reason = 'failed', 'skipped: the end of flight was cut short'
                continue
            if say is not None and announce:
                say(f'end of flight: {time.monotonic() - t0:.0f} s: {FINISH_STEP_WORDS[role, method]} '
                    + (f'(RSS {rss_mb():.0f} MB' + (f', {budget.left_s():.0f} s of the budget left' if budget.bounded
                                                     else '') + ')'))
            before, error = self.counts().get(role, {}), ''
            if budget.bounded and role == 'tracker':   # what its part cannot take goes now (and its memory with it)
                dropped = drop_queued_frames(self.nodes.get(role), frames_in(self.nodes.get(role),
                                                                             kwargs['max_wait_s']))
            try:
                fn()
            except Exception as exc:  # one node's failure must not lose the others' data
                error = f'{role}: {method} failed: {exc}'
                end.errors.append(error)
                print(error, file=sys.stderr, flush=True)
            if budget.bounded and role == 'tracker':
                dropped += drop_queued_frames(self.nodes.get(role))
                if dropped:
                    end.skipped.append(f'{dropped} frames the tracker had not taken yet (the stop budget)')
                    if say is not None:
                        say(f'end of flight: {dropped} frames the tracker had not taken yet dropped (its part of '
                            '--stop-budget-s)')
            if budget.bounded:
                settle(timeout_s=min(SETTLE_MAX_S, max(1.0, SETTLE_SHARE * budget.left_s())))
            else:
                settle()
            if role == 'bundle':
                end.final_adjustment, end.reason = _final_adjustment_outcome(
                    before, self.counts().get('bundle', {}), self.problems('bundle'), error)
        return end

    def shutdown(self) -> None:
        """Stop spinning and destroy the nodes (the map node flushes its tiles to disk on destroy); the
        child process does the same with its nodes and ends."""
        if getattr(self, '_watch_stop', None) is not None:
            self._watch_stop.set()
        if self.child is not None:
            self.child.stop()
        if getattr(self, '_trimmer', None) is not None:
            self._trimmer.set()
        self.executor.shutdown(timeout_sec=5)
        for n in self.nodes.values():
            n.destroy_node()
        if self.child is not None:
            self.child.node.destroy_node()


# The end-of-flight steps, in data-flow order (Graph.finish_flight), and how the progress lines name them.
FINISH_STEPS = (('tracker', 'flush'), ('bundle', 'finish'), ('stereo', 'flush'), ('map', 'finish_coverage'))
FINISH_STEP_WORDS = {('tracker', 'flush'): 'the tracker emits the keyframes it holds',
                     ('bundle', 'finish'): 'final adjustment',
                     ('stereo', 'flush'): 'stereo pairs the keyframes still waiting',
                     ('map', 'finish_coverage'): 'the map closes its coverage'}

# A stopped flight's end (Graph.finish_flight's budget_s): each step's part of the budget left when it begins.
# The tracker works through its queued frames for TRACKER_SHARE of it; the adjuster keeps STEREO_AND_MAP_SHARE of
# the whole budget for the steps after it; a settle waits for the nodes downstream at most SETTLE_SHARE of what is
# left (and SETTLE_MAX_S, as without a budget).
TRACKER_SHARE = 0.2
STEREO_AND_MAP_SHARE = 0.15
SETTLE_SHARE = 0.1
SETTLE_MAX_S = 60.0


def step_budget(role: str, method: str, budget: EndBudget) -> dict:
    """The keyword arguments that hand an end-of-flight step its part of `budget` (what is left of it now)."""
    left = budget.left_s()
    if (role, method) == ('tracker', 'flush'):
        return {'max_wait_s': max(1.0, TRACKER_SHARE * left)}
    if (role, method) == ('bundle', 'finish'):
        return {'budget_s': max(1.0, left - STEREO_AND_MAP_SHARE * budget.budget_s)}
    if (role, method) == ('stereo', 'flush'):
        return {'budget_s': max(1.0, left)}
    return {}


def call_if_there(graph, role: str, method: str, say=None, **kwargs) -> None:
    """`method` of the `role` node of `graph` (in its process or its child) with `kwargs`, when it has one; a
    failure is printed, not raised."""
    try:
        if graph.child is not None and role in graph.child.spec.roles:
            graph.child.call(role, method, say=say, kwargs=kwargs, timeout_s=30.0, stall_s=30.0)
        elif callable(getattr(graph.nodes.get(role), method, None)):
            getattr(graph.nodes[role], method)(**kwargs)
    except Exception as exc:   # the end of flight goes on without it
        print(f'graph: {role}.{method} failed: {exc}', file=sys.stderr, flush=True)


def drop_queued_frames(tracker, keep: int = 0) -> int:
    """Drop the frames queued in `tracker` (a TrackerNode: its drop_queued) that it has not taken yet but the
    `keep` next in line; returns how many (0 without a tracker in this process)."""
    drop = getattr(tracker, 'drop_queued', None)
    return drop(keep) if callable(drop) else 0


def frames_in(tracker, seconds: float) -> int:
    """How many frames `tracker` takes in `seconds` at its pace of the last 10 s (frames_tracked on /diagnostics);
    1 when it has none."""
    diag = getattr(tracker, 'diag', None)
    rate_hz = diag.rate_hz('frames_tracked', 10.0) if diag is not None and hasattr(diag, 'rate_hz') else 0.0
    return max(1, int(rate_hz * seconds))


# The roles whose nodes bring data into the graph (Graph.stop_sources): each has stop_input().
SOURCE_ROLES = ('camera', 'mavlink')


def rss_mb(pid: int | str = 'self') -> float:
    """Resident memory of process `pid` (this one by default), MB, from /proc; 0 where it cannot be read."""
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return 0.0


# The counters of the mapping work itself, per role (Graph.activity(work_only=True)).
WORK_COUNTERS = {'tracker': ('keyframes',),
                 'bundle': ('keyframes_received', 'keyframes_oriented', 'keyframes_failed', 'full_adjustments',
                            'keyframes_adjusted'),
                 'stereo': ('images', 'pairs_done', 'pairs_failed'),
                 'map': ('clouds', 'clouds_dropped', 'keyframes_saved', 'points_fused')}

# Topics every node publishes (or the graph's own): many publishers are normal there.
SHARED_TOPICS = ('/diagnostics', '/rosout', '/parameter_events', '/clock')


def duplicate_publishers(node) -> list[str]:
    """For each topic `node` publishes, a sentence when another node of the same name and namespace
    publishes it too: two copies of one mapper on one graph, whose data the subscribers mix up."""
    out = []
    mine: dict = {}
    for pub in node.publishers:
        mine[pub.topic_name] = mine.get(pub.topic_name, 0) + 1
    name, ns = node.get_name(), node.get_namespace()
    for topic, own in mine.items():
        if topic in SHARED_TOPICS or '/graph/child/' in f'/{topic.lstrip("/")}':
            continue
        same = [i for i in node.get_publishers_info_by_topic(topic) if i.node_name == name and i.node_namespace == ns]
        if len(same) > own:
            domain = os.environ.get('ROS_DOMAIN_ID', '0') or '0'
            out.append(f'{topic}: {len(same) - own} other {ns.rstrip("/")}/{name} also publishes it on ROS_DOMAIN_ID '
                       f'{domain}: a second mapper (run, or replay --domain) on this graph mixes its data with '
                       'this one\'s; give each its own ROS_DOMAIN_ID or --namespace')
    return out


TOPIC_CHILD_STATUS = 'graph/child/status'
TOPIC_CHILD_COMMAND = 'graph/child/command'
# A parent names its child's topics after its pid (graph/child/p1234/status): two replays on one domain
# (--domain) then never take each other's commands (a "stop") or status.
GRAPH_TOKEN_ENV = 'PHOTOGRAM_GRAPH_TOKEN'


def child_topic(base: str, token: str) -> str:
    """'graph/child/status', 'p1234' -> 'graph/child/p1234/status'."""
    head, _, tail = base.rpartition('/')
    return f'{head}/{token}/{tail}' if token else base


# CPU seconds per second of wall time above which the child counts as computing (its idle DDS and
# status threads take about 0.01).
CHILD_COMPUTING_CPU_S = 0.05


def process_cpu_s(pid: int) -> float | None:
    """CPU time (user + system, s) of process `pid` so far, from /proc; None where it cannot be read."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, ValueError, IndexError):
        return None


class WorkWatch:
    """How long a graph has done nothing: no mapping counter moved (Graph.activity(work_only=True)), no
    node busy, and its nodes not computing (the child process's CPU time, or this process's). Lets a
    wait that holds the player for a lagging node end when that node has stalled instead of at a fixed
    timeout."""

    # This process's own CPU seconds a second above which its nodes count as computing (the waiting
    # player and DDS take a few per cent).
    OWN_COMPUTING_CPU_S = 0.3

    def __init__(self, graph, period_s: float = 0.5):
        self.graph, self.period_s = graph, period_s
        child = getattr(graph, 'child', None)
        self._pid = child.proc.pid if child is not None else os.getpid()
        self._threshold = CHILD_COMPUTING_CPU_S if child is not None else self.OWN_COMPUTING_CPU_S
        self._last = (graph.activity(work_only=True), process_cpu_s(self._pid))
        self.moved = self._checked = time.monotonic()

    def idle_s(self) -> float:
        now = time.monotonic()
        if now - self._checked >= self.period_s:
            act, cpu = self.graph.activity(work_only=True), process_cpu_s(self._pid)
            computing = (cpu is not None and self._last[1] is not None
                         and cpu - self._last[1] > self._threshold * (now - self._checked))
            if act != self._last[0] or computing or self.graph.busy():
                self.moved = now
            self._last, self._checked = (act, cpu), now
        return now - self.moved


class ChildGraph:
    """The parent's handle on a child process running `spec.roles` (see child_main)."""

    def __init__(self, spec: GraphSpec, node_kwargs: dict):
        from rclpy.node import Node

        from photogram_ros.nodes import qos
        from std_msgs.msg import String
        self.spec = spec
        self.node = Node('graph_parent', **node_kwargs)
        self._status: dict = {}
        self._status_at = time.monotonic()   # when the last status came (the child sends one every 0.2 s)
        self._cond = threading.Condition()
        self._seq = 0
        token = f'p{os.getpid()}'
        self._pub = self.node.create_publisher(String, child_topic(TOPIC_CHILD_COMMAND, token), qos.reliable())
        self.node.create_subscription(String, child_topic(TOPIC_CHILD_STATUS, token), self._on_status, qos.reliable())
        ctx = node_kwargs.get('context')
        env = dict(os.environ)
        if ctx is not None and getattr(ctx, 'get_domain_id', None):
            env['ROS_DOMAIN_ID'] = str(ctx.get_domain_id())
        # The child runs the very code of this process (a source tree may shadow an installed copy).
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        env['PYTHONPATH'] = os.pathsep.join([root] + [v for v in [env.get('PYTHONPATH')] if v])
        # glibc reads this before the child's first thread, so no thread gets an arena of its own
        # before the cap (capped late, the 16-minute soak's child had 4 arenas and 100 MB more heap).
        env.setdefault('MALLOC_ARENA_MAX', str(DEFAULT_ARENAS))
        # The child stops when this pipe closes: when this process ends, however it ends.
        env[WATCH_PARENT_ENV] = '1'
        env[GRAPH_TOKEN_ENV] = token
        code = 'import sys; from photogram_ros.nodes.graph import child_main; sys.exit(child_main())'
        self.proc = subprocess.Popen([sys.executable, '-c', code, child_argument(spec)], env=env,
                                     stdin=subprocess.PIPE)

    def _on_status(self, msg) -> None:
        with self._cond:
            self._status = json.loads(msg.data)
            self._status_at = time.monotonic()
            self._cond.notify_all()

    def _wait(self, what, timeout_s: float) -> bool:
        """Until what(status) holds, the child exits (nothing notifies the condition then: poll it) or the
        time is up."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not what(self._status):
                left = deadline - time.monotonic()
                if left <= 0 or self.proc.poll() is not None:
                    return what(self._status)
                self._cond.wait(min(left, 0.2))
            return True

    def wait_ready(self, local_nodes, timeout_s: float) -> None:
        """Until the child's nodes are up and every topic they take from this process's nodes has
        matched them (a reliable message published before the match would be lost)."""
        if not self._wait(lambda st: 'subs' in st, timeout_s):
            raise ConfigError(f'the child process for {", ".join(self.spec.roles)} did not start '
                              f'(exit status {self.proc.poll()}); see its messages above')
        subs = self._status['subs']
        published = {p.topic_name for n in local_nodes for p in n.publishers}
        local = {}
        for n in local_nodes:
            for sub in n.subscriptions:
                local[sub.topic_name] = local.get(sub.topic_name, 0) + 1
        deadline = time.monotonic() + timeout_s
        for topic, n in subs.items():
            if topic not in published:
                continue
            while self.node.count_subscribers(topic) < n + local.get(topic, 0) and time.monotonic() < deadline:
                time.sleep(0.02)

    def counts(self) -> dict:
        with self._cond:
            return dict(self._status.get('counts', {}))

    def busy(self) -> bool:
        with self._cond:
            return bool(self._status.get('busy'))

    def problems(self, role: str) -> list[str]:
        with self._cond:
            return list(self._status.get('problems', {}).get(role, []))

    def _send(self, **command) -> int:
        from std_msgs.msg import String
        with self._cond:
            self._seq += 1
            seq = self._seq
        self._pub.publish(String(data=json.dumps({'seq': seq, **command})))
        return seq

    def call(self, role: str, method: str, timeout_s: float = 600.0, stall_s: float = 90.0, say=None,
             kwargs: dict | None = None) -> None:
        """Run `method` of the child's `role` node and wait until it returned. Waits on the child's status:
        while it works (a counter moves, a node is busy) up to `timeout_s`; a child that sends no status,
        or whose counters stand still with no node busy, for `stall_s` is not waited for any longer (a
        RuntimeError saying so; the child computing, more than CHILD_COMPUTING_CPU_S of CPU time a
        second, counts as work: a final adjustment moves no counter). `say(text)` gets a line every 10 s.
        `kwargs`: the method's keyword arguments (JSON values)."""
        seq = self._send(call=[role, method], kwargs=kwargs or {})
        t0 = moved = last_said = time.monotonic()
        last, cpu = None, process_cpu_s(self.proc.pid)
        while not self._wait(lambda st: st.get('done', 0) >= seq, 1.0):
            now = time.monotonic()
            if self.proc.poll() is not None:
                raise RuntimeError(f'child process: ended (exit status {self.proc.poll()}) before {role}.{method}')
            with self._cond:
                status_age, counts, busy = now - self._status_at, self._status.get('counts'), self._status.get('busy')
            cpu_now = process_cpu_s(self.proc.pid)
            computing = cpu is None or cpu_now is None or cpu_now - cpu > CHILD_COMPUTING_CPU_S
            cpu = cpu_now
            if counts != last or busy or computing:
                last, moved = counts, now
            if status_age > stall_s:
                raise RuntimeError(f'child process: no status for {status_age:.0f} s during {role}.{method} (it hangs)')
            if now - moved > stall_s:
                raise RuntimeError(f'child process: {role}.{method} made no progress for {stall_s:.0f} s '
                                   '(no counter moved, no node busy): not waited for')
            if now - t0 > timeout_s:
                raise RuntimeError(f'child process: {role}.{method} did not finish in {timeout_s:.0f} s')
            if say is not None and now - last_said > 10.0:
                last_said = now
                say(f'end of flight: {now - t0:.0f} s: waiting for {role} ({method}) in the child process'
                    + (' (computing)' if busy else ''))
        err = self._status.get('errors', {}).get(str(seq))
        if err:
            raise RuntimeError(err)

    def stop(self, timeout_s: float = 120.0) -> int:
        """Ask the child to destroy its nodes (the map flushes) and end; SIGTERM, then kill, if it does not."""
        try:
            if self.proc.poll() is None:
                self._send(stop=True)
                try:
                    return self.proc.wait(timeout=timeout_s)
                except subprocess.TimeoutExpired:
                    self.proc.send_signal(signal.SIGTERM)
                    try:
                        return self.proc.wait(timeout=30)
                    except subprocess.TimeoutExpired:
                        self.proc.kill()
            return self.proc.wait()
        finally:
            if self.proc.stdin is not None:
                self.proc.stdin.close()


def child_main(argv=None) -> int:
    """The child process: a Graph of the given roles, plus the status/command node."""
    import rclpy
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
    from rclpy.node import Node

    from photogram_ros.nodes import qos
    from std_msgs.msg import String
    args = sys.argv[1:] if argv is None else argv
    spec = child_spec(args[0])
    limit_malloc_arenas()   # before rclpy.init(): it starts the DDS threads
    init_ros()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # the parent decides when the flight ends
    watch_parent(stop.set)
    graph = None
    try:
        graph = Graph(spec)
        ctl = Node('graph_child', **({'namespace': spec.namespace} if spec.namespace else {}))
        state = {'done': 0, 'errors': {}}
        token = os.environ.get(GRAPH_TOKEN_ENV, '')
        pub = ctl.create_publisher(String, child_topic(TOPIC_CHILD_STATUS, token), qos.reliable())
        subs = {}
        for n in graph.nodes.values():
            for sub in n.subscriptions:
                subs[sub.topic_name] = subs.get(sub.topic_name, 0) + 1

        def status():
            pub.publish(String(data=json.dumps({'counts': graph.counts(), 'busy': graph.busy(), 'subs': subs,
                                                'done': state['done'], 'errors': state['errors'],
                                                'problems': {r: graph.problems(r) for r in graph.nodes}})))

        def command(msg):
            c = json.loads(msg.data)
            if c.get('stop'):
                stop.set()
                return
            role, method = c['call']
            try:
                getattr(graph.nodes[role], method)(**c.get('kwargs', {}))
            except Exception as exc:   # reported to the parent, which prints it
                state['errors'][str(c['seq'])] = f'{type(exc).__name__}: {exc}'
            state['done'] = max(state['done'], c['seq'])
            status()
        # Commands in their own group: a flush taking seconds must not stop the status reports.
        ctl.create_subscription(String, child_topic(TOPIC_CHILD_COMMAND, token), command, qos.reliable(),
                                callback_group=MutuallyExclusiveCallbackGroup())
        ctl.create_timer(0.2, status, callback_group=MutuallyExclusiveCallbackGroup())
        graph.executor.add_node(ctl)
        graph.start()
        while not stop.wait(0.2):
            pass
    except PhotogramError as exc:
        print(f'graph child: {exc}', file=sys.stderr)
        return 2
    finally:
        if graph is not None:
            graph.shutdown()
        rclpy.try_shutdown()
    return 0


def start_separate(spec: GraphSpec) -> list[subprocess.Popen]:
    """One process per node (the console scripts), each given the same parameter file, in its own
    session (a terminal's Ctrl-C reaches only the caller, which stops them in data-flow order) and
    watching a pipe from the caller (they stop when it is gone)."""
    env = {**os.environ, WATCH_PARENT_ENV: '1'}
    procs = []
    for role in spec.roles:
        args = [sys.executable, '-c', f'import sys; from {NODES[role][0]} import main; sys.exit(main())',
                '--ros-args']
        if spec.params_file:
            args += ['--params-file', spec.params_file]
        if spec.namespace:
            args += ['-r', f'__ns:={spec.namespace}']
        for k, v in set_by_command(spec).get(role, {}).items():
            args += ['-p', f'{k}:={v}']
        procs.append(subprocess.Popen(args, env=env, stdin=subprocess.PIPE, start_new_session=True))
    return procs
