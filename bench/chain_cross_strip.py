"""Tie points across strips for keyframes KLT carried (core/cross_strip.py): parts of the block and tracker CPU.

The flight: the simulator's 20 MP survey of bench/inflight_20mp.py (`--flight sim`: 6 lines of 350 m at 80 m,
a photo a second, 317 photos upscaled to 5472 x 3648; its cache is shared, built by its build_sim_flight),
whose consecutive photos overlap enough for KLT: its keyframes are KLT carried, and without SIFT features
a later strip cannot be matched with them. Each photo's EXIF GPS is its fix (5 m horizontal, 10 m vertical
sigma: the camera node's exif_sigma_m).

Both configurations run in the same process, one after the other, on the same photos: `main` (the
cross-strip logic off: cross_strip_store_every=0, cross_strip_min_back=0, what main does) and `cross` (the
defaults, or --set tracker.X=V). Each feeds core/tracker.Tracker (the still-compressed photo, as the tracker
node does) and stages/adjustment.AdjustmentStage keyframe by keyframe (no ROS), and reports: keyframes,
the tracker's breaks and bridged breaks, keyframes given SIFT features by the cross-strip logic (stored /
revisits), descriptor pairs tried and verified, the tracker's CPU (time.process_time around
Tracker.process: per photo and per keyframe, and the ratio to `main`), the adjuster's segments: how many
joined the block and through what (tie points 'ties', manual tie points 'mtp', 'gnss'), keyframes oriented,
the chain's bytes, and the block's overlap graph after the final adjustment (core/block_check.tie_evidence:
cameras joined by >= 5 shared tie points; `block_parts` > 1: parts joined through their GNSS only).

    .venv/bin/python bench/chain_cross_strip.py [--photos 317] [--set cross_strip_store_every=2]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
sys.path.insert(0, str(ROOT))
os.environ.setdefault('ROS_DOMAIN_ID', '101')

import numpy as np  # noqa: E402
from machine import ResultWriter  # noqa: E402

OFF = {'cross_strip_store_every': 0, 'cross_strip_min_back': 0}
CONFIGS = {'main': OFF, 'cross': {}, 'all_klt_keyframes': {**OFF, 'chain_klt_keyframes': True}}
EXIF_SIGMA_M = 5.0


def photos(n: int):
    """[(path, stamp_ns, fix)] of the simulated 20 MP flight's first n photos, and its camera."""
    from inflight_20mp import build_sim_flight

    from photogram_ros.core.camera import load_calibration
    from photogram_ros.io.image_source import FolderSource, read_exif_gps
    folder, calib, _ = build_sim_flight(n)
    out = []
    for path, stamp in FolderSource(folder).entries[:n]:
        gps = read_exif_gps(path)
        out.append((path, stamp, gps.gnss_fix(stamp, EXIF_SIGMA_M, 2 * EXIF_SIGMA_M) if gps else None))
    return out, load_calibration(calib)


def lines_of(positions: np.ndarray, max_deg: float = 15.0) -> np.ndarray:
    """Per position (N, 3 local m, in flight order) its survey line (0, 1, ...: runs along the first line's
    axis, either way) or -1 in a turn (travel more than max_deg off the axis)."""
    d = np.gradient(positions[:, :2], axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    axis = np.median(d[:5], axis=0)
    axis /= np.linalg.norm(axis)
    c = d @ axis
    on = np.abs(c) >= np.cos(np.radians(max_deg))
    out = np.full(len(positions), -1)
    line, sign = -1, 0.0
    for i in range(len(positions)):
        if on[i]:
            if np.sign(c[i]) != sign:
                line, sign = line + 1, np.sign(c[i])
            out[i] = line
    return out


def enu(fixes) -> np.ndarray:
    from photogram_ros.core.geodesy import LocalFrame
    f0 = fixes[0]
    frame = LocalFrame(f0.lat_deg, f0.lon_deg, f0.h_m)
    return np.array([frame.geodetic_to_enu(f.lat_deg, f.lon_deg, f.h_m) for f in fixes]).reshape(-1, 3)


def line_ties(at, kfs, min_shared: int = 5) -> dict:
    """The tracker's tie points (track ids the adjuster triangulated) between keyframes of different survey
    lines: keyframe pairs of two lines sharing >= min_shared, adjacent line pairs tied directly (not through a
    turn), and the parts of the overlap graph of the keyframes on the lines alone (turn keyframes left out: the
    parts a break in every turn would leave, joined only through their GNSS)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    kfs = [k for k in kfs if k.fix is not None]
    line = lines_of(enu([k.fix for k in kfs]))
    rows, cols = [], []
    for i, k in enumerate(kfs):
        ids = k.observations['track_id'].astype(np.int64)
        ids = ids[at.block.has_points(ids)] if at is not None else ids[:0]
        rows.append(np.full(len(ids), i))
        cols.append(ids)
    r, t = np.concatenate(rows), np.concatenate(cols)
    _, col = np.unique(t, return_inverse=True)
    A = coo_matrix((np.ones(len(r)), (r, col)), shape=(len(kfs), int(col.max()) + 1 if len(col) else 0)).tocsr()
    S = (A @ A.T).tocoo()
    strong = (S.data >= min_shared) & (S.row < S.col)
    a, b = S.row[strong], S.col[strong]
    la, lb = line[a], line[b]
    cross = (la >= 0) & (lb >= 0) & (la != lb)
    tied = sorted({(int(min(x, y)), int(max(x, y))) for x, y in zip(la[cross], lb[cross])})
    n_lines = int(line.max()) + 1
    on = np.flatnonzero(line >= 0)
    keep = (line[a] >= 0) & (line[b] >= 0)
    G = coo_matrix((np.ones(int(keep.sum())), (a[keep], b[keep])), shape=(len(kfs), len(kfs)))
    _, labels = connected_components(G, directed=False)
    return {'lines': n_lines, 'line_keyframes': int(len(on)),
            'cross_line_keyframe_pairs': int(cross.sum()),
            'adjacent_lines_tied': sum((x, x + 1) in tied for x in range(n_lines - 1)),
            'line_pairs_tied': [list(x) for x in tied],
            'parts_without_turns': int(len(np.unique(labels[on])))}


def turn_photos(flight) -> set:
    """Indices of the photos taken in the turns (lines_of on their fixes)."""
    line = lines_of(enu([f for _, _, f in flight]))
    return set(np.flatnonzero(line < 0).tolist())


def run(config: str, tracker_values: dict, flight, cam) -> dict:
    from photogram_ros.core.gnss_fix import COV_DIAGONAL_KNOWN, STATUS_FIX
    from photogram_ros.core.tracker import EncodedImage, Tracker, TrackerParams
    from photogram_ros.params import from_dict
    from photogram_ros.stages.adjustment import AdjustmentParams, AdjustmentStage, DiagnosticsLog, RecordedOutputs

    trk = Tracker(cam, from_dict(TrackerParams, tracker_values))
    stage = AdjustmentStage(from_dict(AdjustmentParams, {}), DiagnosticsLog(), RecordedOutputs())
    stage.set_camera(cam)
    cpu = 0.0
    n_kf = 0
    made = []
    t_wall = time.perf_counter()

    def feed(kfs):
        nonlocal n_kf
        for kf in kfs:
            n_kf += 1
            made.append(kf)
            f = kf.fix
            if f is not None:
                stage.add_fix(kf.stamp_ns, f.lat_deg, f.lon_deg, f.h_m, np.asarray(f.cov_enu_m2), STATUS_FIX,
                              COV_DIAGONAL_KNOWN)
            obs = kf.observations
            stage.add_keyframe(kf.stamp_ns, obs['track_id'], np.column_stack([obs['u'], obs['v']]))
            stage.drain()

    for path, stamp, fix in flight:
        enc = EncodedImage(np.fromfile(str(path), np.uint8))
        if fix is not None:
            trk.add_fix(fix)
        t0 = time.process_time()
        kfs = trk.process(enc, stamp)
        cpu += time.process_time() - t0
        feed(kfs)
    t0 = time.process_time()
    kfs = trk.flush()
    cpu += time.process_time() - t0
    feed(kfs)
    stage.finish()
    at = stage.at
    from photogram_ros.core.block_check import tie_evidence
    tie = tie_evidence(at) if at is not None else {'component': [], 'parts': 0}
    comp = np.asarray(tie['component'])
    joins = at.segment_joins if at is not None else []
    through = {}
    for j in joins:
        through[j['through']] = through.get(j['through'], 0) + 1
    s = trk.stats
    return {'config': config, 'tracker_set': {k: v for k, v in tracker_values.items()},
            'photos': len(flight), 'keyframes': n_kf, 'breaks': s.breaks, 'bridged': s.bridged,
            'cross_strip_stored': trk.cross.stored, 'cross_strip_revisits': trk.cross.revisits,
            'chain_entries': len(trk.chain) + trk.chain.dropped, 'chain_pairs': s.chain_pairs,
            'chain_verified': s.chain_verified, 'chain_bytes': s.chain_bytes,
            'tracker_cpu_s': round(cpu, 2), 'tracker_cpu_s_per_photo': round(cpu / max(len(flight), 1), 4),
            'tracker_cpu_s_per_keyframe': round(cpu / max(n_kf, 1), 4),
            'segments_joined': len(joins), 'segments_joined_through': through,
            'segment_joins': [{'keyframes': j.get('keyframes'), 'through': j.get('through'),
                               'ties': j.get('ties'), 'shared_points': j.get('shared_points')} for j in joins],
            'keyframes_oriented': len(stage.out.pose_by_stamp),
            'block_parts': tie['parts'], 'block_part_cameras': [int(np.sum(comp == c)) for c in range(tie['parts'])],
            **line_ties(at, made),
            'ray_angle_deg': tie.get('ray_angle_deg'), 'reprojection_px': tie.get('reprojection_px'),
            'wall_s': round(time.perf_counter() - t_wall, 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--photos', type=int, default=317)
    ap.add_argument('--set', action='append', default=[], help='tracker.X=V (or X=V) for the cross configuration')
    ap.add_argument('--configs', default='main,cross,all_klt_keyframes')
    ap.add_argument('--variants', default='every_photo,turn_gap',
                    help='every_photo: the flight as taken; turn_gap: the photos taken in the turns left out (KLT '
                         'breaks at every turn, as when a loaded tracker drops them)')
    ap.add_argument('--out', default='')
    a = ap.parse_args()
    import yaml
    cross = {}
    for item in a.set:
        k, v = item.split('=', 1)
        cross[k.removeprefix('tracker.')] = yaml.safe_load(v)
    flight, cam = photos(a.photos)
    from machine import tree_state
    out = a.out or str(ROOT / 'bench' / 'results' / f'chain_cross_strip_{tree_state()["commit"][:7]}.jsonl')
    with ResultWriter(out, 'chain_cross_strip', modules=['photogram_ros/core/cross_strip.py',
                                                          'photogram_ros/core/tracker.py']) as w:
        for variant in a.variants.split(','):
            turns = turn_photos(flight) if variant == 'turn_gap' else set()
            photos_run = [p for i, p in enumerate(flight) if i not in turns]
            rows = {}
            for config in a.configs.split(','):
                values = {**CONFIGS[config], **(cross if config == 'cross' else {})}
                row = run(config, values, photos_run, cam)
                row['flight'] = f'sim20mp_{a.photos}'
                row['variant'] = variant
                row['photos_left_out'] = len(turns)
                if 'main' in rows and config != 'main':
                    base = rows['main']
                    row['tracker_cpu_ratio_to_main'] = round(row['tracker_cpu_s'] / max(base['tracker_cpu_s'], 1e-9), 3)
                    row['tracker_cpu_per_keyframe_ratio_to_main'] = round(
                        row['tracker_cpu_s_per_keyframe'] / max(base['tracker_cpu_s_per_keyframe'], 1e-9), 3)
                rows[config] = row
                w.write(row)
                print({k: v for k, v in row.items() if k not in ('segment_joins', 'line_pairs_tied')}, flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
