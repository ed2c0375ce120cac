"""CPU seconds per photo of every stage of the in-flight graph on 20 MP photos, beside each stage's floor.

The photos: toledo's real DJI photos cropped to 3:2 and upscaled to 5472 x 3648 (20 MP), as
bench/inflight_20mp.py builds them (its cache is shared), with the calibration scaled the same way and
the EXIF GPS as fixes. Every stage is the project's own code called directly (no ROS), one photo or
keyframe after the other in this process, and timed in CPU seconds of the process (time.process_time:
OpenCV's worker threads count, the other engineers' jobs do not):

- decode: the full BGR decode of the JPEG (what a keyframe image needed), and libjpeg's DCT-scaled decodes
  at 1/2, 1/4 (colour) and 1/8 (grey: the tracker's working size); floor: the 1/8 grey decode.
- tracking: core/tracker.Tracker.process on the still-compressed photo (its reduced decode, KLT, keyframe
  choice), less the descriptor matching it does at breaks (timed apart, below); floor: KLT of 400 corners
  between two 1/8 greys (goodFeaturesToTrack + calcOpticalFlowPyrLK, no checks).
- descriptor matching: core/photo_matching extract + match_pair as the tracker calls them; floor: 1000 SIFT
  features on the 1/8 grey and a brute-force ratio match to the previous photo's.
- pose (resection) and window adjustment: stages/adjustment.AdjustmentStage fed keyframe by keyframe (its
  IncrementalAT's registration and window update timed apart, the rest of the stage as 'adjustment_other');
  floor of the pose: cv2.solvePnPRansac on 300 of the keyframe's points; of the window: the cheapest
  window update of the run (a keyframe joining an adjusted window).
- targets: core/control.detect_keyframe_targets on the full image (what the tracker node ran), on the
  photo searched everywhere (control.detect_keyframe_targets_encoded: the grey decode, candidates on a 1/4
  copy, full resolution around candidates: target_search everywhere), and searched only where surveyed
  targets can be (control.target_regions + detect_targets_in_regions on the keyframe image's reduced decode,
  as the tracker node does with a control file). Toledo has no surveyed targets: SURVEY_TARGETS places
  three boards on the ground under photos of the flight (the ground EXIF_HEIGHT_M below their EXIF
  altitudes), so the rings are where a surveyor's would be; floor: the candidate search alone on the 1/8 grey.
- stereo pair: core/stereo.stereo_pair on consecutive keyframes with the final poses, from full-size images
  and from images at the keyframe reduction (gsd.keyframe_reduction) with the camera scaled; floor: SGBM alone
  on two images of the matched size with the pair's disparity count.
- fusion and tiles: stages/map.MapStage.add_cloud and stream_ortho per pair cloud; floors: summing the cloud's
  heights into its cells (one numpy bincount) and one 256 px PNG encode.
- messages: serialising the keyframe image message (full raw, reduced raw) and the features and cloud
  messages (rclpy.serialization, no ROS graph); floor: the 1/8 image message.

Per stage: CPU s per call, calls, and CPU s per photo (total / photos in). JSON lines to
bench/results/stage_budget_<commit>.jsonl (commit, clean tree, cores, load), and a markdown table (--table).

    .venv/bin/python bench/stage_budget.py [--photos 24] [--table bench/notes_stage_budget_table.md]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT))

from machine import machine_info  # noqa: E402


class Budget:
    """CPU seconds and calls per stage name."""

    def __init__(self):
        self.cpu = defaultdict(float)
        self.calls = defaultdict(int)

    def time(self, name, fn, *args, **kwargs):
        t0 = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            self.cpu[name] += time.process_time() - t0
            self.calls[name] += 1

    def wrap(self, owner, attr: str, name: str):
        """Replace owner.attr with a timed call (bench instrumentation, from outside)."""
        fn = getattr(owner, attr)
        budget = self

        def timed(*args, **kwargs):
            return budget.time(name, fn, *args, **kwargs)
        setattr(owner, attr, timed)
        return fn


def git(*args) -> str:
    return subprocess.run(['git', *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()


def photos_and_fixes(n: int):
    from inflight_20mp import build_flight

    from photogram_ros.core.camera import load_calibration
    from photogram_ros.io.image_source import FolderSource
    folder, calib = build_flight(1.0, 42)   # bench/inflight_20mp.py's 1 s flight (cached); its first n photos
    src = FolderSource(folder)
    out = []
    for path, stamp in src.entries[:n]:
        from photogram_ros.io.image_source import read_exif_gps
        gps = read_exif_gps(path)
        out.append((path, stamp, gps.gnss_fix(stamp, 3.0, 5.0) if gps else None))
    return out, load_calibration(calib)


# Made-up boards for the region search on toledo (no surveyed targets): on the ground under these photos.
SURVEY_TARGETS = (4, 14, 30)
EXIF_HEIGHT_M = 100.0   # toledo's height above ground, about (its EXIF altitudes are above the take-off point)


def survey_targets(photos):
    from photogram_ros.core.control import ControlSet, SurveyedTarget
    out = []
    for k, i in enumerate(SURVEY_TARGETS):
        fix = photos[i][2] if i < len(photos) else None
        if fix is not None:
            out.append(SurveyedTarget(f'T{k}', k, fix.lat_deg, fix.lon_deg, fix.h_m - EXIF_HEIGHT_M, 'gcp'))
    return ControlSet(out)


def run(n_photos: int) -> tuple[list[dict], dict]:
    from rclpy.serialization import serialize_message

    from photogram_ros import msgs
    from photogram_ros.core import control, gsd, stereo
    from photogram_ros.core import tracker as tracker_mod
    from photogram_ros.core.gnss_fix import COV_DIAGONAL_KNOWN, STATUS_FIX
    from photogram_ros.core.incremental import IncrementalAT
    from photogram_ros.core.pairs import PairCriteria, plan_pairs
    from photogram_ros.core.tracker import EncodedImage, Tracker, TrackerParams
    from photogram_ros.params import from_dict
    from photogram_ros.stages.adjustment import AdjustmentParams, AdjustmentStage, DiagnosticsLog, RecordedOutputs
    from photogram_ros.stages.map import MapOutputs, MapParams, MapStage

    photos, cam = photos_and_fixes(n_photos)
    b = Budget()
    floors = Budget()
    # The tracker's descriptor matching, timed apart (it runs inside Tracker.process).
    b.wrap(tracker_mod, 'extract', 'descriptor_matching')
    b.wrap(tracker_mod, 'match_pair', 'descriptor_matching')
    if hasattr(tracker_mod, 'DescriptorIndex'):   # the frame's FLANN index, built once for its matches
        b.wrap(tracker_mod, 'DescriptorIndex', 'descriptor_matching')
    from photogram_ros.core.at_register import Registration
    b.wrap(Registration, 'resect', 'pose_resection')
    b.wrap(Registration, 'relative', 'pose_resection')
    b.wrap(IncrementalAT, '_window_adjust', 'window_adjustment')
    window_calls = []
    win = IncrementalAT._window_adjust

    def window_timed(self, *a, **k):
        t0 = time.process_time()
        try:
            return win(self, *a, **k)
        finally:
            window_calls.append(time.process_time() - t0)
    IncrementalAT._window_adjust = window_timed

    trk = Tracker(cam, TrackerParams())
    stage = AdjustmentStage(from_dict(AdjustmentParams, {}), DiagnosticsLog(), RecordedOutputs())
    stage.set_camera(cam)
    fixes = {}
    keyframes = []     # (stamp, encoded photo)
    by_stamp = {}
    prev_grey8 = None
    prev_sift = None
    sift = cv2.SIFT_create(1000)
    aruco = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50),
                                    cv2.aruco.DetectorParameters())
    bf = cv2.BFMatcher(cv2.NORM_L2)
    n_kf_targets = 0
    kf_reduction = gsd.keyframe_reduction(cam.width, cam.height)
    regional = hasattr(control, 'target_regions')
    surveyed = survey_targets(photos) if regional else None
    rings = 0
    for path, stamp, fix in photos:
        data = np.fromfile(str(path), np.uint8)
        full = b.time('decode_full', cv2.imdecode, data, cv2.IMREAD_COLOR)
        b.time('decode_reduced_2', cv2.imdecode, data, cv2.IMREAD_REDUCED_COLOR_2)
        b.time('decode_reduced_4', cv2.imdecode, data, cv2.IMREAD_REDUCED_COLOR_4)
        grey8 = floors.time('decode', cv2.imdecode, data, cv2.IMREAD_REDUCED_GRAYSCALE_8)
        del full
        enc = EncodedImage(data)
        by_stamp[stamp] = enc
        if fix is not None:
            trk.add_fix(fix)
            fixes[stamp] = fix
        d0 = b.cpu['descriptor_matching']
        kfs = b.time('tracking', trk.process, enc, stamp)
        b.cpu['tracking'] -= b.cpu['descriptor_matching'] - d0
        # Floors of tracking and descriptor matching on the 1/8 grey.
        if prev_grey8 is not None:
            def klt(a=prev_grey8, c=grey8):
                p0 = cv2.goodFeaturesToTrack(a, 400, 0.01, 10)
                return cv2.calcOpticalFlowPyrLK(a, c, p0, None)
            floors.time('tracking', klt)

        def sift_match(g=grey8, prev=prev_sift):
            kp, d = sift.detectAndCompute(g, None)
            if prev is not None and d is not None and prev[1] is not None:
                bf.knnMatch(d, prev[1], k=2)
            return kp, d
        prev_sift = floors.time('descriptor_matching', sift_match)
        prev_grey8 = grey8
        for kf in kfs:
            keyframes.append(kf)
            encoded = by_stamp[kf.stamp_ns]
            image = b.time('decode_full_keyframe', cv2.imdecode, encoded.data, cv2.IMREAD_COLOR)
            n_kf_targets += len(b.time('targets_full_image', control.detect_keyframe_targets, image, cam))
            b.time('targets_as_node', control.detect_keyframe_targets_encoded, encoded.data, cam)
            floors.time('targets', aruco.detectMarkers, grey8)
            small = cv2.imdecode(encoded.data, cv2.IMREAD_REDUCED_COLOR_8)
            b.time('message_image_full_raw', lambda im=image: serialize_message(msgs.image_msg(im, kf.stamp_ns)))
            reduced = b.time('decode_keyframe_reduced', msgs.decode_reduced, encoded.data, kf_reduction)
            if regional and kf.fix is not None:
                def in_regions(k=kf, im=reduced, data=encoded.data):
                    cov = np.asarray(k.fix.cov_enu_m2)
                    reg = control.target_regions(cam, surveyed, k.fix.lat_deg, k.fix.lon_deg, k.fix.h_m,
                                                 float(np.sqrt(max(cov[0, 0], cov[1, 1]))))
                    grey = cv2.cvtColor(im, cv2.COLOR_BGR2GRAY)
                    return reg, control.detect_targets_in_regions(data, grey, cam, reg)
                reg, _ = b.time('targets_in_regions', in_regions)
                rings += bool(reg.rings_px)
            b.time('message_image_reduced_raw', lambda im=reduced: serialize_message(msgs.image_msg(im, kf.stamp_ns)))
            floors.time('messages', lambda im=small: serialize_message(msgs.image_msg(im, kf.stamp_ns)))
            b.time('message_features', lambda k=kf: serialize_message(msgs.keyframe_features_msg(
                k.observations, k.stamp_ns)))
            f = fixes.get(kf.stamp_ns) or kf.fix
            if f is not None:
                stage.add_fix(kf.stamp_ns, f.lat_deg, f.lon_deg, f.h_m, np.asarray(f.cov_enu_m2), STATUS_FIX,
                              COV_DIAGONAL_KNOWN)
            obs = kf.observations
            stage.add_keyframe(kf.stamp_ns, obs['track_id'], np.column_stack([obs['u'], obs['v']]))
            b.time('adjustment_stage', stage.drain)
            # PnP floor: 300 of the keyframe's points on a plane seen from above.
            uv = np.column_stack([obs['u'], obs['v']])[:300].astype(np.float64)
            if len(uv) >= 6:
                X = np.column_stack([uv / 100.0, np.zeros(len(uv))])
                floors.time('pose_resection', cv2.solvePnPRansac, X, uv, cam.K, None)
            del image, reduced
    for kf in trk.flush():
        keyframes.append(kf)
    stage.finish()
    b.cpu['adjustment_other'] = b.cpu['adjustment_stage'] - b.cpu['pose_resection'] - b.cpu['window_adjustment']
    b.calls['adjustment_other'] = b.calls['adjustment_stage']
    floors.cpu['window_adjustment'] = min(window_calls) if window_calls else float('nan')
    floors.calls['window_adjustment'] = 1 if window_calls else 0
    poses = {s: T for s, (T, _) in stage.out.pose_by_stamp.items()}

    # Stereo, fusion, tiles, cloud messages: consecutive posed keyframes, as the stereo node plans them.
    posed = [k for k in keyframes if k.stamp_ns in poses]
    sparse = np.concatenate([c[0] for c in stage.out.clouds[-1:]]) if stage.out.clouds else np.zeros((0, 3))
    ground = float(np.median(sparse[:, 2])) if len(sparse) else 0.0
    tmp = tempfile.mkdtemp(prefix='stage_budget_')
    lat, lon, h = stage.out.georeferences[0][:3] if stage.out.georeferences else (0.0, 0.0, 0.0)
    mp = from_dict(MapParams, {'map_dir': tmp, 'use_origin_params': True, 'origin_lat_deg': lat,
                               'origin_lon_deg': lon, 'origin_h_m': h, 'coverage': False})
    mstage = MapStage(mp, out=MapOutputs())
    mstage.set_camera(lambda: cam)
    height = float(np.median([poses[k.stamp_ns][2, 3] for k in posed]) - ground) if posed else 100.0
    settings = gsd.derive(cam.width, cam.height, cam.fx, height)
    sp, _ = gsd.resolve(stereo.StereoParams(), settings)
    crit, _ = gsd.resolve(PairCriteria(), settings)
    cam_r = cam.scaled(1.0 / kf_reduction)
    sp_r = gsd.for_reduced_images(sp, kf_reduction)
    statuses = defaultdict(int)
    for i in range(1, len(posed)):
        a, c = posed[i - 1], posed[i]
        mstage.add_pose(a.stamp_ns, poses[a.stamp_ns])
        mstage.add_pose(c.stamp_ns, poses[c.stamp_ns])
        plan = plan_pairs(cam, poses[c.stamp_ns], {a.stamp_ns: poses[a.stamp_ns]}, ground, crit,
                          (sp.min_depth_m, sp.max_depth_m), sparse)
        if not plan.pairs:
            statuses['not_planned'] += 1
            continue
        rng = plan.pairs[0].depth_range_m
        ia, ic = by_stamp[a.stamp_ns], by_stamp[c.stamp_ns]
        fa, fc = cv2.imdecode(ia.data, cv2.IMREAD_COLOR), cv2.imdecode(ic.data, cv2.IMREAD_COLOR)
        res = b.time('stereo_pair_full_images', stereo.stereo_pair, cam, fa, poses[a.stamp_ns], fc,
                     poses[c.stamp_ns], sp, rng)
        del fa, fc
        ra = msgs.decode_reduced(ia.data, kf_reduction)[:cam_r.height, :cam_r.width]
        rc = msgs.decode_reduced(ic.data, kf_reduction)[:cam_r.height, :cam_r.width]
        res_r = b.time('stereo_pair_reduced_images', stereo.stereo_pair, cam_r, ra, poses[a.stamp_ns], rc,
                       poses[c.stamp_ns], sp_r, rng)
        statuses[res.status] += 1
        if not res.ok:
            continue
        statuses['points_full'] += int(res.cloud.size)
        statuses['points_reduced'] += int(res_r.cloud.size) if res_r.ok else 0
        h_, w_ = res.disparity.disparity_px.shape
        g1 = np.random.default_rng(0).integers(0, 255, (h_, w_), np.uint8)
        sgbm = stereo.make_sgbm(sp, res.min_disparity, res.num_disparities)
        floors.time('stereo_pair', sgbm.compute, g1, np.roll(g1, 3, axis=1))
        b.time('message_cloud', lambda r=res: serialize_message(msgs.dense_cloud_msg(r.cloud, c.stamp_ns, 'map')))
        b.time('fusion', mstage.add_cloud, 'map', c.stamp_ns, res.cloud)
        cell = mstage.cell_m
        floors.time('fusion', lambda r=res: np.bincount(
            (np.floor(r.cloud['x'] / cell).astype(np.int64) % 4096) * 4096
            + np.floor(r.cloud['y'] / cell).astype(np.int64) % 4096, weights=r.cloud['z'], minlength=1))
        b.time('tiles', mstage.stream_ortho, True)
        floors.time('tiles', cv2.imencode, '.png', np.zeros((256, 256, 4), np.uint8))
    mstage.close()
    n = len(photos)
    rows = []
    for name in sorted(set(b.cpu) | set(floors.cpu)):
        rows.append({'stage': name, 'calls': b.calls.get(name, 0), 'cpu_s': round(b.cpu.get(name, 0.0), 3),
                     'cpu_s_per_call': round(b.cpu[name] / b.calls[name], 4) if b.calls.get(name) else None,
                     'cpu_s_per_photo': round(b.cpu.get(name, 0.0) / n, 4) if name in b.cpu else None,
                     'floor_cpu_s_per_call': (round(floors.cpu[name] / floors.calls[name], 4)
                                              if floors.calls.get(name) else None)})
    summary = {'photos': n, 'keyframes': len(keyframes), 'posed': len(posed), 'reduction': kf_reduction,
               'camera': f'{cam.width}x{cam.height}', 'gsd': settings.as_dict(), 'pairs': dict(statuses),
               'targets_on_keyframes': n_kf_targets,
               'keyframes_with_a_surveyed_target_near': rings if regional else None}
    return rows, summary


ORDER = [('decode_full', 'decode, full BGR (per photo)'), ('decode_reduced_2', 'decode 1/2 colour (per photo)'),
         ('decode_reduced_4', 'decode 1/4 colour (per photo)'), ('decode', 'decode 1/8 grey (floor)'),
         ('tracking', 'features / KLT tracking (incl. its 1/8 decode)'),
         ('descriptor_matching', 'descriptor matching (SIFT at breaks)'),
         ('pose_resection', 'pose (resection)'), ('window_adjustment', 'window adjustment'),
         ('adjustment_other', 'rest of the adjustment stage'),
         ('decode_full_keyframe', 'keyframe full decode (before)'),
         ('targets_full_image', 'targets (ArUco) on the full image (before)'),
         ('targets_as_node', 'targets searched everywhere (grey decode, 1/4 candidates)'),
         ('targets_in_regions', 'targets searched where surveyed targets can be (regions)'),
         ('targets', 'targets floor (1/8 candidates)'),
         ('decode_keyframe_reduced', 'keyframe image at the map\'s reduction'),
         ('stereo_pair_full_images', 'stereo pair, full images (before)'),
         ('stereo_pair_reduced_images', 'stereo pair, reduced images'), ('stereo_pair', 'stereo floor (SGBM alone)'),
         ('fusion', 'fusion'), ('tiles', 'ortho tiles'),
         ('message_image_full_raw', 'image message, 20 MP raw (before)'),
         ('message_image_reduced_raw', 'image message, reduced raw'), ('messages', 'messages floor (1/8 image)'),
         ('message_features', 'features message'), ('message_cloud', 'pair cloud message')]


def table(rows: list[dict], summary: dict) -> str:
    by = {r['stage']: r for r in rows}
    lines = ['| stage | calls | CPU s / call | CPU s / photo | floor CPU s / call |', '|---|---|---|---|---|']
    for key, label in ORDER:
        r = by.get(key)
        if r is None:
            continue
        lines.append(f"| {label} | {r['calls']} | {r['cpu_s_per_call']} | {r['cpu_s_per_photo']} | "
                     f"{r['floor_cpu_s_per_call']} |")
    lines.append(f"\n{summary['photos']} photos ({summary['camera']}), {summary['keyframes']} keyframes, "
                 f"{summary['posed']} posed; keyframe image reduction {summary['reduction']}; pairs {summary['pairs']}; "
                 f"keyframes with a surveyed target near {summary.get('keyframes_with_a_surveyed_target_near')}")
    return '\n'.join(lines) + '\n'


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--photos', type=int, default=24, help='photos of toledo used (at most 42)')
    ap.add_argument('--out', default='', help='JSON lines file (default bench/results/stage_budget_<commit>.jsonl)')
    ap.add_argument('--table', default='', help='also write the markdown table here')
    a = ap.parse_args()
    commit = git('rev-parse', '--short', 'HEAD')
    clean = not git('status', '--porcelain', '--', 'photogram_ros', 'bench/stage_budget.py')
    load0 = os.getloadavg()
    t0 = time.time()
    rows, summary = run(a.photos)
    head = {'bench': 'stage_budget', 'commit': commit, 'clean_tree': clean, 'machine': machine_info(),
            'load_avg_before': [round(x, 2) for x in load0], 'load_avg_after': [round(x, 2) for x in os.getloadavg()],
            'wall_s': round(time.time() - t0, 1), **summary}
    out = Path(a.out or ROOT / 'bench' / 'results' / f'stage_budget_{commit}.jsonl')
    with out.open('w') as f:
        f.write(json.dumps(head) + '\n')
        for r in rows:
            f.write(json.dumps({'bench': 'stage_budget', 'commit': commit, **r}) + '\n')
    text = table(rows, summary)
    if a.table:
        Path(a.table).write_text(text)
    print(json.dumps(head))
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
