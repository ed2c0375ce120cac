"""photogram-ros ground-station: follow one or more drones' maps over DDS and save them."""

from __future__ import annotations

HELP = 'receive the downsampled maps, poses and health of drones on the same DDS domain and save them'


def add_arguments(p) -> None:
    p.add_argument('--namespaces', default='', help='comma-separated drone namespaces (default: discover all)')
    p.add_argument('--out', default='ground_station', help='folder for the merged cloud, tracks and status')
    p.add_argument('--crs', default='', help='EPSG code of the saved cloud (default: UTM of the first drone)')
    p.add_argument('--save-period', type=float, default=10.0, help='seconds between saves')
    p.add_argument('--duration', type=float, default=0.0, help='stop after this many seconds (0 = until Ctrl-C)')


def run(a) -> int:
    import time

    import rclpy

    from photogram_ros.nodes.ground_station import GroundStationNode
    rclpy.init()
    node = GroundStationNode(overrides={'namespaces': a.namespaces, 'out_dir': a.out, 'crs': a.crs,
                                        'save_period_s': float(a.save_period)})
    start = time.monotonic()
    last_print = 0.0
    try:
        while rclpy.ok() and (not a.duration or time.monotonic() - start < a.duration):
            rclpy.spin_once(node, timeout_sec=0.2)
            if time.monotonic() - last_print > 5.0:
                last_print = time.monotonic()
                parts = [f'{ns or "/"}: {len(d.poses)} keyframes, {d.points} points' for ns, d in node.drones.items()]
                print(f'[ground station] {len(node.merged_cloud())} merged cells; '
                      + ('; '.join(parts) or 'waiting for drones'))
    except KeyboardInterrupt:
        pass
    finally:
        node.save()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
