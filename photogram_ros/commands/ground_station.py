"""photogram-ros ground-station: follow one or more drones' maps over DDS and save them."""

from __future__ import annotations

HELP = 'receive the downsampled maps, poses and health of drones on the same DDS domain and save them'


def add_arguments(p) -> None:
    p.add_argument('--params', default=None, help='parameter file with a ground_station section '
                                                  '(e.g. config/ground_station.yaml); options below override it')
    p.add_argument('--namespaces', default=None, help='comma-separated drone namespaces (default: discover all)')
    p.add_argument('--out', default=None, help='folder for the merged cloud, tracks and status')
    p.add_argument('--crs', default=None, help='EPSG code of the saved cloud (default: UTM of the first drone)')
    p.add_argument('--save-period', type=float, default=None, help='seconds between saves')
    p.add_argument('--duration', type=float, default=0.0, help='stop after this many seconds (0 = until Ctrl-C)')


def run(a) -> int:
    import time

    import rclpy

    from photogram_ros.nodes.ground_station import GroundStationNode
    from photogram_ros.params import load_params_file
    values = load_params_file(a.params).get('ground_station', {}) if a.params else {}
    for opt, name in (('namespaces', 'namespaces'), ('out', 'out_dir'), ('crs', 'crs'),
                      ('save_period', 'save_period_s')):
        if getattr(a, opt) is not None:
            values[name] = getattr(a, opt)
    rclpy.init()
    node = GroundStationNode(overrides=values)
    start = time.monotonic()
    last_print = 0.0
    try:
        while rclpy.ok() and (not a.duration or time.monotonic() - start < a.duration):
            rclpy.spin_once(node, timeout_sec=0.2)
            if time.monotonic() - last_print > 5.0:
                last_print = time.monotonic()
                parts = [f'{ns or "/"}: {len(d.poses)} keyframes, {d.points} points' for ns, d in node.drones.items()]
                print(f'[ground station] {len(node.merged_cloud())} merged cells; '
                      + ('; '.join(parts) or 'waiting for drones'), flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        node.save()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
