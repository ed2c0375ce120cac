"""photogram-ros run: start the whole mapper (live, on the companion computer)."""

from __future__ import annotations

HELP = 'start every mapping node (mavlink, tracker, bundle, stereo, map) with one parameter file'


def add_arguments(p) -> None:
    p.add_argument('--params', default=None, help='ROS 2 parameter file, e.g. config/onboard_rtk.yaml')
    p.add_argument('--namespace', default='', help='namespace of this drone, e.g. /drone1')
    p.add_argument('--separate', action='store_true', help='one process per node instead of one process')
    p.add_argument('--nodes', default='', help='comma-separated subset of camera,mavlink,tracker,bundle,stereo,map '
                                              '(default: all but camera; camera too when the file configures it)')
    p.add_argument('--out', default='products', help='where the survey products go when the mapper stops (SIGINT or '
                                                    'SIGTERM): clouds, DSM, orthomosaic, trajectory, report')
    p.add_argument('--crs', default='', help='CRS of the products (default: UTM zone of the map origin)')
    p.add_argument('--no-export', action='store_true', help='only flush the map when stopping (export later with '
                                                            'photogram-ros export MAPDIR --densify)')
    p.add_argument('--live-map', action='store_true', help='export the in-flight map instead of matching the '
                                                           'keyframes again from the final adjustment')


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
        rc = max((p.wait(timeout=60) or 0) for p in procs)
        return rc or _export_at_stop(a, roles)
    rclpy.init()
    graph = Graph(spec)
    graph.start()
    print(f'photogram_ros running: {", ".join(graph.nodes)} (Ctrl-C flushes the map and writes the products to '
          f'{a.out}/)' if not a.no_export else f'photogram_ros running: {", ".join(graph.nodes)}', flush=True)
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        graph.finish_flight()
        graph.shutdown()
        rclpy.try_shutdown()
    return _export_at_stop(a, roles)


def map_dir_of(params_file: str | None) -> str:
    """The map node's map_dir in a parameter file (its default without one)."""
    from photogram_ros.nodes.map_node import MapParams
    from photogram_ros.params import from_dict, load_params_file
    sections = load_params_file(params_file) if params_file else {}
    return from_dict(MapParams, sections.get('map_node', {}), f'{params_file} map_node').map_dir


def _export_at_stop(a, roles) -> int:
    if a.no_export or 'map' not in roles:
        return 0
    from photogram_ros.commands.products import export_products
    from photogram_ros.errors import PhotogramError
    try:
        res = export_products(map_dir_of(a.params), a.out, a.params, a.crs, a.live_map)
    except (PhotogramError, OSError) as exc:   # the map itself is safe on disk: say how to export it later
        print(f'exports failed ({exc}); the map is on disk: photogram-ros export MAPDIR --densify', flush=True)
        return 3
    for n in res.get('notes', []):
        print(f'note: {n}', flush=True)
    if res.get('files'):
        print(f"products in {a.out}/ ({res['crs']}): " + ', '.join(sorted(res['files'])) + ', report', flush=True)
    return 0
