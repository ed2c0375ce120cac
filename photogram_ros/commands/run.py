"""photogram-ros run: start the whole mapper (live, on the companion computer)."""

from __future__ import annotations

HELP = 'start every mapping node (mavlink, tracker, bundle, stereo, map) with one parameter file'


def add_arguments(p) -> None:
    p.add_argument('--params', default=None, help='ROS 2 parameter file, e.g. config/onboard_rtk.yaml')
    p.add_argument('--namespace', default='', help='namespace of this drone, e.g. /drone1')
    p.add_argument('--separate', action='store_true', help='one process per node instead of one process')
    p.add_argument('--nodes', default='', help='comma-separated subset of camera,mavlink,tracker,bundle,stereo,map '
                                              '(default: all but camera; camera too when the file configures it)')


def run(a) -> int:
    import signal
    import threading

    import rclpy

    from photogram_ros.errors import ConfigError
    from photogram_ros.nodes.graph import NODES, Graph, GraphSpec, roles_for, start_separate
    roles = tuple(r.strip() for r in a.nodes.split(',') if r.strip()) or roles_for(a.params)
    bad = [r for r in roles if r not in NODES]
    if bad:
        raise ConfigError(f'unknown nodes {bad}; choose from {list(NODES)}')
    spec = GraphSpec(roles=roles, params_file=a.params, namespace=a.namespace)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if a.separate:
        procs = start_separate(spec)
        try:
            while not stop.wait(0.5) and all(p.poll() is None for p in procs):
                pass
        except KeyboardInterrupt:
            pass
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        return max((p.wait(timeout=60) or 0) for p in procs)
    rclpy.init()
    graph = Graph(spec)
    graph.start()
    print(f'photogram_ros running: {", ".join(graph.nodes)} (Ctrl-C flushes the map and writes the exports)')
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        graph.finish_flight()
        graph.shutdown()
        rclpy.try_shutdown()
    return 0
