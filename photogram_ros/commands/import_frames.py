"""photogram-ros import-frames: a folder of frames + intrinsics + a GNSS/pose log -> a flight bag."""

from __future__ import annotations

HELP = ('write a flight bag (images, camera_info, /gps/fix) from a folder of frames named by their UNIX time, '
        'a calibration and a track of positions (e.g. a Map2DFusion data set: rgb/, config.cfg, trajectory.txt)')


def add_arguments(p) -> None:
    p.add_argument('frames', help='folder of <unix time>.jpg frames, or the data set folder holding rgb/')
    p.add_argument('--out', required=True, help='bag folder to create')
    p.add_argument('--camera', default='', help='calibration: a Map2DFusion config.cfg (also gives GPS.Origin) or a '
                                                'ROS / OpenCV camera YAML (default: config.cfg next to the frames)')
    p.add_argument('--track', default='', help='"time x y z ..." per line, local ENU metres about the origin '
                                               '(default: trajectory.txt next to the frames)')
    p.add_argument('--origin', default='',
                   help='LAT,LON,H of the track\'s local frame (default: config.cfg GPS.Origin)')
    p.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap', help='bag storage (as record)')
    p.add_argument('--raw', action='store_true', help='decoded bgr8 Images instead of the JPEG bytes')
    p.add_argument('--fix-rate-hz', type=float, default=1.0, help='GNSS fix rate, interpolated along the track '
                                                                  '(0: a fix at each frame time)')
    p.add_argument('--noise-h-m', type=float, default=0.0, help='horizontal sigma of the fix error to add, m '
                                                                '(a plain 3D fix: 1.5)')
    p.add_argument('--noise-v-m', type=float, default=0.0, help='vertical sigma of the fix error to add, m (3D fix: 3)')
    p.add_argument('--noise-tau-s', type=float, default=30.0, help='correlation time of that error, s (0: white)')
    p.add_argument('--seed', type=int, default=0, help='seed of the noise')
    p.add_argument('--max-frames', type=int, default=0, help='import only this many frames (0: all)')
    p.add_argument('--start-frame', type=int, default=0, help='skip this many frames first')


def _camera_and_origin(a, base):
    from pathlib import Path

    from photogram_ros.errors import ConfigError
    from photogram_ros.io.frame_import import read_map2dfusion_config
    cam_path = Path(a.camera) if a.camera else base / 'config.cfg'
    if not cam_path.exists():
        raise ConfigError(f'no calibration: {cam_path} does not exist (give --camera)')
    origin = None
    if cam_path.suffix in ('.yaml', '.yml'):
        from photogram_ros.io.keyframe_block import camera_from_yaml
        camera = camera_from_yaml(cam_path)
    else:
        camera, origin = read_map2dfusion_config(cam_path)
    if a.origin:
        from photogram_ros.commands.products import parse_origin
        origin = parse_origin(a.origin)
    if origin is None:
        raise ConfigError('the track\'s geodetic origin is unknown: give --origin LAT,LON,H')
    return camera, origin


def run(a) -> int:
    import sys
    from pathlib import Path

    from photogram_ros.errors import ConfigError
    from photogram_ros.io.frame_import import FrameImportOptions, import_frames, read_track

    frames = Path(a.frames)
    if (frames / 'rgb').is_dir():
        base, frames = frames, frames / 'rgb'
    else:
        base = frames.parent
    if min(a.noise_h_m, a.noise_v_m, a.noise_tau_s, a.fix_rate_hz) < 0:
        raise ConfigError('noise sigmas, --noise-tau-s and --fix-rate-hz must not be negative')
    camera, origin = _camera_and_origin(a, base)
    track_path = Path(a.track) if a.track else base / 'trajectory.txt'
    track = read_track(track_path)

    def progress(done, total):
        if done == total or done % 25 == 0:
            print(f'\rimported {done}/{total} frames', end='\n' if done == total else '', file=sys.stderr, flush=True)

    res = import_frames(FrameImportOptions(
        frames, Path(a.out), camera, track, origin, storage=a.storage, compressed=not a.raw,
        fix_rate_hz=a.fix_rate_hz, noise_h_m=a.noise_h_m, noise_v_m=a.noise_v_m, noise_tau_s=a.noise_tau_s,
        seed=a.seed, max_frames=a.max_frames, start_frame=a.start_frame), progress)
    print(f'{res.bag}: {res.frames} frames, {res.fixes} fixes over {res.duration_s:.1f} s '
          f'(added noise RMS {res.noise_rms_m[0]:.2f} m horizontal, {res.noise_rms_m[1]:.2f} m vertical); '
          f'camera {camera.width}x{camera.height} f={camera.fx:g} px, origin {origin}')
    return 0
