"""The in-flight graph on 20 MP photos (5472 x 3648) at a current mapping drone's photo rate.

Three flights (--flight): toledo (below), `seneca` (after it), or `sim`: the simulator's survey (SIM_FLIGHT: 6 lines of 350 m at
80 m above ground, 8 m/s, a photo every second, 317 photos, 9 ArUco targets surveyed in its control file)
rendered at 1368 x 912 and upscaled x4 to 20 MP (build_sim_flight; cached in
/tmp/photogram_bench_cache/inflight_20mp_sim_<n>), played at --periods (1 s: its own timing; 0.7 s: 1/0.7 times as
fast, the same photos a camera takes every 0.7 s) with its control file given to
the adjuster (and through the graph to the tracker's target search). Rendering takes about 8 CPU
minutes (39 min wall on the loaded 2-core machine), upscaling about 1 CPU s a photo, once.

The flight: toledo's 42 real DJI survey photos (../shared/data/photos/toledo, 2400 x 1800, EXIF GPS),
cropped to 3:2 (2400 x 1600, rows 100-1700) and upscaled x2.28 to 5472 x 3648, re-timed one photo per
`--period` seconds (EXIF DateTimeOriginal / SubSec / OffsetTimeOriginal rewritten, the EXIF GPS kept,
so the camera node publishes each photo's position as its fix), with a calibration file of the EXIF
camera cropped and scaled the same way. Real photos rather than the simulator: real texture, real
GNSS noise, and the live graph is known to orient toledo (29-31 keyframes, all oriented, in replay);
the simulator at 20 MP would spend most of the bench's time rendering. The photos are built once into
/tmp/photogram_bench_cache/inflight_20mp_<period>s (about 3 MB each).

The seneca flight: seneca_part's 41 real near-infrared photos of a fixed-wing survey (../shared/data/photos/
seneca_part, 1600 x 1200, EXIF GPS, about 7 s apart; the held-out rest of that survey is 3600 x 2700), upscaled
x3.2275 to 5164 x 3873 (20 MP, 4:3 kept, no crop) and re-timed one photo per `--period` s like toledo's, built once
into /tmp/photogram_bench_cache/inflight_20mp_seneca_<period>s_<n>. No calibration file, as `replay` of the folder
runs: the camera node takes the camera from the EXIF (its focal-plane resolution and pixel dimensions rewritten to
the new size, so the EXIF camera is the 1600 x 1200 one scaled by the same factor) and the replay self-calibrates
as it does for an EXIF camera; <folder>_camera.yaml beside it holds that scaled camera for reference.

The run: photogram_ros.nodes.replay_session.run_replay with the camera node playing the folder at
its EXIF timing (rate 1) and the replay's waits off (frame_timeout_s 0, max_lag_keyframes 0): photos
come at the period whatever the graph does, as from a live camera, and the tracker's bounded queue
drops what it cannot take: with --params config/replay.yaml (the default) that queue holds 100 frames (tracker_node
queue_size), so a tracker slower than the camera falls behind without dropping; `--set tracker.queue_size=8` gives it
the companion profile's queue (config/companion.yaml), `=2` the node's default, as `photogram-ros run` without a
params file. Bundle, stereo and map run in a child process (replay's default,
--processes 2). Timing hooks come from bench/replay_probe.py (no benchmark code in the nodes).

Reported (JSON lines, --out appends them to a file; a markdown table with --table): photos in, keyframes taken, photos skipped
by the overlap rule, photos dropped otherwise and why, keyframes oriented (given a pose on
map/keyframe_pose before the end of the run, a segment joined through its GNSS included), lag from exposure (the
photo's time on the camera's schedule: the first photo's publication plus its stamp's offset; how late the
camera node published each is reported too) to the keyframe's first pose on map/keyframe_pose and to
its first fused pair cloud (p50/p95/max, wall s; over the whole flight and over the keyframes exposed in its
last minute), the first pose after the first photo, what was shed (frames the tracker dropped, keyframes whose
stereo pairs were shed, ortho batches deferred), the real-time factor of the play (flight seconds
over wall seconds until the map fused its last cloud), peak RSS of both processes (and their sum, an upper
bound of all mapping processes' peak together), the tracker's target search counts, and the cores and
load average of the machine around the run (bench/machine.py). Also: the lag from exposure to the keyframe's first
final (not provisional) pose and from that pose to its first fused cloud (the part stereo and the map add), and how
far the poses moved after their first fused cloud (pose_moved_after_fused: from the last final pose before it;
pose_moved_after_first_fused_any_status: from the pose of any status, a provisional one included, it was fused
with, which is how far the map node had to place that cloud again: stages/map.py replace_moved, counted in
map_counts clouds_replaced).
With --export-dsm, after each run `photogram-ros export MAP --densify --products dsm` on its stored map (the pairs
shed in flight matched there from the stored keyframes); each later run's DSM against the first run's
(inflight_20mp_dsm rows: median and p90 |dz| over the cells stereo measured in both, in m and in the GSD, with both
runs' shed counts and the shed WARNs said on /diagnostics). The reference is the first run's `export --densify`:
every pair planned and matched again after landing from all its stored keyframes and final poses (io/densify.py
reads no in-flight pair, shed or not, only the in-flight map's median height as the centre of the depth search),
so it is a DSM that shed nothing whatever the first run shed in flight; each dsm row says so (`reference_is`).

With --tracker-cpu N, no graph: the tracker alone (core/tracker.Tracker with run's default parameters and the
tracker.X of --set; --baseline-set's alternating with it, N passes each) over the built photos, each photo's EXIF fix
given before it: CPU per frame and its split by step (decode, KLT, corners, SIFT extraction, FLANN build, knn
matching, essential-matrix verification, the rest), keyframes, breaks bridged, lost, chain pairs matched and verified
(inflight_20mp_tracker_cpu rows, and a _compare row with the CPU ratio).

    .venv/bin/python bench/inflight_20mp.py [--periods 2,1] [--photos 42] [--set tracker.X=V] [--table out.md]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT))
os.environ.setdefault('ROS_DOMAIN_ID', '171')

from machine import machine_info  # noqa: E402

SRC = ROOT.parent / 'shared' / 'data' / 'photos' / 'toledo' / 'images'
CACHE = Path('/tmp/photogram_bench_cache')
SIZE = (5472, 3648)
CROP = (0, 100, 2400, 1700)        # 3:2 window of the 2400 x 1800 photos
T0 = datetime(2015, 10, 16, 13, 23, 30, tzinfo=timezone.utc)


OUT: list = []   # the JSON lines file (--out), when given
CODE: dict = {}  # the commit and clean-tree flag of the code run, taken when the bench starts


def emit(d: dict) -> None:
    print(json.dumps(d), flush=True)
    if OUT:
        with open(OUT[0], 'a') as f:
            f.write(json.dumps(d) + '\n')


def git(*args) -> str:
    import subprocess
    return subprocess.run(['git', *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()


def log(s: str) -> None:
    print(s, file=sys.stderr, flush=True)


def _one_photo(args) -> None:
    src, dst, when, crop, size, exif_camera = args
    from PIL import Image
    with Image.open(src) as im:
        exif = im.getexif()
        gps = exif.get_ifd(0x8825)   # loaded so that it is written back
        ex = exif.get_ifd(0x8769)
        ex[0x9003] = when.strftime('%Y:%m:%d %H:%M:%S')        # DateTimeOriginal
        ex[0x9291] = f'{when.microsecond // 1000:03d}'          # SubSecTimeOriginal
        ex[0x9011] = '+00:00'                                   # OffsetTimeOriginal
        if exif_camera:   # the EXIF gives the camera: its sensor tags rewritten to the new size
            factor = size[0] / (crop[2] - crop[0])
            for tag in (0xA20E, 0xA20F):                        # FocalPlaneX/YResolution
                if tag in ex:
                    ex[tag] = float(ex[tag]) * factor
            ex[0xA002], ex[0xA003] = size                       # PixelX/YDimension
        else:
            ex.pop(0xA405, None)    # FocalLengthIn35mmFilm: the calibration file gives the camera
        assert gps, f'{src} has no EXIF GPS'
        big = im.crop(crop).resize(size, Image.BICUBIC)
        tmp = dst.with_suffix('.tmp')
        big.save(tmp, 'JPEG', quality=90, exif=exif)
        tmp.rename(dst)


# The seneca flight (--flight seneca): the fixed-wing survey's first 41 photos, 4:3 kept, upscaled to 20 MP.
SENECA_SRC = ROOT.parent / 'shared' / 'data' / 'photos' / 'seneca_part' / 'images'
SENECA_SIZE = (5164, 3873)         # 1600 x 1200 x 3.2275 (the held-out 3600 x 2700 at 20 MP)
SENECA_CROP = (0, 0, 1600, 1200)   # the whole photo
SENECA_T0 = datetime(2013, 6, 4, 13, 37, 35, tzinfo=timezone.utc)


def build_flight(period_s: float, n_photos: int = 42, folder: Path | None = None,
                 flight: str = 'toledo') -> tuple[Path, Path]:
    """The 20 MP photo folder and its calibration YAML (built once, cached), `period_s` apart: toledo's first
    `n_photos` photos cropped to 3:2 and upscaled to 5472 x 3648, or (flight 'seneca') seneca_part's upscaled to
    5164 x 3873, whose EXIF keeps giving the camera (the YAML is that camera, for reference)."""
    import yaml

    from photogram_ros.io.image_source import FolderSource
    seneca = flight == 'seneca'
    src_dir, crop, size, t0_photo = ((SENECA_SRC, SENECA_CROP, SENECA_SIZE, SENECA_T0) if seneca
                                     else (SRC, CROP, SIZE, T0))
    folder = folder or CACHE / (f'inflight_20mp_seneca_{period_s:g}s_{n_photos}' if seneca
                                else f'inflight_20mp_{period_s:g}s_{n_photos}')
    calib = folder.parent / (folder.name + '_camera.yaml')
    src = FolderSource(src_dir)
    entries = src.entries[:n_photos]
    folder.mkdir(parents=True, exist_ok=True)
    jobs = [(p, folder / p.name, t0_photo + timedelta(seconds=i * period_s), crop, size, seneca)
            for i, (p, _) in enumerate(entries)]
    jobs = [j for j in jobs if not j[1].exists()]
    if jobs:
        from concurrent.futures import ProcessPoolExecutor
        t0 = time.perf_counter()
        with ProcessPoolExecutor(2) as ex:
            list(ex.map(_one_photo, jobs))
        log(f'[20mp] built {len(jobs)} photos in {time.perf_counter() - t0:.0f} s into {folder}')
    cam = src.exif_intrinsics().camera
    factor = size[0] / (crop[2] - crop[0])
    from dataclasses import replace
    cam = replace(cam, height=crop[3] - crop[1], cy=cam.cy - crop[1]).scaled(factor)
    calib.write_text(yaml.safe_dump(cam.to_ros_yaml_dict()))
    return folder, calib


# The simulated flight (--flight sim): the simulator's survey rendered at SIM_SIZE, one photo a second, each
# upscaled to SIZE (x4) with its EXIF GPS kept; its ArUco targets' control file beside it.
SIM_SIZE = (1368, 912)
SIM_FLIGHT = dict(fps=1.0, width_px=SIM_SIZE[0], height_px=SIM_SIZE[1], focal_px=520.0 * SIM_SIZE[0] / 640,
                  altitude_m=80.0, speed_mps=8.0, turn_speed_mps=5.0, line_length_m=350.0, n_lines=6,
                  photos=True, front_overlap=0.97)   # a photo at every frame (2 m trigger spacing, frames 5-8 m apart)


EVERY_FRAME = 'every_frame.txt'   # in the simulated photos' folder: a photo was written for every frame


def _upscale_photo(args) -> None:
    src, dst = args
    from PIL import Image
    with Image.open(src) as im:
        exif = im.getexif()
        exif.get_ifd(0x8825)   # loaded so that it is written back
        ex = exif.get_ifd(0x8769)
        for tag in (0xA002, 0xA003, 0xA20E, 0xA20F, 0xA210, 0xA405):   # the rendered size's sensor tags
            ex.pop(tag, None)
        big = im.resize(SIZE, Image.BICUBIC)
        tmp = dst.with_suffix('.tmp')
        big.save(tmp, 'JPEG', quality=90, exif=exif)
        tmp.rename(dst)


def _photos_from_bag(src: Path) -> None:
    """Every frame of the simulated bag written as a geotagged photo (sim/photos.write_photos), from the bag's
    JPEG frames: for a cache simulated with a front overlap that took fewer photos than frames."""
    import shutil
    from types import SimpleNamespace

    import cv2
    import numpy as np
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import CompressedImage

    from photogram_ros.io.bag import BagReader
    from photogram_ros.msgs import ns_from_time
    from photogram_ros.sim.photos import write_photos
    from photogram_ros.sim.scenario import preset
    from photogram_ros.sim.truth import GroundTruth
    truth = GroundTruth.load(src)

    def frames():
        with BagReader(src) as bag:
            for m in bag.messages(['/camera/image_raw/compressed']):
                msg = deserialize_message(m.data, CompressedImage)
                ft = truth.frame_by_stamp(ns_from_time(msg.header.stamp))
                img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
                yield ft.index, img, SimpleNamespace(pos_enu=ft.map_T_cam[:3, 3])
    shutil.rmtree(src / 'photos')
    n = len(write_photos(src / 'photos', frames(), truth, preset('sample', **SIM_FLIGHT)))
    (src / 'photos' / EVERY_FRAME).write_text(f'{n}\n')
    log(f'[20mp] {n} photos written from the frames of {src}')


def build_sim_flight(n_photos: int) -> tuple[Path, Path, Path]:
    """The simulated 20 MP flight (built once, cached): (photo folder, calibration YAML, control file). The
    simulator's survey (SIM_FLIGHT: 6 lines of 350 m at 80 m, 8 m/s, a frame a second, 317 frames) rendered at
    SIM_SIZE and every frame a photo (317); the first `n_photos` upscaled to SIZE."""
    import shutil

    import yaml

    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.sim.scenario import preset, simulate
    src = CACHE / 'sim20mp_src'
    if not (src / 'photos' / 'camera.yaml').exists():
        if src.exists():
            shutil.rmtree(src)
        t0 = time.perf_counter()
        simulate(preset('sample', **SIM_FLIGHT), src)
        log(f'[20mp] simulated {src} in {time.perf_counter() - t0:.0f} s')
    if not (src / 'photos' / EVERY_FRAME).exists():
        _photos_from_bag(src)
    folder = CACHE / f'inflight_20mp_sim_{n_photos}'
    calib = folder.parent / (folder.name + '_camera.yaml')
    control = folder.parent / (folder.name + '_targets.txt')
    photos = sorted((src / 'photos').glob('IMG_*.JPG'))[:n_photos]
    folder.mkdir(parents=True, exist_ok=True)
    jobs = [(p, folder / p.name) for p in photos if not (folder / p.name).exists()]
    if jobs:
        from concurrent.futures import ProcessPoolExecutor
        t0 = time.perf_counter()
        with ProcessPoolExecutor(2) as ex:
            list(ex.map(_upscale_photo, jobs))
        log(f'[20mp] upscaled {len(jobs)} photos in {time.perf_counter() - t0:.0f} s into {folder}')
    d = yaml.safe_load((src / 'photos' / 'camera.yaml').read_text())
    cam = PinholeCamera.from_ros_yaml_dict(d).scaled(SIZE[0] / SIM_SIZE[0])
    calib.write_text(yaml.safe_dump(cam.to_ros_yaml_dict()))
    shutil.copyfile(src / 'targets.txt', control)
    return folder, calib, control


def pct(v: list, q: float, digits: int = 2):
    import numpy as np
    return round(float(np.percentile(v, q)), digits) if v else None


def lag_stats(v: list, digits: int = 2) -> dict:
    return {'n': len(v), 'p50': pct(v, 50, digits), 'p95': pct(v, 95, digits),
            'max': round(max(v), digits) if v else None}


def pose_moved_after_first_fused(history: dict, fused_at: dict) -> dict:
    """How far each keyframe's pose moved from the pose of its first fused cloud (its latest pose of any status,
    provisional included, before then) to its last pose: the centre in m, p50/p95/max, and how many were fused
    with a provisional pose."""
    import numpy as np
    move_m, provisional = [], 0
    for s, t_fused in fused_at.items():
        h = history.get(s, ())
        at = [(prov, T) for t, prov, T in h if t <= t_fused]
        if not at or not h:
            continue
        provisional += bool(at[-1][0])
        move_m.append(float(np.linalg.norm(h[-1][2][:3, 3] - at[-1][1][:3, 3])))
    return {'centre_m': lag_stats(move_m, 3), 'fused_with_provisional_pose': provisional}


def relative_pose_moved_after_fused(history: dict, fused_at: dict) -> dict:
    """What a pair's depth depends on: each fused keyframe's pose relative to the keyframe before it, at its first
    fused cloud (the latest poses of any status then) against the last poses: the change of the relative centre
    in m, and of the baseline's length as a ratio (the depth's scale error a cloud placed again keeps), p50/p95/max."""
    import numpy as np
    stamps = sorted(history)
    move_m, scale = [], []
    for prev, s in zip(stamps, stamps[1:]):
        if s not in fused_at:
            continue
        t = fused_at[s]
        a_then = [T for tt, _, T in history[prev] if tt <= t]
        b_then = [T for tt, _, T in history[s] if tt <= t]
        if not a_then or not b_then:
            continue
        rel_then = np.linalg.inv(a_then[-1]) @ b_then[-1]
        rel_end = np.linalg.inv(history[prev][-1][2]) @ history[s][-1][2]
        move_m.append(float(np.linalg.norm(rel_end[:3, 3] - rel_then[:3, 3])))
        base = float(np.linalg.norm(rel_then[:3, 3]))
        if base > 1e-6:
            scale.append(abs(float(np.linalg.norm(rel_end[:3, 3])) / base - 1.0))
    return {'relative_centre_m': lag_stats(move_m, 3), 'baseline_scale_change': lag_stats(scale, 4)}


def summarise_kept(keep: Path) -> dict:
    """The pose figures of a kept run (--keep: its pose_history.json), recomputed."""
    d = json.loads((keep / 'pose_history.json').read_text())
    import numpy as np
    history = {int(s): [(t, p, np.array(T)) for t, p, T in h] for s, h in d['poses'].items()}
    fused = {int(s): t for s, t in d['fused'].items()}
    return {'bench': 'inflight_20mp_kept', 'config': keep.name, 'kept': str(keep), **CODE,
            'pose_moved_after_first_fused_any_status': pose_moved_after_first_fused(history, fused),
            'relative_pose_moved_after_first_fused': relative_pose_moved_after_fused(history, fused),
            'pose_moved_after_fused': pose_moved_after_fused(history, fused, d['flight_end'])}


def pose_moved_after_fused(history: dict, fused_at: dict, flight_end: float) -> dict:
    """How far each keyframe's pose moved after its first fused cloud (the pose stereo paired it with: its last
    final pose before then) until its last pose in flight and its last pose at all (the final adjustment's): the
    centre in m and the rotation in degrees, p50/p95/max over the fused keyframes."""
    import numpy as np
    out = {}
    for name, until in (('in_flight', flight_end), ('final', float('inf'))):
        move_m, turn_deg = [], []
        for s, t_fused in fused_at.items():
            final = [(t, T) for t, prov, T in history.get(s, ()) if not prov]
            at = [T for t, T in final if t <= t_fused]
            later = [T for t, T in final if t <= until]
            if not at or not later:
                continue
            A, B = at[-1], later[-1]
            move_m.append(float(np.linalg.norm(B[:3, 3] - A[:3, 3])))
            c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1.0) / 2.0
            turn_deg.append(float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))))
        out[f'centre_m_{name}'] = lag_stats(move_m, 3)
        out[f'rotation_deg_{name}'] = lag_stats(turn_deg, 4)
    return out


class PoseListener:
    """First arrival (monotonic) of each keyframe stamp on map/keyframe_pose, in a thread of its own."""

    def __init__(self):
        import rclpy
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from photogram_ros import msgs
        self.first: dict[int, float] = {}
        self.first_final: dict[int, float] = {}   # the first pose that was not provisional
        self.history: dict[int, list] = {}        # stamp -> [(monotonic, provisional, map_T_cam)]

        def on_pose(m):
            now, s = time.monotonic(), msgs.ns_from_time(m.header.stamp)
            provisional = msgs.pose_is_provisional(m)
            self.first.setdefault(s, now)
            if not provisional:
                self.first_final.setdefault(s, now)
            self.history.setdefault(s, []).append((now, provisional, msgs.T_from_pose_with_covariance(m)[0]))
        self.node = rclpy.create_node('bench_pose_listener')
        self.node.create_subscription(PoseWithCovarianceStamped, '/map/keyframe_pose', on_pose,
                                      QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
        self.ex = SingleThreadedExecutor()
        self.ex.add_node(self.node)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        while not self._stop.is_set():
            self.ex.spin_once(timeout_sec=0.1)

    def stop(self):
        self._stop.set()
        self.thread.join(2.0)
        self.ex.remove_node(self.node)
        self.node.destroy_node()


def run_period(a, period_s: float, extra: dict, tag: str) -> dict:
    """One live-paced run of the 20 MP flight at `period_s`; returns the figures."""
    import rclpy

    from photogram_ros.nodes.camera_node import CameraNode
    from photogram_ros.nodes.replay_session import ReplayOptions, run_replay
    from replay_probe import Probe, RssSampler

    rate = 1.0
    if a.flight == 'sim':   # the simulated survey: its surveyed targets go to the adjuster (and the tracker)
        folder, calib, control = build_sim_flight(a.photos)
        rate = 1.0 / period_s   # its photos are 1 s apart: played 1/period_s times as fast
        extra = {**extra, 'bundle': {'control_file': str(control), **extra.get('bundle', {})}}
    else:
        folder, calib = build_flight(period_s, a.photos, flight=a.flight)
    if a.flight == 'seneca':   # as `replay` of the folder: the camera from the photos' EXIF
        calib = None
    probe = Probe().install()
    published: dict[int, float] = {}    # photo stamp -> when the camera node published it
    publish_next = CameraNode.publish_next

    def timed_publish(self):
        s = self.peek_stamp_ns()
        if s is not None:
            published.setdefault(s, time.monotonic())
        return publish_next(self)
    CameraNode.publish_next = timed_publish
    out = Path(a.keep) / tag if a.keep else Path(tempfile.mkdtemp(prefix='inflight20mp_'))
    child_out = out / 'child_probe.json'
    site = Probe.child_sitecustomize(out / 'probe_site', ROOT / 'bench')
    old_pp = os.environ.get('PYTHONPATH')
    os.environ['PYTHONPATH'] = os.pathsep.join([str(site)] + [v for v in [old_pp] if v])
    os.environ[Probe.CHILD_ENV] = str(child_out)
    load_before = os.getloadavg()
    try:   # VmHWM from here on: this run's peak, not an earlier run's in the same process
        Path('/proc/self/clear_refs').write_text('5')
    except OSError:
        pass
    rclpy.init()
    poses = PoseListener()
    sampler = RssSampler(probe, period_s=1.0)
    sampler.start()
    t0 = time.monotonic()
    try:
        res = run_replay(ReplayOptions(bag=str(folder), out=str(out / 'replay'), params_file=a.params, rate=rate,
                                       progress=False, extra=extra, calibration_file=str(calib) if calib else '',
                                       child_roles=('bundle', 'stereo', 'map'), frame_timeout_s=0.0,
                                       max_lag_keyframes=0))
    finally:
        t_end = time.monotonic()
        sampler.stop()
        poses.stop()
        rclpy.try_shutdown()
        probe.uninstall()
        CameraNode.publish_next = publish_next
        os.environ.pop(Probe.CHILD_ENV, None)
        if old_pp is None:
            os.environ.pop('PYTHONPATH', None)
        else:
            os.environ['PYTHONPATH'] = old_pp
    load_after = os.getloadavg()
    # Exposure: the photo's time on the camera's schedule (the first photo's publication + its stamp's offset),
    # as a live camera takes it; a camera node late with a photo (decoding the previous) counts in the lags.
    first = min(published) if published else 0
    exposure = {s: published[first] + (s - first) * 1e-9 / rate for s in published}
    camera_late = [published[s] - exposure[s] for s in published]
    probe.merge_child(str(child_out))
    run, diag = res['run'], res['diagnostics']
    counts = run['counts']
    tr = counts.get('tracker', {})
    bundle = counts.get('bundle', {})
    stereo = counts.get('stereo', {})
    kf_stamps = list(probe.kf_order)
    n_in = run['frames']
    n_kf = len(kf_stamps)
    n_tracked = tr.get('frames_tracked', 0)
    dropped = {k: tr.get(k, 0) for k in ('drops', 'frames_unused', 'bad_images') if tr.get(k, 0)}
    cam_counts = counts.get('camera', {})
    dropped.update({f'camera_{k}': cam_counts[k] for k in ('skipped_unreadable', 'skipped_size_mismatch')
                    if cam_counts.get(k)})
    lag_pose = [poses.first[s] - exposure[s] for s in kf_stamps if s in poses.first and s in exposure]
    lag_kf = [probe.kf_published[s] - exposure[s] for s in kf_stamps if s in exposure]
    lag_cloud = [probe.kf_fused[s][0] - exposure[s] for s in kf_stamps if s in probe.kf_fused and s in exposure]
    last_fused = max((v[0] for v in probe.kf_fused.values()), default=t_end)
    # Poses that came while photos were still coming (the flight's end: its last photo's period after it),
    # apart from those that waited for the end of flight (a segment joined at the final adjustment).
    flight_end = max(exposure.values(), default=t0) + period_s
    lag_pose_flight = [poses.first[s] - exposure[s] for s in kf_stamps
                       if s in poses.first and s in exposure and poses.first[s] <= flight_end]
    flight_s = run['bag_s'] / rate + period_s   # the last photo's period is flown too
    # The flight's last minute: keyframes exposed in its last 60 s.
    last_min = {s for s in kf_stamps if s in exposure and exposure[s] >= flight_end - period_s - 60.0}
    lag_pose_last = [poses.first[s] - exposure[s] for s in last_min if s in poses.first]
    lag_cloud_last = [probe.kf_fused[s][0] - exposure[s] for s in last_min if s in probe.kf_fused]
    # The stereo node pairs final (not provisional) poses: the lag it adds is final pose -> fused cloud.
    lag_final_pose = [poses.first_final[s] - exposure[s] for s in kf_stamps if s in poses.first_final and s in exposure]
    lag_final_to_cloud = [probe.kf_fused[s][0] - poses.first_final[s] for s in kf_stamps
                          if s in probe.kf_fused and s in poses.first_final]
    lag_final_to_cloud_last = [probe.kf_fused[s][0] - poses.first_final[s] for s in last_min
                               if s in probe.kf_fused and s in poses.first_final]
    if a.keep:   # every pose each keyframe was given (monotonic s, provisional, map_T_cam), and when it was fused
        (out / 'pose_history.json').write_text(json.dumps(
            {'poses': {str(s): [(t, p, T.tolist()) for t, p, T in h] for s, h in poses.history.items()},
             'fused': {str(s): v[0] for s, v in probe.kf_fused.items()},
             'exposure': {str(s): v for s, v in exposure.items()}, 'flight_end': flight_end}))
    moved = pose_moved_after_fused(poses.history, {s: v[0] for s, v in probe.kf_fused.items()}, flight_end)
    first_photo = min(exposure.values(), default=None)
    first_pose_s = (round(min(poses.first.values()) - first_photo, 2)
                    if poses.first and first_photo is not None else None)
    map_counts = counts.get('map', {})
    shed = {'tracker_frames_dropped': dropped, 'stereo_keyframes_shed': stereo.get('keyframes_shed', 0),
            'stereo_pairs_shed': sum(v for k, v in stereo.items() if k.startswith('pairs_shed')),
            'ortho_batches_deferred': map_counts.get('ortho_batches_deferred', 0)}
    tracker_node = 'tracker_node'
    sdiag = diag.get('stereo_node', diag.get('/stereo_node', {}))
    # What was shed as /diagnostics said it: the stereo node's WARNs about shed pairs, the tracker's drops.
    shed['said_on_diagnostics'] = sorted({text for _, text in sdiag.get('problems', []) if 'shed' in text})
    shed['gsd_m'] = sdiag.get('values', {}).get('gsd_m')
    tdiag = diag.get(tracker_node, diag.get('/' + tracker_node, {})).get('values', {})
    row = {'bench': 'inflight_20mp', 'flight': a.flight, 'config': tag, 'period_s': period_s,
           'size': '{}x{}'.format(*(SENECA_SIZE if a.flight == 'seneca' else SIZE)), **CODE,
           'photos_in': n_in, 'photos_tracked': n_tracked, 'keyframes': n_kf,
           'skipped_by_overlap_rule': n_tracked - n_kf - tr.get('unusable', 0),
           'dropped_otherwise': sum(dropped.values()), 'dropped_why': dropped,
           'oriented': len(lag_pose), 'oriented_share': round(len(lag_pose) / max(n_kf, 1), 3),
           'bundle_counts': {k: bundle[k] for k in sorted(bundle) if k.startswith(('keyframes_', 'not_oriented'))},
           'lag_exposure_to_keyframe_s': lag_stats(lag_kf),
           'lag_exposure_to_pose_s': lag_stats(lag_pose),
           'lag_exposure_to_pose_in_flight_s': lag_stats(lag_pose_flight),
           'poses_only_at_end_of_flight': len(lag_pose) - len(lag_pose_flight), 'lag_exposure_to_fused_cloud_s': lag_stats(lag_cloud),
           'keyframes_in_fused_clouds': len(lag_cloud),
           'last_minute_keyframes': len(last_min),
           'lag_exposure_to_pose_last_minute_s': lag_stats(lag_pose_last),
           'lag_exposure_to_fused_cloud_last_minute_s': lag_stats(lag_cloud_last),
           'first_pose_after_first_photo_s': first_pose_s,
           'lag_exposure_to_final_pose_s': lag_stats(lag_final_pose),
           'lag_final_pose_to_fused_cloud_s': lag_stats(lag_final_to_cloud),
           'lag_final_pose_to_fused_cloud_last_minute_s': lag_stats(lag_final_to_cloud_last),
           'pose_moved_after_fused': moved,
           'pose_moved_after_first_fused_any_status': pose_moved_after_first_fused(
               poses.history, {s: v[0] for s, v in probe.kf_fused.items()}),
           'relative_pose_moved_after_first_fused': relative_pose_moved_after_fused(
               poses.history, {s: v[0] for s, v in probe.kf_fused.items()}),
           'shed': shed,
           'camera_late_s': lag_stats(camera_late),
           'stereo': {k: stereo[k] for k in sorted(stereo) if k.startswith(('pairs', 'keyframes', 'images'))},
           'tracker_diag': {k: tdiag[k] for k in sorted(tdiag) if k in (
               'process_ms', 'frame_from_msg_ms', 'keyframe_ms', 'target_detection_ms', 'keyframe_images_ms',
               'target_detection_ms_total', 'keyframe_image_reduction', 'fps')},
           'tracker_counts': {k: v for k, v in sorted(tr.items()) if not k.startswith(('keyframes_target', 'target'))},
           'tracker_target_search': {k: v for k, v in tr.items() if k.startswith(('keyframes_target', 'target',
                                                                                 'targets'))},
           'map_counts': {k: v for k, v in counts.get('map', {}).items() if k.startswith(('ortho', 'clouds', 'keyframes'))},
           'flight_s': round(flight_s, 1), 'wall_s': round(run['wall_s'], 1),
           'until_last_cloud_s': round(last_fused - t0, 1),
           'real_time_factor': round(flight_s / max(last_fused - t0, 1e-9), 3),
           'real_time_factor_with_end_of_flight': round(flight_s / run['wall_s'], 3),
           'peak_rss_mb': round(sampler.peak_mb, 1), 'child_peak_rss_mb': round(probe.child_figures.get('peak_rss_mb') or 0.0, 1),
           'peak_rss_all_mapping_mb_upper_bound': round(sampler.peak_mb + (probe.child_figures.get('peak_rss_mb') or 0.0), 1),
           'cores': os.cpu_count(), 'load_avg_before': [round(x, 2) for x in load_before],
           'load_avg_after': [round(x, 2) for x in load_after]}
    row['map_dir'] = str(res['map_dir'])
    if a.verdict:
        row['verdict'] = replay_verdict(a, res, out / 'products')
    emit(row)
    per = {k: v for k, v in probe.breakdown(run['wall_s']).items() if v['calls']}
    emit({'bench': 'inflight_20mp_methods', 'config': tag, 'methods': per})
    return row


def replay_verdict(a, res: dict, out: Path) -> dict:
    """What `replay` prints at the end of this run: its products made as replay makes them (export_products: matched
    again from the final adjustment) and the flight report's verdict (mapped, or MAPPING FAILED, with its warnings)."""
    from photogram_ros.commands.products import export_products
    t0 = time.perf_counter()
    try:
        prod = export_products(res['map_dir'], out, a.params, run=res['run'], diagnostics=res['diagnostics'])
    except Exception as exc:   # a failed export is the verdict's finding, not the bench's end
        return {'mapped': False, 'failures': [f'export failed: {type(exc).__name__}: {exc}'],
                'export_wall_s': round(time.perf_counter() - t0, 1)}
    fig = prod['figures']
    v = fig.get('mapping', {'mapped': False, 'failures': ['no report was made']})
    return {'mapped': bool(v.get('mapped')), 'failures': v.get('failures', []), 'warnings': v.get('warnings', []),
            'keyframes_taken': fig.get('keyframes_taken'), 'keyframes_oriented': fig.get('keyframes_oriented'),
            'export_wall_s': round(time.perf_counter() - t0, 1)}


TABLE_ROWS = [
    ('photos in', lambda r: r['photos_in']),
    ('keyframes', lambda r: r['keyframes']),
    ('skipped by the overlap rule', lambda r: r['skipped_by_overlap_rule']),
    ('dropped otherwise (why)', lambda r: f"{r['dropped_otherwise']} {r['dropped_why'] or ''}".strip()),
    ('oriented share', lambda r: f"{r['oriented_share']:.3f} ({r['oriented']}/{r['keyframes']})"),
    ('lag exposure -> pose p50/p95/max, s', lambda r: '{p50}/{p95}/{max}'.format(**r['lag_exposure_to_pose_s'])),
    ('... of the poses given in flight (n)', lambda r: '{p50}/{p95}/{max} ({n})'.format(**r['lag_exposure_to_pose_in_flight_s'])),
    ('lag exposure -> keyframe published p50/p95/max, s',
     lambda r: '{p50}/{p95}/{max}'.format(**r['lag_exposure_to_keyframe_s'])),
    ('lag exposure -> fused cloud p50/p95/max, s',
     lambda r: '{p50}/{p95}/{max}'.format(**r['lag_exposure_to_fused_cloud_s'])),
    ('... in the last minute p50/p95 (n)', lambda r: '{p50}/{p95} ({n})'.format(
        **r.get('lag_exposure_to_fused_cloud_last_minute_s', {'p50': None, 'p95': None, 'n': 0}))),
    ('lag exposure -> pose in the last minute p50/p95 (n)', lambda r: '{p50}/{p95} ({n})'.format(
        **r.get('lag_exposure_to_pose_last_minute_s', {'p50': None, 'p95': None, 'n': 0}))),
    ('first pose after the first photo, s', lambda r: r.get('first_pose_after_first_photo_s')),
    ('lag final pose -> fused cloud p50/p95 (n)', lambda r: '{p50}/{p95} ({n})'.format(
        **r.get('lag_final_pose_to_fused_cloud_s', {'p50': None, 'p95': None, 'n': 0}))),
    ('keyframes in fused clouds', lambda r: r['keyframes_in_fused_clouds']),
    ('stereo pairs done / skipped', lambda r: f"{r['stereo'].get('pairs_done', 0)} / "
     f"{sum(v for k, v in r['stereo'].items() if k.startswith('pairs_skipped'))}"),
    ('keyframes whose stereo pairs were shed', lambda r: r['stereo'].get('keyframes_shed', 0)),
    ('ortho batches deferred', lambda r: r.get('map_counts', {}).get('ortho_batches_deferred', 0)),
    ('real-time factor (to the last fused cloud)', lambda r: r['real_time_factor']),
    ('peak RSS main / child, MB', lambda r: f"{r['peak_rss_mb']} / {r['child_peak_rss_mb']}"),
    ('verdict (replay\'s, from the products)', lambda r: ('mapped' if r['verdict']['mapped'] else 'MAPPING FAILED')
     if 'verdict' in r else '-'),
    ('cores, load avg (1 min) before/after', lambda r: f"{r['cores']}, {r['load_avg_before'][0]}/{r['load_avg_after'][0]}"),
]


def utm_epsg(lat_deg: float, lon_deg: float) -> str:
    zone = int((lon_deg + 180.0) // 6.0) % 60 + 1
    return f'EPSG:{32600 + zone if lat_deg >= 0 else 32700 + zone}'


def export_dsm(map_dir: str, out: Path, params: str) -> dict:
    """`photogram-ros export MAP --densify --products dsm` as a surveyor runs it after landing (the pairs shed in
    flight are matched there from the stored keyframes, io/densify.py); the DSM's path, the wall time and what
    export printed."""
    import subprocess

    from photogram_ros.io.map_store import MapStore
    origin = MapStore(map_dir).origin
    crs = utm_epsg(origin.lat_deg, origin.lon_deg)
    env = {**os.environ, 'PYTHONPATH': str(ROOT)}
    env.pop('PHOTOGRAM_PROBE_CHILD_OUT', None)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'export', map_dir, '--crs', crs, '--out', str(out),
                        '--densify', '--params', params, '--products', 'dsm', '--quiet'],
                       capture_output=True, text=True, env=env)
    return {'dsm': str(out / 'dsm.tif'), 'crs': crs, 'exit': r.returncode, 'wall_s': round(time.perf_counter() - t0, 1),
            'printed': r.stdout.strip().splitlines()[:3] + ([r.stderr.strip()[-400:]] if r.returncode else [])}


def compare_dsm(dsm: str, reference: str) -> dict:
    """|dz| between two DSM GeoTIFFs over the cells stereo measured in both (band 2 > 0: not interpolated), the
    DSM resampled onto the reference's grid (nearest): median, p90, the cells compared."""
    import numpy as np
    import rasterio
    from rasterio.warp import Resampling, reproject
    with rasterio.open(reference) as ref, rasterio.open(dsm) as ds:
        z_ref, n_ref = ref.read(1).astype(float), ref.read(2)
        z, n = np.full(z_ref.shape, np.nan), np.zeros(z_ref.shape, np.float32)
        src_z = ds.read(1).astype(float)
        if ds.nodata is not None:
            src_z[src_z == ds.nodata] = np.nan
        reproject(src_z, z, src_transform=ds.transform, src_crs=ds.crs, dst_transform=ref.transform, dst_crs=ref.crs,
                  resampling=Resampling.nearest, src_nodata=np.nan, dst_nodata=np.nan)
        reproject(ds.read(2).astype(np.float32), n, src_transform=ds.transform, src_crs=ds.crs,
                  dst_transform=ref.transform, dst_crs=ref.crs, resampling=Resampling.nearest)
        if ref.nodata is not None:
            z_ref[z_ref == ref.nodata] = np.nan
    both = np.isfinite(z) & np.isfinite(z_ref) & (n > 0) & (n_ref > 0)
    dz = np.abs(z[both] - z_ref[both])
    return {'cells_compared': int(both.sum()), 'cells_reference_measured': int(np.sum(np.isfinite(z_ref) & (n_ref > 0))),
            'median_abs_dz_m': round(float(np.median(dz)), 4) if dz.size else None,
            'p90_abs_dz_m': round(float(np.percentile(dz, 90)), 4) if dz.size else None}


def dsm_row(a, row: dict, ref: dict, out_root: Path) -> dict:
    """Export the run's stored map (densify included) and compare its DSM with the reference run's."""
    mine = export_dsm(row['map_dir'], out_root / f"export_{row['config']}", a.params)
    d = {'bench': 'inflight_20mp_dsm', 'config': row['config'], 'reference': ref['config'], **CODE,
         'reference_is': REFERENCE_IS,
         'export': mine, 'reference_export': ref.get('export'), 'shed': row['shed'], 'reference_shed': ref['shed']}
    if mine['exit'] == 0 and ref.get('export', {}).get('exit') == 0:
        d.update(compare_dsm(mine['dsm'], ref['export']['dsm']))
        g = row['shed'].get('gsd_m') or ref['shed'].get('gsd_m')
        if g and d['median_abs_dz_m'] is not None:
            d['gsd_m'] = g
            d['median_abs_dz_gsd'] = round(d['median_abs_dz_m'] / g, 3)
            d['within_1_gsd'] = d['median_abs_dz_gsd'] <= 1.0
    return d


REFERENCE_IS = ('the first run\'s export --densify: every pair matched again after landing from all its stored keyframes '
                'and final poses (no in-flight pair read, shed or not)')


def table(rows: list[dict]) -> str:
    head = '| | ' + ' | '.join(f"{r['config']}" for r in rows) + ' |'
    lines = [head, '|---' * (len(rows) + 1) + '|']
    for name, fn in TABLE_ROWS:
        lines.append(f'| {name} | ' + ' | '.join(str(fn(r)) for r in rows) + ' |')
    return '\n'.join(lines) + '\n'


def parse_sets(items) -> dict:
    extra: dict = {}
    for item in items:
        key, _, value = item.partition('=')
        role, _, name = key.partition('.')
        extra.setdefault(role, {})[name] = json.loads(value) if value[:1] in '-0123456789[{tf' else value
    return extra


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--periods', default='2,1', help='photo periods to run, s (comma list)')
    ap.add_argument('--flight', default='toledo', choices=('toledo', 'seneca', 'sim'),
                    help='toledo\'s 42 real photos upscaled, seneca_part\'s 41 real near-infrared fixed-wing photos '
                         'upscaled, or the simulated survey (317 photos, a second apart, '
                         'with surveyed targets; played 1/period times as fast: at 0.7 s a photo every 0.7 s)')
    ap.add_argument('--photos', type=int, default=42,
                    help='photos used (toledo: at most 42; seneca: at most 41; sim: at most 317)')
    ap.add_argument('--params', default=str(ROOT / 'config' / 'replay.yaml'))
    ap.add_argument('--set', action='append', default=[], metavar='ROLE.PARAM=VALUE',
                    help='override a node parameter for every run')
    ap.add_argument('--baseline-set', action='append', default=[], metavar='ROLE.PARAM=VALUE',
                    help='also run each period with these overrides first (the baseline of the ratios)')
    ap.add_argument('--keep', default='', help='keep the outputs in this folder')
    ap.add_argument('--table', default='', help='write the markdown table to this file')
    ap.add_argument('--json', default='', help='write all rows as one JSON file')
    ap.add_argument('--out', default='', help='append every JSON line to this file (e.g. '
                                               'bench/results/inflight_20mp_<commit>.jsonl)')
    ap.add_argument('--verdict', action='store_true',
                    help='after each run, make the products as `replay` does and record its verdict (mapped or '
                         'MAPPING FAILED, with the warnings)')
    ap.add_argument('--build-only', action='store_true')
    ap.add_argument('--tracker-cpu', type=int, default=0, metavar='REPEATS',
                    help='instead of the graph: the tracker alone (core/tracker.Tracker, run\'s defaults with the '
                         'tracker.X of --set / --baseline-set) over the built photos, REPEATS times alternating with the '
                         'baseline: CPU per frame and its split by step (tracker_cpu_split)')
    ap.add_argument('--summarise-kept', default='', metavar='DIR',
                    help='recompute the pose figures of a run kept with --keep (DIR: its period folder, e.g. KEEP/1s)')
    ap.add_argument('--export-dsm', action='store_true',
                    help='after each run, `export --densify --products dsm` its stored map; the first period\'s '
                         'run is the reference the later ones\' DSMs are compared with (median |dz|, in GSD)')
    a = ap.parse_args()
    periods = [float(p) for p in a.periods.split(',') if p.strip()]
    if a.out:
        OUT.append(a.out)
    CODE.update(commit=git('rev-parse', '--short', 'HEAD'),
                clean_tree=not git('status', '--porcelain', '--', 'photogram_ros', 'bench/inflight_20mp.py'))
    emit({'machine': machine_info(), 'load_avg_before': [round(x, 2) for x in os.getloadavg()]})
    if a.summarise_kept:
        emit(summarise_kept(Path(a.summarise_kept)))
        return 0
    if a.tracker_cpu:
        for p in periods:
            folder, calib = build_flight(p, a.photos, flight=a.flight)
            for row in tracker_cpu_rows(folder, calib, a):
                emit(row)
        return 0
    if a.build_only:
        for p in periods:
            built = build_sim_flight(a.photos) if a.flight == 'sim' else build_flight(p, a.photos, flight=a.flight)
            emit({'built': [str(x) for x in built]})
        return 0
    extra = parse_sets(a.set)
    rows = []
    ref = None   # the first run, exported: the DSM the later runs' are compared with (--export-dsm)
    out_root = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix='inflight20mp_dsm_'))
    for p in periods:
        if a.baseline_set:
            base_extra = {r: {**extra.get(r, {}), **v} for r, v in parse_sets(a.baseline_set).items()}
            base_extra = {**extra, **base_extra}
            rows.append(run_period(a, p, base_extra, f'{p:g}s_baseline'))
        rows.append(run_period(a, p, extra, f'{p:g}s'))
        if a.export_dsm:
            if ref is None:
                ref = dict(rows[-1], export=export_dsm(rows[-1]['map_dir'], out_root / f"export_{rows[-1]['config']}",
                                                       a.params))
                emit({'bench': 'inflight_20mp_dsm', 'config': ref['config'], 'reference': None, **CODE,
                      'reference_is': REFERENCE_IS,
                      'export': ref['export'], 'shed': ref['shed']})
            else:
                emit(dsm_row(a, rows[-1], ref, out_root))
        if a.baseline_set:
            b, n = rows[-2], rows[-1]
            emit({'bench': 'inflight_20mp_compare', 'period_s': p, 'baseline': a.baseline_set,
                  'keyframes': [b['keyframes'], n['keyframes']], 'dropped': [b['dropped_otherwise'], n['dropped_otherwise']],
                  'lag_pose_p95_ratio': _ratio(n['lag_exposure_to_pose_s']['p95'], b['lag_exposure_to_pose_s']['p95']),
                  'lag_cloud_p95_ratio': _ratio(n['lag_exposure_to_fused_cloud_s']['p95'],
                                                b['lag_exposure_to_fused_cloud_s']['p95']),
                  'rtf_ratio': _ratio(n['real_time_factor'], b['real_time_factor'])})
    if a.table:
        Path(a.table).write_text(table(rows))
    if a.json:
        Path(a.json).write_text(json.dumps({'machine': machine_info(), 'rows': rows}, indent=1))
    print(table(rows))
    return 0


# cProfile entries (by function name) of each step of the tracker's CPU split (tracker_cpu_split).
CPU_STEPS = {'decode': ('imdecode',), 'klt': ('calcOpticalFlowPyrLK', 'warpAffine', 'warpPerspective',
                                                'estimateAffinePartial2D', 'findHomography'),
             'corners': ('goodFeaturesToTrack', 'circle'), 'normalise': ("apply' of 'cv2.CLAHE",),
             'sift_extract': ("detectAndCompute",), 'match_flann_build': ("train' of 'cv2.DescriptorMatcher",),
             'match_knn': ("knnMatch",), 'match_verify_essential': ('findEssentialMat',)}


def tracker_cpu_split(folder: Path, calib: Path, overrides: dict) -> dict:
    """One pass of the tracker alone over the photos (EncodedImage, each photo's EXIF fix given before it, as the
    camera node publishes it): CPU s per frame (time.process_time) and the split by step (cProfile's own time of
    the OpenCV calls of CPU_STEPS; the rest: Python)."""
    import cProfile
    import pstats

    import numpy as np

    from photogram_ros.core.camera import load_calibration
    from photogram_ros.core.tracker import EncodedImage, Tracker, TrackerParams
    from photogram_ros.io.image_source import FolderSource, read_exif_gps
    from photogram_ros.params import from_dict
    cam = load_calibration(str(calib))
    photos = []
    for path, stamp in FolderSource(folder).entries:
        gps = read_exif_gps(path)
        photos.append((np.fromfile(str(path), np.uint8), stamp, gps.gnss_fix(stamp, 3.0, 5.0) if gps else None))
    tr = Tracker(cam, from_dict(TrackerParams, overrides))
    per, kfs = [], []
    prof = cProfile.Profile(time.process_time)
    prof.enable()
    for data, stamp, fix in photos:
        if fix is not None:
            tr.add_fix(fix)
        t0 = time.process_time()
        kfs += tr.process(EncodedImage(data), stamp)
        per.append(time.process_time() - t0)
    kfs += tr.flush()
    prof.disable()
    own = {}
    for (_, _, name), (_, _, tt, _, _) in pstats.Stats(prof).stats.items():
        step = next((k for k, names in CPU_STEPS.items() if any(n in name for n in names)), 'python_and_rest')
        own[step] = own.get(step, 0.0) + tt
    total = float(sum(per))
    st = tr.stats
    return {'frames': st.frames, 'keyframes': st.keyframes, 'breaks': st.breaks, 'bridged': st.bridged,
            'lost': sum(1 for k in kfs if k.break_before and not k.bridged), 'chain_pairs': st.chain_pairs,
            'chain_verified': st.chain_verified,
            'cpu_s_per_frame': {'p50': round(float(np.median(per)), 3), 'mean': round(total / len(per), 3),
                                'max': round(float(max(per)), 3)},
            'cpu_split_s_per_frame': {k: round(v / len(per), 4) for k, v in sorted(own.items(), key=lambda kv: -kv[1])}}


def tracker_cpu_rows(folder: Path, calib: Path, a) -> list[dict]:
    """--tracker-cpu: the tracker alone, new (--set) and baseline (--baseline-set) alternating, a.tracker_cpu times
    each; one row per pass and a comparison row (ratio of the mean CPU per frame)."""
    import numpy as np
    new = parse_sets(a.set).get('tracker', {})
    base = {**new, **parse_sets(a.baseline_set).get('tracker', {})}
    configs = [('baseline', base), ('new', new)] if a.baseline_set else [('new', new)]
    rows = []
    for rep in range(a.tracker_cpu):
        for tag, over in configs:
            rows.append({'bench': 'inflight_20mp_tracker_cpu', 'flight': a.flight, 'photos': str(folder.name),
                         'config': tag, 'tracker_set': over, 'repeat': rep, **CODE,
                         'load_avg': [round(x, 2) for x in os.getloadavg()],
                         **tracker_cpu_split(folder, calib, over)})
    if a.baseline_set:
        mean = {tag: np.mean([r['cpu_s_per_frame']['mean'] for r in rows if r['config'] == tag]) for tag, _ in configs}
        rows.append({'bench': 'inflight_20mp_tracker_cpu_compare', 'flight': a.flight, **CODE,
                     'baseline': a.baseline_set, 'set': a.set,
                     'cpu_per_frame_mean_s': [round(float(mean['baseline']), 3), round(float(mean['new']), 3)],
                     'cpu_ratio_new_to_baseline': _ratio(float(mean['new']), float(mean['baseline']))})
    return rows


def _ratio(x, y):
    return round(x / y, 3) if x is not None and y else None


if __name__ == '__main__':
    sys.exit(main())
