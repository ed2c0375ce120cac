"""photogram-ros replay: run photogram_ros on a recorded flight and write the map and the report.

The flight is a bag, a folder of geotagged photos (played in EXIF time order with their EXIF GPS, the
camera from the EXIF unless --calibration) or a video file with its GNSS log (--gnss-log, a CSV as
`photogram-ros fixes --format csv` writes from a .tlog, a dataflash .bin or a bag; --calibration). The
replay ends by itself at the end of the flight and writes the products and the report. `--resume` continues the
map in --out as `run --resume` does (`resume_extra`): the adjuster anchored at the map's origin, the keyframes saved
without a pose (a crash) fed again first, and the keyframes from before counted in the report.
"""

from __future__ import annotations

from photogram_ros.commands import common_args

HELP = ('replay a flight (bag, photo folder, or video + GNSS log) through the whole mapper; writes clouds, DSM, '
        'ortho, trajectory and report to --out')
EXIT_NOT_MAPPED = 5


def add_arguments(p) -> None:
    p.add_argument('bag', metavar='FLIGHT',
                   help='rosbag2 folder (sqlite3 or MCAP), a folder of geotagged photos, or a video file (with '
                        '--gnss-log)')
    p.add_argument('--calibration', default='', help='camera calibration YAML for a video (a photo folder takes '
                                                    'its camera from the EXIF without it)')
    p.add_argument('--gnss-log', default='', help='GNSS fixes of a video: CSV with t_unix_s, lat_deg, lon_deg, h_m '
                                                  '(ellipsoidal) and optional variances, e.g. from photogram-ros '
                                                  'fixes LOG.tlog --format csv')
    p.add_argument('--video-start', type=float, default=0.0,
                   help='Unix time of the video\'s first frame (default: the first fix of --gnss-log)')
    p.add_argument('--out', default='output/replay', help='output folder')
    p.add_argument('--params', default=None, help='ROS 2 parameter file (default: the package\'s config/replay.yaml)')
    p.add_argument('--rate', type=float, default=0.0, help='bag time speed; 0 = as fast as the mapper keeps up')
    p.add_argument('--crs', default='', help='output CRS, e.g. EPSG:2056 (default: UTM zone of the map origin)')
    common_args.add_heights(p, old_flag='--orthometric')
    common_args.add_exif_altitude(p, 'For a photo folder (camera_node\'s exif_altitude)')
    p.add_argument('--min-pairs', type=int, default=2,
                   help='export only cells confirmed by this many stereo pairs (1 keeps everything)')
    common_args.add_live_control(p)
    p.add_argument('--live-map', action='store_true',
                   help='make the products from the in-flight map (pairs matched with the poses they had when '
                        'they left the bundle window) instead of matching the keyframes again with the final '
                        'adjustment\'s poses into OUT/map_final (the default; seconds for the sample)')
    p.add_argument('--truth', default='', metavar='SIM_FLIGHT',
                   help='for development: a simulated flight folder (`photogram-ros simulate`); the report then '
                        'also compares the cameras, check points (its targets), DSM and cloud with its ground '
                        'truth. Nothing of it enters the mapping or the products')
    p.add_argument('--quiet', action='store_true', help='no progress lines')
    reuse = p.add_mutually_exclusive_group()
    reuse.add_argument('--resume', action='store_true',
                       help='--out holds a previous replay: continue its map (products are replaced; its '
                            'keyframes saved without a pose, as a crash leaves them, are fed again first)')
    reuse.add_argument('--overwrite', action='store_true',
                       help='--out holds a previous replay: delete it first (without --resume or --overwrite an '
                            '--out that holds anything is refused; a folder another replay is writing always is)')
    p.add_argument('--domain', type=int, default=None, metavar='N',
                   help='ROS_DOMAIN_ID to replay on, e.g. your own to watch the replay in RViz or Foxglove '
                        '(default: a free domain of its own in 215-232, so that no other ROS 2 process hears '
                        'the old flight and the replay hears no one else)')
    common_args.add_processes(p)


def resume_extra(extra: dict, kind: str, params_file: str | None, map_dir, before: dict) -> dict:
    """`extra` (role -> parameter overrides) for a replay resuming the map `map_dir` that holds keyframes from before
    (commands/run.keyframes_before): the adjuster anchored at the map's origin, and for a photo folder or a video
    (`kind`, replay_session.source_kind) the keyframes saved without a pose fed again first by camera_node
    (resume_keyframes_of), as `run --resume` does (commands/run.in_the_map_origin, feed_unposed_keyframes). A bag
    is played again whole: its frames are taken again as they come."""
    from photogram_ros.commands.run import feed_unposed_keyframes, in_the_map_origin
    from photogram_ros.nodes.graph import GraphSpec
    roles = ('tracker', 'bundle') if kind == 'bag' else ('camera', 'tracker', 'bundle')
    spec = in_the_map_origin(GraphSpec(roles=roles, params_file=params_file, extra=extra), map_dir)
    if kind != 'bag':
        spec = feed_unposed_keyframes(spec, map_dir, before)
    return {r: dict(v) for r, v in (spec.extra or {}).items()}


def run(a) -> int:
    """Exit status 0; 2 bad input (before the first frame); 3 the bag was damaged (what it held was
    mapped); 4 the final adjustment failed (products from the in-flight poses); 5 the flight did not
    map (no georeferenced keyframe, fewer than half of the keyframes oriented, or the DSM mostly
    empty: the report's Verdict and the last line say why), when nothing above applies."""
    import json
    from pathlib import Path

    import rclpy

    from photogram_ros.commands.products import check_output_crs, export_products
    from photogram_ros.nodes.node_main import init_ros
    from photogram_ros.nodes.replay_session import ReplayOptions, run_replay, source_kind
    from photogram_ros.io.flight_verdict import keyframes_line
    from photogram_ros.commands.run import count_keyframes_before, keyframes_before
    from photogram_ros.errors import ConfigError
    from photogram_ros.sim.truth import GroundTruth

    from photogram_ros.io.out_dir import claim_output
    from photogram_ros.nodes.ros_domain import (check_domain_env, own_domain, parse_domain, shared_domain,
                                                  use_domain)

    params = a.params
    if params is None:
        from photogram_ros.package_files import config_file
        found = config_file('replay.yaml')   # from the package, wherever the command runs
        params = str(found) if found is not None else None
    out = Path(a.out)
    if not 0 <= a.rate <= 10000:   # said before any process starts
        raise ConfigError(f'--rate {a.rate:g}: the flight\'s speed factor, 0 (as fast as the mapper keeps up) '
                          'to 10000')
    if a.min_pairs < 1:
        raise ConfigError(f'--min-pairs {a.min_pairs}: 1 (keep every cell) or more')
    if not -1e12 < a.video_start < 1e12:
        raise ConfigError(f'--video-start {a.video_start:g}: the Unix time of the video\'s first frame, s')
    child = common_args.child_roles(a)
    if a.crs:   # checked now, not after the whole replay
        check_output_crs(a.crs)
    source_kind(a.bag)   # a flight that is not there: said before any folder is made
    if a.truth and not GroundTruth.exists(a.truth):
        raise ConfigError(f'--truth {a.truth}: no simulator ground truth (ground_truth.json) there')
    domain = shared_domain(parse_domain(a.domain, '--domain')) if a.domain is not None else \
        own_domain(avoid=check_domain_env())
    extra = {}
    camera = common_args.exif_altitude_overrides(a)   # checked before any process starts
    if camera:
        extra['camera'] = camera
    control = common_args.live_control(a)   # a bad file is reported before the replay starts
    lock = claim_output(out, 'resume' if a.resume else 'overwrite' if a.overwrite else 'new', 'replay')
    if lock.previous:
        print(f'note: --resume: continuing the map in {out}', flush=True)
    before = keyframes_before(out / 'map') if a.resume else None
    if before is not None:
        extra = resume_extra(extra, source_kind(a.bag), params, out / 'map', before)
    use_domain(domain)
    if a.domain is None and not a.quiet:
        print(f'replaying on ROS_DOMAIN_ID {domain}, a domain of its own (--domain N to watch it from another '
              'ROS 2 tool)', flush=True)
    init_ros()   # Ctrl-C is a KeyboardInterrupt: the graph still shuts down in order (the map flushes)
    try:
        res = run_replay(ReplayOptions(bag=a.bag, out=str(out), params_file=params, rate=a.rate,
                                       progress=not a.quiet, child_roles=child, extra=extra,
                                       calibration_file=a.calibration, gnss_log=a.gnss_log,
                                       video_start_unix_s=a.video_start, control=control))
    finally:
        rclpy.try_shutdown()
    if before is not None:   # the keyframes of the map from before this replay are taken too (the report's N of N)
        res['run']['resumed'] = count_keyframes_before(res['run'].setdefault('counts', {}), before, out / 'map')
    truth = GroundTruth.load(a.truth) if a.truth else None
    prod = export_products(res['map_dir'], out, params, a.crs, a.live_map, a.heights, a.min_pairs,
                           progress=not a.quiet, run=res['run'], truth=truth,
                           control=control.targets if control is not None else None,
                           diagnostics=res['diagnostics'])
    files, notes, figures = prod['files'], prod['notes'], prod['figures']
    res['run'] = figures.get('run', res['run'])
    (out / 'run.json').write_text(json.dumps({**res['run'], 'notes': notes}, indent=1, default=str))
    r = res['run']
    print(f"replayed {r['frames']} frames ({r['bag_s']:.1f} s of flight) in {r['wall_s']:.1f} s, "
          f"real-time factor {r['real_time_factor']:.2f}; {figures.get('keyframes', 0)} keyframes, "
          f"{r.get('map_points', 0)} map points")
    print(keyframes_line(figures))
    for h in figures.get('health', []):
        if h['worst_level'] != 'OK':
            print(f"health: {h['node']} {h['worst_level']}: {' | '.join(h['reasons'])[:300]}")
    cp = figures.get('check_points', {}).get('rmse')
    if cp and cp.get('count'):
        ce = figures['check_points'].get('ce90_le90', {})
        print(f"check points: RMSE horizontal {cp['horizontal_m'] * 100:.1f} cm, vertical {cp['z_m'] * 100:.1f} cm "
              f"over {cp['count']} targets" + (f"; CE90 {ce['ce90_m'] * 100:.1f} cm, LE90 {ce['le90_m'] * 100:.1f} cm"
                                               if ce.get('n') else ''))
    gr = figures.get('gcp_residuals', {}).get('rmse')
    if gr and gr.get('count'):
        v = f"{gr['z_m'] * 100:.1f} cm" if gr.get('z_m') is not None else 'not used (no GCP height was)'
        print(f"GCP residuals (the fit, not the accuracy): RMSE horizontal {gr['horizontal_m'] * 100:.1f} cm, "
              f"vertical {v} over {gr['count']} GCPs ({figures['gcp_residuals'].get('used_by_adjuster', '?')} used "
              'by the adjuster)')
    for f in figures.get('gcp_residuals', {}).get('faults', []):
        print(f'control: {f}')
    written = sorted(Path(f).name for f in files.values()) + ['report.html', 'report.md', 'report.json']
    written += ['trajectory.csv'] if (out / 'trajectory.csv').exists() else []
    print(f'outputs in {out}/: ' + ', '.join(written))
    for n in notes:
        print(f'note: {n}')
    for e in r['bag_errors']:
        print(f'bag damaged: {e}')
    if r.get('final_adjustment') == 'failed':
        print(f"the final adjustment failed ({r.get('final_adjustment_reason', '')}): products from the in-flight poses")
    if r.get('end_of_flight_errors'):
        print('end of flight: ' + '; '.join(r['end_of_flight_errors']))
    verdict = figures.get('mapping', {'mapped': False, 'failures': ['no report was made']})
    print('MAPPING FAILED: ' + '; '.join(verdict['failures']) if not verdict['mapped'] else
          f"mapped: {figures.get('keyframes_oriented', 0)} of {figures.get('keyframes_taken', 0)} keyframes oriented"
          + ''.join(f'; WARNING: {w}' for w in verdict.get('warnings', [])))
    if r['bag_errors']:
        return 3
    if r.get('final_adjustment') == 'failed' or r.get('end_of_flight_errors'):
        return 4
    return 0 if verdict['mapped'] else EXIT_NOT_MAPPED
