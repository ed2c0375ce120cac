"""photogram-ros geotag: camera positions at the exposures from a PPK antenna track -> geo.txt (+ CSV)."""

from __future__ import annotations

from photogram_ros.commands import common_args

HELP = ('PPK geotagging: a post-processed antenna track (RTKLIB/Emlid .pos, GrafNav/Inertial Explorer export, '
        'Emlid/TBC/Leica CSV, recognised by content) and the camera events (DJI Timestamp.MRK, ArduPilot .bin CAM/TRIG, '
        '.tlog CAMERA_FEEDBACK / PX4 CAMERA_TRIGGER / CAMERA_IMAGE_CAPTURED, or the photos\' EXIF times) -> '
        'OpenDroneMap geo.txt and a CSV for Pix4D/Metashape')


# --accept -> the worst quality used on the common scale (RTKLIB Q: 1 fix, 2 float, 3 sbas, 4 dgps, 5 single, 6 ppp).
ACCEPT_Q = {'fix': 1, 'float': 2, 'dgps': 4, 'single': 5, 'all': 6}


def add_arguments(p) -> None:
    p.add_argument('--pos', help='the post-processed antenna track, recognised by its content: RTKLIB / RTKLIB-demo5 '
                                 '/ Emlid Studio .pos (and *_events.pos), a NovAtel GrafNav / Inertial Explorer '
                                 'ASCII export, an Emlid Studio, Trimble Business Center or Leica Infinity CSV; '
                                 'not given with a DJI MRK: the MRK\'s own onboard RTK positions')
    p.add_argument('--events', required=True, help='Timestamp.MRK, an ArduPilot .bin, a .tlog, or "exif" (the '
                                                   'photos\' EXIF times)')
    p.add_argument('--photos', help='folder of the photos (default: the events file\'s folder when it holds '
                                    'photos); without photos the rows are named event_NNNN')
    p.add_argument('--out', help='geo.txt to write (default: geo.txt in the photos\' folder, where triangulate reads '
                                 'it; without photos, geo.txt in the current folder)')
    p.add_argument('--csv', help='CSV to write (default: beside --out, .csv)')
    common_args.add_lever_arm_body(p, 'Turned by each event\'s attitude; level along the track without one. Not '
                                      'with an MRK: its per-photo N/E/V offsets are the lever arm')
    p.add_argument('--match', choices=('auto', 'number', 'order', 'time'), default='auto',
                   help='photo <-> event: by the number in the photo name, by order, by EXIF time, or auto')
    p.add_argument('--match-tolerance', type=float, default=1.5, help='largest time mismatch of a pair, s')
    p.add_argument('--utc-offset', type=float, default=0.0,
                   help='camera clock minus UTC, s, for EXIF times without a zone (e.g. 7200 for CEST)')
    p.add_argument('--event-type', default='auto',
                   help='CAM or TRIG (.bin); CAMERA_FEEDBACK, CAMERA_TRIGGER or CAMERA_IMAGE_CAPTURED (.tlog)')
    p.add_argument('--max-gap', type=float, default=-1.0,
                   help='longest track gap an exposure is interpolated across, s (-1: 2.5x the epoch interval)')
    p.add_argument('--sigma-scale', type=float, default=1.0, help='factor on the solution\'s formal sigmas')
    p.add_argument('--accept', choices=tuple(ACCEPT_Q), default='all',
                   help='worst solution quality used for a photo, on the one scale every format maps to (fix < float '
                        '< sbas < dgps < single < ppp; docs/commands.md has each format\'s table)')
    p.add_argument('--interpolation', choices=('linear', 'cubic'), default=None,
                   help='between two epochs: linear (as the surveyors\' PPK tools interpolate) or cubic (Hermite on '
                        'centred-difference velocities, linear next to a gap or an end); default linear')
    p.add_argument('--event-delay-ms', type=float, default=0.0,
                   help='the exposure this long after its event mark (the shutter\'s delay), ms; negative: before. '
                        'Every event is moved along the trajectory by it before interpolation')
    p.add_argument('--accept-no-fix', action='store_true', help='use a .pos that has no fixed epoch at all')
    p.add_argument('--skip-unplaced', action='store_true',
                   help='write the photos that could be placed and list the others, instead of stopping')


def run(a) -> int:
    import sys
    from pathlib import Path

    from photogram_ros.params import floats
    from photogram_ros.core.exposure_positions import Q_NAMES, ExposureOptions
    from photogram_ros.io.geotag import GeotagInput, geotag

    from photogram_ros.io.geotag import photos_in
    folder = a.photos or (str(Path(a.events).parent) if a.events != 'exif' and photos_in(Path(a.events).parent)
                          else None)
    out = a.out or str(Path(folder) / 'geo.txt' if folder else Path('geo.txt'))
    opt = ExposureOptions(max_gap_s=float(a.max_gap), sigma_scale=float(a.sigma_scale),
                          lever_arm_frd_m=floats(a.lever_arm, '--lever-arm', 3),
                          accept_q=ACCEPT_Q[a.accept], event_delay_s=float(a.event_delay_ms) * 1e-3,
                          **({'interpolation': a.interpolation} if a.interpolation else {}))
    res = geotag(GeotagInput(a.pos, a.events, folder, out, a.csv, a.match, a.match_tolerance, a.utc_offset,
                             a.event_type, a.accept_no_fix, a.skip_unplaced, opt))
    for n in res.notes:
        print(f'note: {n}', file=sys.stderr)
    for p in res.problems:
        print(f'problem: {p}', file=sys.stderr)
    q = {}
    for _, pe in res.rows:
        q[Q_NAMES.get(pe.q, str(pe.q))] = q.get(Q_NAMES.get(pe.q, str(pe.q)), 0) + 1
    h = sorted(pe.h_acc_m for _, pe in res.rows)
    v = sorted(pe.v_acc_m for _, pe in res.rows)
    print(f'geotagged {len(res.rows)} photos ({", ".join(f"{n} {k}" for k, n in q.items())}; matched '
          f'{res.match_how}; {res.placement.mode}); accuracy median {h[len(h) // 2] * 100:.1f} cm horizontal, '
          f'{v[len(v) // 2] * 100:.1f} cm vertical; wrote {res.geo_txt} and {res.csv}')
    return 0
