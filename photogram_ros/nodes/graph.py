"""The mapping graph: every node of photogram_ros composed in one process, or one process per node.

One process (the default) shares a MultiThreadedExecutor, so images travel between nodes without
leaving the process's DDS participant. `--separate` starts the console scripts instead, with the same
parameter file, for integrators who want to restart or pin nodes individually.
"""

from __future__ import annotations

import importlib
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

from photogram_ros.errors import ConfigError
from photogram_ros.params import load_params_file

# role -> (module, class, console script); the order is the data-flow order.
NODES = {
    'camera': ('photogram_ros.nodes.camera_node', 'CameraNode', 'camera_node'),
    'mavlink': ('photogram_ros.nodes.mavlink_node', 'MavlinkNode', 'mavlink_node'),
    'tracker': ('photogram_ros.nodes.tracker_node', 'TrackerNode', 'tracker_node'),
    'bundle': ('photogram_ros.nodes.bundle_node', 'BundleNode', 'bundle_node'),
    'stereo': ('photogram_ros.nodes.stereo_node', 'StereoNode', 'stereo_node'),
    'map': ('photogram_ros.nodes.map_node', 'MapNode', 'map_node'),
}


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


class Graph:
    """All nodes in one process, spun by a multi-threaded executor in a background thread."""

    def __init__(self, spec: GraphSpec, context=None):
        from rclpy.executors import MultiThreadedExecutor
        self.spec = spec
        sections = _sections(spec)
        self.nodes = {}
        kwargs = {'namespace': spec.namespace} if spec.namespace else {}
        if context is not None:
            kwargs['context'] = context
        for role in spec.roles:
            cls = node_class(role)
            script = NODES[role][2]
            values = dict(sections.get('**', {}))
            for name, section in sections.items():
                if name.split('/')[-1] == script:
                    values.update(section)
            values.update((spec.extra or {}).get(role, {}))
            self.nodes[role] = cls(overrides=values, **kwargs)
        self.executor = MultiThreadedExecutor(num_threads=4, context=context)
        for n in self.nodes.values():
            self.executor.add_node(n)
        self._thread = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self.executor.spin, daemon=True, name='graph-executor')
        self._thread.start()

    def finish_flight(self, settle=lambda: time.sleep(2.0)) -> None:
        """End of flight, in data-flow order: the tracker emits the keyframes it still holds, the
        bundle adjuster runs its final adjustment and republishes the poses, stereo pairs the
        keyframes still waiting; `settle` lets the downstream nodes consume each step's output."""
        for role, method in (('tracker', 'flush'), ('bundle', 'finish'), ('stereo', 'flush')):
            fn = getattr(self.nodes.get(role), method, None)
            if callable(fn):
                try:
                    fn()
                except Exception as exc:  # one node's failure must not lose the others' data
                    print(f'{role}: {method} failed: {exc}', file=sys.stderr)
                settle()

    def shutdown(self) -> None:
        """Stop spinning and destroy the nodes (the map node flushes its tiles to disk on destroy)."""
        self.executor.shutdown(timeout_sec=5)
        for n in self.nodes.values():
            n.destroy_node()


def start_separate(spec: GraphSpec) -> list[subprocess.Popen]:
    """One process per node (the console scripts), each given the same parameter file."""
    procs = []
    for role in spec.roles:
        args = [sys.executable, '-c', f'import sys; from {NODES[role][0]} import main; sys.exit(main())',
                '--ros-args']
        if spec.params_file:
            args += ['--params-file', spec.params_file]
        if spec.namespace:
            args += ['-r', f'__ns:={spec.namespace}']
        for k, v in (spec.extra or {}).get(role, {}).items():
            args += ['-p', f'{k}:={v}']
        procs.append(subprocess.Popen(args))
    return procs
