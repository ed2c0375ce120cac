"""photogram-ros ground-station: follow one or more drones' maps and survey quality over DDS, save them,
and (--web HOST:PORT) serve the map page: live ortho, tracks, gaps, check points, go / no-go."""

from __future__ import annotations

HELP = ('receive the maps, poses, health and survey quality of drones on the same DDS domain, save them and '
        'serve the map page (--web HOST:PORT)')


def add_arguments(p) -> None:
    p.add_argument('--params', default=None, help='parameter file with a ground_station section '
                                                  '(e.g. config/ground_station.yaml); options below override it')
    p.add_argument('--namespaces', default=None, help='comma-separated drone namespaces (default: discover all)')
    p.add_argument('--out', default=None, help='folder for the merged cloud, tracks and status')
    p.add_argument('--crs', default=None, help='EPSG code of the saved cloud (default: UTM of the first drone)')
    p.add_argument('--save-period', type=float, default=None, help='seconds between saves')
    p.add_argument('--duration', type=float, default=0.0, help='stop after this many seconds (0 = until Ctrl-C)')
    p.add_argument('--web', default=None, metavar='HOST:PORT',
                   help='serve the map page (/, /status.json, /tiles/DRONE/Z/X/Y.png), e.g. 127.0.0.1:8080')


def run(a) -> int:
    import time

    import rclpy

    from photogram_ros.nodes.ground_station import GroundStationNode
    from photogram_ros.params import load_params_file
    values = load_params_file(a.params).get('ground_station', {}) if a.params else {}
    for opt, name in (('namespaces', 'namespaces'), ('out', 'out_dir'), ('crs', 'crs'),
                      ('save_period', 'save_period_s'), ('web', 'web')):
        if getattr(a, opt) is not None:
            values[name] = getattr(a, opt)
    rclpy.init()
    node = GroundStationNode(overrides=values)
    if node.web is not None:
        print(f'[ground station] map page on {node.web.url}', flush=True)
    start = time.monotonic()
    last_print = 0.0
    try:
        while rclpy.ok() and (not a.duration or time.monotonic() - start < a.duration):
            rclpy.spin_once(node, timeout_sec=0.2)
            if time.monotonic() - last_print > 5.0:
                last_print = time.monotonic()
                parts = []
                for ns, d in node.drones.items():
                    gng = node.drone_status(d)['go_no_go']
                    parts.append(f'{ns or "/"}: {len(d.poses)} keyframes, {d.points} points, {len(d.tiles)} ortho '
                                 f'tiles, {gng["verdict"]}' + (f' ({"; ".join(gng["reasons"])})' if gng['reasons'] else ''))
                print(f'[ground station] {len(node.merged_cloud())} merged cells; '
                      + ('; '.join(parts) or 'waiting for drones'), flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        node.save()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
