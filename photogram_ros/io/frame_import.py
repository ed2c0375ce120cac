"""A folder of frames + intrinsics + a GNSS/pose log -> a flight bag the mapper replays.

Many drone video data sets come as image files named by their time, a camera calibration and a
track of positions in a local metric frame tied to a geodetic origin (e.g. Map2DFusion's
phantom3-village: `rgb/<unix time>.jpg`, `config.cfg` with `Camera.Paraments=[w,h,fx,fy,cx,cy]` and
`GPS.Origin=lon lat alt`, `trajectory.txt` with `time x y z [qx qy qz qw]`). `import_frames` writes
them as a rosbag2 (MCAP or sqlite3, io/bag.BagWriter) with

- `/camera/image_raw/compressed` (CompressedImage, the file's JPEG bytes as they are) or
  `/camera/image_raw` (Image, bgr8), stamped with the frame time;
- `/camera/camera_info` with each frame;
- `/gps/fix` (NavSatFix, REP-145 ellipsoidal height): the track's positions (local ENU about the
  origin -> WGS84 through core/geodesy.LocalFrame) at `fix_rate_hz` (interpolated linearly) or at the
  frame times, optionally with the noise of a real receiver: a first-order Gauss-Markov error per
  axis (stationary sigma noise_h_m horizontally, noise_v_m vertically, correlation time
  noise_tau_s; 0: white), seeded, and the covariance set to those sigmas.

The track is taken as a stand-in GNSS log, never as truth: the adjustment orients the frames.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.errors import DataError

IMAGE_SUFFIXES = ('.jpg', '.jpeg', '.png')
TOPIC_IMAGE = '/camera/image_raw'
TOPIC_INFO = '/camera/camera_info'
TOPIC_FIX = '/gps/fix'


@dataclass
class FrameImportOptions:
    frames_dir: Path                       # image files named <unix time s>.<ext>
    out: Path                              # the bag folder to create
    camera: PinholeCamera
    track: np.ndarray                      # (N, 4) time_s, x_e, y_n, z_u in the local ENU frame, m
    origin: LocalFrame                     # the local frame's geodetic origin
    storage: str = 'mcap'
    compressed: bool = True                # JPEG bytes as they are; False: decoded bgr8 Image
    fix_rate_hz: float = 1.0               # 0: a fix at each frame time
    noise_h_m: float = 0.0
    noise_v_m: float = 0.0
    noise_tau_s: float = 30.0
    seed: int = 0
    max_frames: int = 0                    # 0: all
    start_frame: int = 0


@dataclass
class FrameImportResult:
    bag: Path
    frames: int = 0
    fixes: int = 0
    duration_s: float = 0.0
    noise_rms_m: tuple = (0.0, 0.0)        # horizontal, vertical RMS of the noise added
    notes: list = field(default_factory=list)


# --- reading the inputs ----------------------------------------------------------------------------


def read_map2dfusion_config(path: str | Path) -> tuple[PinholeCamera, LocalFrame | None]:
    """`config.cfg` of a Map2DFusion data set -> (camera, origin or None).

    `Camera.Paraments=[width,height,fx,fy,cx,cy]` (pinhole, no distortion); `GPS.Origin=lon lat alt`
    (degrees, metres).
    """
    path = Path(path)
    try:
        text = path.read_text(errors='replace')
    except OSError as exc:
        raise DataError(f'cannot read the camera file {path}: {exc}') from exc
    kv = {}
    for line in text.splitlines():
        if '=' in line and not line.lstrip().startswith('#'):
            k, v = line.split('=', 1)
            kv[k.strip()] = v.strip()
    nums = [float(x) for x in re.findall(r'[-+0-9.eE]+', kv.get('Camera.Paraments', ''))]
    if len(nums) < 6:
        raise DataError(f'{path}: no Camera.Paraments=[width,height,fx,fy,cx,cy] line')
    w, h, fx, fy, cx, cy = nums[:6]
    camera = PinholeCamera(int(w), int(h), fx, fy, cx, cy)
    origin = None
    if 'GPS.Origin' in kv:
        o = [float(x) for x in re.findall(r'[-+0-9.eE]+', kv['GPS.Origin'])]
        if len(o) < 3:
            raise DataError(f'{path}: GPS.Origin must be "longitude latitude altitude"')
        origin = LocalFrame(o[1], o[0], o[2])
    return camera, origin


def read_track(path: str | Path) -> np.ndarray:
    """`time x y z [...]` per line (whitespace or commas, '#' comments) -> (N, 4) sorted by time."""
    path = Path(path)
    rows = []
    try:
        lines = path.read_text(errors='replace').splitlines()
    except OSError as exc:
        raise DataError(f'cannot read the track {path}: {exc}') from exc
    for i, line in enumerate(lines, 1):
        line = line.split('#', 1)[0].replace(',', ' ').strip()
        if not line:
            continue
        try:
            vals = [float(v) for v in line.split()]
        except ValueError as exc:
            raise DataError(f'{path} line {i}: not numbers ({line[:40]!r})') from exc
        if len(vals) < 4:
            raise DataError(f'{path} line {i}: expected "time x y z", got {len(vals)} values')
        rows.append(vals[:4])
    if len(rows) < 2:
        raise DataError(f'{path} holds fewer than two track positions')
    track = np.array(rows, float)
    track = track[np.argsort(track[:, 0], kind='stable')]
    if not np.all(np.isfinite(track)):
        raise DataError(f'{path} holds non-finite values')
    return track


def frame_files(frames_dir: str | Path) -> list[tuple[float, Path]]:
    """(time s, path) of the image files named by their UNIX time, in time order."""
    d = Path(frames_dir)
    if not d.is_dir():
        raise DataError(f'{d} is not a folder of frames')
    out = []
    for p in d.iterdir():
        if p.suffix.lower() in IMAGE_SUFFIXES:
            try:
                out.append((float(p.stem), p))
            except ValueError:
                continue
    if not out:
        raise DataError(f'{d} holds no image files named by their time (e.g. 1455008966.000000.jpg)')
    return sorted(out)


# --- the fixes -------------------------------------------------------------------------------------


def fix_times(frame_times_s: np.ndarray, track_t: np.ndarray, rate_hz: float) -> np.ndarray:
    """When the receiver reports: every 1/rate_hz s over the frames' span within the track, or the frame times."""
    t0, t1 = max(frame_times_s[0], track_t[0]), min(frame_times_s[-1], track_t[-1])
    if rate_hz <= 0:
        t = frame_times_s
        return t[(t >= track_t[0]) & (t <= track_t[-1])]
    return np.arange(np.ceil(t0 * rate_hz) / rate_hz, t1 + 1e-9, 1.0 / rate_hz)


def gauss_markov_noise(t_s: np.ndarray, sigmas_m: np.ndarray, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) first-order Gauss-Markov errors at times t_s with stationary sigma per axis (tau 0: white)."""
    n = t_s.size
    e = np.zeros((n, 3))
    if n == 0:
        return e
    e[0] = rng.normal(0.0, sigmas_m)
    for i in range(1, n):
        rho = np.exp(-(t_s[i] - t_s[i - 1]) / tau_s) if tau_s > 0 else 0.0
        e[i] = rho * e[i - 1] + np.sqrt(1.0 - rho * rho) * rng.normal(0.0, sigmas_m)
    return e


def track_positions(track: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """(N, 3) ENU positions of the track at times t_s (linear interpolation)."""
    return np.column_stack([np.interp(t_s, track[:, 0], track[:, k]) for k in (1, 2, 3)])


def _check_first_frame(path: Path, camera: PinholeCamera) -> None:
    import cv2
    img = cv2.imread(str(path), cv2.IMREAD_REDUCED_GRAYSCALE_2)
    if img is None:
        raise DataError(f'{path} is not a readable image')
    h, w = img.shape[0] * 2, img.shape[1] * 2
    if abs(w - camera.width) > 1 or abs(h - camera.height) > 1:
        raise DataError(f'the frames are {w}x{h} but the calibration is for {camera.width}x{camera.height}')


# --- writing ---------------------------------------------------------------------------------------


def import_frames(opts: FrameImportOptions, progress=None) -> FrameImportResult:
    """Write the bag (see the module docstring); `progress(done, total)` after each frame."""
    from sensor_msgs.msg import CompressedImage, NavSatFix

    from photogram_ros import msgs
    from photogram_ros.io.bag import BagWriter

    frames = frame_files(opts.frames_dir)[opts.start_frame:]
    if opts.max_frames > 0:
        frames = frames[:opts.max_frames]
    if not frames:
        raise DataError(f'{opts.frames_dir}: no frames left after start_frame {opts.start_frame}')
    times = np.array([t for t, _ in frames])
    _check_first_frame(frames[0][1], opts.camera)
    t_fix = fix_times(times, opts.track[:, 0], opts.fix_rate_hz)
    if t_fix.size == 0:
        raise DataError('the track does not cover the frames\' times: no GNSS fix can be written '
                        f'(frames {times[0]:.1f}-{times[-1]:.1f} s, track {opts.track[0, 0]:.1f}-'
                        f'{opts.track[-1, 0]:.1f} s)')
    sig = np.array([opts.noise_h_m, opts.noise_h_m, opts.noise_v_m], float)
    noise = gauss_markov_noise(t_fix, sig, opts.noise_tau_s, np.random.default_rng(opts.seed))
    enu = track_positions(opts.track, t_fix) + noise
    lat, lon, h = opts.origin.enu_to_geodetic(enu)
    # A receiver always reports some uncertainty: 2 cm / 3 cm where no noise was asked for.
    var = np.maximum(sig, [0.02, 0.02, 0.03]) ** 2
    res = FrameImportResult(Path(opts.out), notes=[])
    res.noise_rms_m = (float(np.sqrt(np.mean(noise[:, 0] ** 2 + noise[:, 1] ** 2))),
                       float(np.sqrt(np.mean(noise[:, 2] ** 2))))
    events = [(int(round(t * 1e9)), 1, i) for i, t in enumerate(t_fix)]
    events += [(int(round(t * 1e9)), 0, i) for i, t in enumerate(times)]
    events.sort()
    with BagWriter(opts.out, storage=opts.storage) as bag:
        for stamp_ns, kind, i in events:
            if kind == 1:
                bag.write(TOPIC_FIX, stamp_ns, msgs.navsatfix_msg(
                    stamp_ns, float(np.ravel(lat)[i]), float(np.ravel(lon)[i]), float(np.ravel(h)[i]),
                    0, var, NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN))
                res.fixes += 1
                continue
            path = frames[i][1]
            data = path.read_bytes()
            bag.write(TOPIC_INFO, stamp_ns, msgs.camera_info_msg(opts.camera, stamp_ns))
            if opts.compressed and path.suffix.lower() in ('.jpg', '.jpeg'):
                msg = CompressedImage(header=msgs.header(stamp_ns, 'camera_optical'), format='jpeg')
                msg.data = data
                bag.write(TOPIC_IMAGE + '/compressed', stamp_ns, msg)
            else:
                import cv2
                img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
                if img is None:
                    raise DataError(f'{path} is not a readable image')
                opts.camera.check_image_size(img.shape[1], img.shape[0])
                bag.write(TOPIC_IMAGE, stamp_ns, msgs.image_msg(img, stamp_ns))
            res.frames += 1
            if progress is not None:
                progress(res.frames, len(frames))
    res.duration_s = float(max(times[-1], t_fix[-1]) - min(times[0], t_fix[0]))
    return res
