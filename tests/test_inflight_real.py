"""The in-flight path (core/tracker.py -> core/incremental.py, as tracker_node and bundle_node chain them)
on real imagery: brighton_beach, 18 DJI survey photos 7 s apart with EXIF GPS and EXIF
intrinsics (photo-rate input: every frame beyond KLT's reach), and the phantom3 village video keyframes
(1920 x 1080, 0.4-2 s apart) with a GNSS track made from the published trajectory plus the noise of a
3D fix. Both go frame by frame as in flight: keyframes are adjusted as they come, never the whole set
at once; the share oriented is counted before any end-of-flight second chance."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import shared_data
from figures import newest_figure
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.gnss_fix import STATUS_FIX, GnssFix
from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions, KeyframeRecord
from photogram_ros.core.similarity import umeyama
from photogram_ros.core.tracker import Tracker, TrackerParams

pytestmark = pytest.mark.slow

# The same photos and frames through `replay` (tracker_node and bundle_node chaining these classes), as
# bench/real_surveys.py measured them: the gates below hold the counts as measured and the errors within 1.5x, of
# the line the real-surveys table renders (the newest bench/results/real_surveys*.jsonl holding it, named in the
# messages).
REAL = 'real_surveys*.jsonl'


def fly(frames, camera, fixes_for, tracker_params=None):
    """Tracker then IncrementalAT, keyframe by keyframe. `frames`: (stamp_ns, image) in time order;
    `fixes_for(stamp_ns)`: the fixes the receiver gave up to that frame. Returns (tracker, at, keyframes)."""
    tr = Tracker(camera, tracker_params or TrackerParams())
    at = IncrementalAT(camera, IncrementalOptions())
    kfs = []

    def adjust(new):
        for k in new:
            rec = KeyframeRecord(k.stamp_ns, k.observations['track_id'].astype(np.int64),
                                 np.column_stack([k.observations['u'], k.observations['v']]), k.fix)
            at.add_keyframe(rec)
            kfs.append(k)

    for stamp, image in frames:
        for f in fixes_for(stamp):
            tr.add_fix(f)
        adjust(tr.process(image, stamp))
    adjust(tr.flush())
    return tr, at, kfs


def track_lengths(kfs) -> np.ndarray:
    ids = np.concatenate([k.observations['track_id'] for k in kfs])
    return np.bincount(np.unique(ids, return_inverse=True)[1])


def test_brighton_beach_photos_orient_in_flight():
    from photogram_ros.io.image_source import FolderSource
    src = FolderSource(shared_data('photos', 'brighton_beach', 'images'))
    camera = src.exif_intrinsics().camera
    photos = list(src)
    fixes = {p.stamp_ns: p.gps.gnss_fix(p.stamp_ns, 5.0, 10.0) for p in photos}
    tr, at, kfs = fly([(p.stamp_ns, p.image) for p in photos], camera, lambda s: [fixes[s]])
    n = len(at.kfs)
    lengths = track_lengths(kfs)
    share = len(at.registered) / n
    print(f'brighton_beach: {tr.stats.frames} photos, {n} keyframes, {tr.stats.bridged} bridged of '
          f'{tr.stats.breaks} breaks, {len(at.registered)} oriented ({share:.0%}); tracks seen 3+ times '
          f'{int(np.sum(lengths >= 3))}, 4+ {int(np.sum(lengths >= 4))}; tracker '
          f'{tr.stats.process_s / tr.stats.frames:.2f} s/photo; GNSS residual {at.gnss_rms_m():.2f} m')
    name, m = newest_figure(REAL, survey='brighton', pipeline='replay')
    assert n == m['keyframes_taken'] and len(at.registered) == m['keyframes_oriented'], (n, name)
    assert at.georeferenced
    assert np.sum(lengths >= 3) >= 20 * n, 'points must be seen by 3+ keyframes'
    # EXIF GPS of a consumer receiver (sigma 5 m given): the adjusted cameras against it as `replay`'s are.
    assert at.gnss_rms_m() <= 1.5 * float(np.hypot(m['rigid_h_m'], m['rigid_v_m']))


def phantom3_frames():
    import cv2
    root = Path(shared_data('video', 'phantom3_village'))
    traj = np.loadtxt(root / 'trajectory.txt')
    frames = [(int(round(t * 1e9)), root / 'rgb' / f'{t:.6f}.jpg') for t in traj[:, 0]]
    frames = [(s, p) for s, p in frames if p.exists()]
    camera = PinholeCamera(1920, 1080, 1220.0, 1220.0, 960.0, 540.0)
    origin = LocalFrame(27.082665, 112.780393, 0.0)     # config.cfg GPS.Origin (lon, lat, alt)
    return camera, origin, traj, [(s, cv2.imread(str(p))) for s, p in frames]


def test_phantom3_video_keyframes_orient_near_the_trajectory():
    camera, origin, traj, frames = phantom3_frames()
    rng = np.random.default_rng(14)
    sig_h, sig_v = 1.5, 3.0          # a 3D fix
    noisy = traj[:, 1:4] + rng.normal(0, [sig_h, sig_h, sig_v], (len(traj), 3))
    lat, lon, h = origin.enu_to_geodetic(noisy)
    cov = np.diag([sig_h ** 2, sig_h ** 2, sig_v ** 2])
    fixes = {int(round(t * 1e9)): GnssFix(float(a), float(o), float(z), cov, int(round(t * 1e9)), STATUS_FIX)
             for t, a, o, z in zip(traj[:, 0], lat, lon, h)}
    tr, at, kfs = fly(frames, camera, lambda s: [fixes[s]] if s in fixes else [])
    share = len(at.registered) / len(at.kfs)
    # Camera centres against the published trajectory, in the block's map (ENU at its first fix).
    truth = {int(round(t * 1e9)): p for t, p in zip(traj[:, 0], traj[:, 1:4])}
    got = np.array([at.kfs[k].map_T_cam[:3, 3] for k in at.registered])
    lat_t, lon_t, h_t = origin.enu_to_geodetic(np.array([truth[at.kfs[k].stamp_ns] for k in at.registered]))
    ref = at.origin.geodetic_to_enu(lat_t, lon_t, h_t)
    rms = float(np.sqrt(np.mean(np.sum((got - ref) ** 2, axis=1))))
    fitted = umeyama(got, ref).apply(got)
    rms_sim = float(np.sqrt(np.mean(np.sum((fitted - ref) ** 2, axis=1))))
    print(f'phantom3: {tr.stats.frames} frames, {len(at.kfs)} keyframes ({tr.stats.breaks} breaks, '
          f'{tr.stats.bridged} bridged), {len(at.registered)} oriented ({share:.0%}); camera centres '
          f'{rms:.2f} m RMS from the trajectory ({rms_sim:.2f} m after a similarity fit; GNSS noise '
          f'{sig_h} m / {sig_v} m); tracker {tr.stats.process_s / tr.stats.frames * 1e3:.0f} ms/frame')
    name, m = newest_figure(REAL, survey='phantom3', pipeline='replay')
    assert share >= m['keyframes_oriented'] / m['keyframes_taken'], name
    # Against the published trajectory after a similarity (the block's shape), and as placed by the noisy fixes.
    assert rms_sim <= 1.5 * float(np.hypot(m['sim_h_m'], m['sim_v_m']))
    assert rms <= 1.5 * float(np.hypot(m['rigid_h_m'], m['rigid_v_m']))
