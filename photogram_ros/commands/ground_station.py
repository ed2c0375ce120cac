"""photogram-ros ground-station: follow the allowed drones' maps and survey quality over DDS, save them,
and (--web HOST:PORT) serve the map page: live ortho over an offline base map, tracks, gaps, check points,
go / no-go. SIGINT / SIGTERM save and exit 0; a failure says where the saved files are."""

from __future__ import annotations

HELP = ('receive the maps, poses, health and survey quality of drones on the same DDS domain, save them and '
        'serve the map page (--web HOST:PORT)')


def add_arguments(p) -> None:
    p.add_argument('--params', default=None, help='parameter file with a ground_station section '
                                                  '(e.g. config/ground_station.yaml); options below override it')
    p.add_argument('--drones', '--namespaces', dest='drones', default=None, metavar='NS[,NS...]',
                   help='allow-list of drone namespaces, e.g. /drone1,/drone2 ("/" for the root namespace); '
                        'others are shown as unknown and never counted (default: every drone found)')
    p.add_argument('--out', default=None, help='folder for the merged cloud, tracks and status')
    p.add_argument('--crs', default=None, help='EPSG code of the saved cloud (default: UTM of the first drone)')
    p.add_argument('--save-period', type=float, default=None, help='seconds between saves')
    p.add_argument('--duration', type=float, default=0.0, help='stop after this many seconds (0 = until Ctrl-C)')
    p.add_argument('--web', default=None, metavar='HOST:PORT',
                   help='serve the map page, e.g. 127.0.0.1:8080 (this machine only; :8080 the same); '
                        '0.0.0.0:8080 serves other machines, only with the token')
    p.add_argument('--web-token', default=None, help='token other machines must give (default: generated, printed)')
    p.add_argument('--basemap', default=None, metavar='DIR|FILE.mbtiles',
                   help='offline base map under the ortho: an XYZ tile folder (Z/X/Y.png) or an MBTiles file')


def run(a) -> int:
    import signal
    import sys
    import time
    import traceback
    early = []   # SIGINT / SIGTERM before the station's own handlers are in place (rclpy loads for a second)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: early.append(signum))

    import rclpy

    from photogram_ros.errors import ConfigError, PhotogramError
    from photogram_ros.nodes.ground_station import GroundStationNode, security_status
    from photogram_ros.nodes.node_main import StopSignals, init_ros
    from photogram_ros.params import load_params_file
    from photogram_ros.web.server import parse_host_port
    if not 0 <= a.duration < float('inf'):   # said before anything starts, like --web below
        raise ConfigError(f'--duration {a.duration:g}: seconds to run, 0 (until Ctrl-C) or more')
    if a.web:
        parse_host_port(a.web)
    values = load_params_file(a.params).get('ground_station', {}) if a.params else {}
    for opt, name in (('drones', 'drones'), ('out', 'out_dir'), ('crs', 'crs'), ('save_period', 'save_period_s'),
                      ('web', 'web'), ('web_token', 'web_token'), ('basemap', 'basemap')):
        if getattr(a, opt) is not None:
            values[name] = getattr(a, opt)
    security = security_status()
    if security['refuse']:
        print(f'[ground station] {security["refuse"]}', file=sys.stderr, flush=True)
        return 2
    signals = StopSignals('saving')
    if early:   # asked to stop while starting: it saves what it has (nothing yet) and exits 0
        signals.signal_name = signal.Signals(early[0]).name
        signals.stop.set()
    init_ros()
    try:
        node = GroundStationNode(overrides=values)
    except (PhotogramError, RuntimeError) as exc:   # RuntimeError: rclpy's RCLError (e.g. a missing enclave)
        print(f'[ground station] cannot start: {exc}', file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        return 2
    print(f'[ground station] {node.security["headline"]}', flush=True)
    print(f'[ground station] ROS 2 security: {node.security["summary"]}', flush=True)
    if node.web is not None:
        print(f'[ground station] map page on {node.web.url_with_token()}'
              + ('' if node.web.local_only else ' (other machines need this token)'), flush=True)
    start = time.monotonic()
    last_print = 0.0
    failed = None
    try:
        while not signals.stop.is_set() and (not a.duration or time.monotonic() - start < a.duration):
            rclpy.spin_once(node, timeout_sec=0.2)
            if time.monotonic() - last_print > 5.0:
                last_print = time.monotonic()
                print(f'[ground station] {progress(node)}', flush=True)
    except Exception as exc:   # noqa: BLE001 (said with where the files are)
        failed = exc
        traceback.print_exc()
    saved = True
    try:
        node.save()
    except Exception as exc:   # noqa: BLE001
        saved = False
        print(f'[ground station] the last save failed: {type(exc).__name__}: {exc}', file=sys.stderr, flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    where = f'{node.out.resolve()} (status.json, merged_cloud.ply, <drone>_track.csv, <drone>_gaps.geojson, tiles/)'
    if failed is not None:
        what = 'the files saved so far are' if saved else 'earlier saves are'
        print(f'[ground station] stopped by an error: {type(failed).__name__}: {failed}; {what} in {where}',
              file=sys.stderr, flush=True)
        return 1
    print(f'[ground station] {"stopped by " + signals.signal_name if signals.signal_name else "done"}; '
          f'saved in {where}', flush=True)
    return 0


def progress(node) -> str:
    parts = []
    for ns, d in list(node.drones.items()):
        gng = node.drone_status(d)['go_no_go']
        parts.append(f'{ns or "/"}: {len(d.poses)} keyframes, {d.points} points, {len(d.tiles)} ortho '
                     f'tiles, {gng["verdict"]}' + (f' ({"; ".join(gng["reasons"])})' if gng['reasons'] else ''))
    unknown = f'; unknown (not counted): {", ".join(sorted(node.unknown))}' if node.unknown else ''
    return f'{len(node.merged_cloud())} merged cells; ' + ('; '.join(parts) or 'waiting for drones') + unknown
