"""photogram-ros simulate: write a synthetic survey flight with its ground truth."""

from __future__ import annotations

HELP = 'simulate a survey flight: a bag, a .tlog and the ground truth beside them'


def _number(text: str, option: str, example: str) -> float:
    from photogram_ros.errors import ConfigError
    try:
        v = float(text)
    except ValueError:
        v = float('nan')
    if v != v or v in (float('inf'), float('-inf')):
        raise ConfigError(f'{option} {text!r}: not a number (e.g. {option} "{example}")')
    return v


def _pairs(text: str, option: str, example: str, kind=None) -> list:
    """'10:20,30:40' -> [(10.0, 20.0), (30.0, 40.0)]; `kind` converts the second value (a number by
    default). A ConfigError naming the option and an example for anything else."""
    from photogram_ros.errors import ConfigError
    out = []
    for item in filter(None, (s.strip() for s in text.split(','))):
        a, sep, b = item.partition(':')
        if not sep or ':' in b:
            raise ConfigError(f'{option} {item!r}: give FROM:TO pairs separated by commas, e.g. {option} "{example}"')
        out.append((_number(a, option, example), kind(b) if kind else _number(b, option, example)))
    return out


def _intervals(text: str, option: str, example: str) -> list:
    """FROM:TO pairs with FROM < TO (seconds from the start)."""
    from photogram_ros.errors import ConfigError
    out = _pairs(text, option, example)
    for a, b in out:
        if not 0 <= a < b:
            raise ConfigError(f'{option} {a:g}:{b:g}: an interval of seconds from the start needs 0 <= FROM < TO')
    return out


def add_arguments(p) -> None:
    p.add_argument('out', help='bag folder to create (must not exist)')
    p.add_argument('--preset', default='sample', help='sample (bags/), tiny (tests) or survey (benchmarks)')
    p.add_argument('--seed', type=int, help='random seed (terrain, noise, jitter)')
    p.add_argument('--fps', type=float, help='camera frame rate, Hz')
    p.add_argument('--altitude', type=float, help='flight height above the take-off point, m')
    p.add_argument('--speed', type=float, help='speed along the lines, m/s')
    p.add_argument('--lines', type=int, help='number of survey lines')
    p.add_argument('--line-length', type=float, help='length of each line, m')
    p.add_argument('--size', help='image size WxH, e.g. 1280x960 (focal length scales with it)')
    p.add_argument('--tilt', type=float, help='camera tilt from nadir, degrees')
    p.add_argument('--gnss', help='GNSS mode: rtk_fixed, rtk_float, dgps, 3d')
    p.add_argument('--gnss-change', default='', help='mode changes, e.g. "30:rtk_float,60:rtk_fixed"')
    p.add_argument('--outage', default='', help='GNSS outages, e.g. "20:30" (seconds from start)')
    p.add_argument('--drop', type=float, help='fraction of frames dropped at random')
    p.add_argument('--gap', default='', help='frame gaps, e.g. "12:14,40:42"')
    p.add_argument('--black', default='', help='times of black frames, e.g. "25,33"')
    p.add_argument('--exposure-jump', default='', help='gain changes, e.g. "30:1.6"')
    p.add_argument('--corrupt-mavlink', default='', help='intervals of corrupted MAVLink, e.g. "40:45"')
    p.add_argument('--repeats', type=int, help='fly the pattern this many times (long flights)')
    p.add_argument('--raw-images', action='store_true', help='write sensor_msgs/Image instead of JPEG')
    p.add_argument('--mcap', action='store_true', help='write MCAP instead of sqlite3')
    p.add_argument('--photos', action='store_true', help='also write geotagged JPEGs and gcp_list.txt')
    p.add_argument('--ppk', action='store_true', help='also write what a PPK drone leaves, in OUT/ppk/: photos '
                                                      'geotagged by a consumer GNSS, a 5 Hz RTKLIB flight.pos of the '
                                                      'antenna at survey accuracy, a Timestamp.MRK and gcp_list.txt')


def config_from_args(a):
    import re

    from photogram_ros.errors import ConfigError
    from photogram_ros.sim.gnss import MODES
    from photogram_ros.sim.scenario import preset
    o = {}
    for arg, key in (('seed', 'seed'), ('fps', 'fps'), ('altitude', 'altitude_m'), ('speed', 'speed_mps'),
                     ('lines', 'n_lines'), ('line_length', 'line_length_m'), ('tilt', 'camera_tilt_deg'),
                     ('gnss', 'gnss_mode'), ('drop', 'drop_fraction'), ('repeats', 'repeats')):
        if getattr(a, arg) is not None:
            o[key] = getattr(a, arg)
    if a.size:
        m = re.fullmatch(r'\s*(\d+)\s*[xX]\s*(\d+)\s*', a.size)
        if not m:
            raise ConfigError(f'--size {a.size!r}: give WIDTHxHEIGHT in pixels, e.g. 1280x960')
        w, h = int(m.group(1)), int(m.group(2))
        o.update(width_px=w, height_px=h, focal_px=520.0 * w / 640.0)
    for arg, key, lo, hi, what in (('drop', 'drop_fraction', 0.0, 0.99, 'a fraction of the frames'),
                                   ('tilt', 'camera_tilt_deg', -60.0, 60.0, 'degrees from nadir'),
                                   ('repeats', 'repeats', 1, 100, 'times the pattern is flown'),
                                   ('seed', 'seed', 0, 2 ** 32 - 1, 'a random seed')):
        v = getattr(a, arg)
        if v is not None and not lo <= v <= hi:
            raise ConfigError(f'--{arg} {v}: {what}, {lo} to {hi}')
    o['gnss_changes'] = _pairs(a.gnss_change, '--gnss-change', '30:rtk_float,60:rtk_fixed', str.strip)
    for _, mode in o['gnss_changes']:
        if mode not in MODES:
            raise ConfigError(f'--gnss-change: unknown GNSS mode {mode!r}; choose from {sorted(MODES)}')
    o['gnss_outages'] = _intervals(a.outage, '--outage', '20:30')
    o['frame_gaps'] = _intervals(a.gap, '--gap', '12:14,40:42')
    o['black_frames'] = [_number(s, '--black', '25,33') for s in a.black.split(',') if s.strip()]
    o['exposure_jumps'] = _pairs(a.exposure_jump, '--exposure-jump', '30:1.6')
    o['mavlink_corruption'] = _intervals(a.corrupt_mavlink, '--corrupt-mavlink', '40:45')
    if a.raw_images:
        o['image_transport'] = 'raw'
    if a.mcap:
        o['storage'] = 'mcap'
    if a.photos:
        o['photos'] = True
    if getattr(a, 'ppk', False):
        o['ppk'] = True
    return preset(a.preset, **o)


def run(a) -> int:
    import sys
    import time

    from photogram_ros.sim.scenario import simulate
    cfg = config_from_args(a)
    t0 = time.monotonic()

    def progress(k, n):
        if k % 20 == 0 or k == n:
            print(f'\rrendered {k}/{n} frames', end='', file=sys.stderr, flush=True)

    truth = simulate(cfg, a.out, progress=progress)
    print(file=sys.stderr)
    n_pub = sum(f.published for f in truth.frames)
    print(f'wrote {a.out}: {n_pub} frames, {len(truth.fixes)} GNSS epochs, {len(truth.targets)} targets, '
          f'GSD {truth.gsd_m * 100:.1f} cm, in {time.monotonic() - t0:.1f} s')
    return 0
