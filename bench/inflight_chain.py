"""The chain in flight: how many of the keyframes whose photos `triangulate` orients `replay` orients, on every
real photo and video set in ../shared/data and on its every-other-photo variant (half the forward overlap).

Sets (../shared/data, see its README):
- brighton: photos/brighton_beach/images (18 DJI photos, EXIF GPS);
- toledo: photos/toledo/images (42 DJI photos, EXIF GPS);
- seneca: photos/seneca_part/images (41 near-infrared photos of a fixed wing, EXIF GPS, roll and crab in turns);
- phantom3: video/phantom3_village (100 1080p keyframes of a video): `replay` gets the bag `import-frames`
  makes of it (the published trajectory plus a 3D fix's noise, 1.5 m / 3 m, as bench/real_surveys.py does);
  `triangulate` gets the frames as a photo folder with an OpenDroneMap geo.txt of the same kind of noisy
  positions and the config.cfg's pinhole camera as a calibration YAML (the frames carry no EXIF).
Variant `half`: every other photo (frame) of the set linked into a folder of its own (bench/real_surveys.py's
half_overlap_block; for phantom3 every other frame with its config.cfg and trajectory.txt).

Per set and variant, one JSON line: photos; `triangulate`'s oriented photos (poses.csv); `replay`'s keyframes
taken (report.json) and oriented (trajectory.csv, by stamp -> photo); replay-oriented keyframes among the
photos triangulate oriented; `share` = that over the keyframes whose photos triangulate oriented. replay
names only its oriented keyframes, so when it took fewer keyframes than photos (video) the denominator is
bounded by min(keyframes taken, photos triangulate oriented): `share` is then a lower bound
(`share_exact` false). Also the tracker's breaks / bridged / problems and the adjuster's not-oriented reasons
from report.json, wall times, the commit (bench/real_surveys.git_commit: '+modified' for a dirty tree), the
cores and the load average. Commands run one after the other, `replay` at rate 0 (no time pressure).
`--triangulate-from` takes triangulate's results from another run's folder (it does not use the tracker), or from
another run's result file (.jsonl): its counts, and the names of the photos it oriented when the row has them
(`triangulate_oriented_names`; or every photo when it oriented every one); else `share` is bounded (`share_bounds`,
`share` the lower bound, `share_exact` false).

`--fallback-cost`: instead, the tracker alone in-process on the photo sets, features_fallback off and on in the
same run (CPU per photo and its ratio, breaks bridged, keyframe pairs sharing tracks; `fallback_cost`).

    ROS_DOMAIN_ID=100 .venv/bin/python bench/inflight_chain.py [--only seneca,toledo] [--variants all,half]
        [--out /tmp/inflight_chain] [--results bench/results] [--fallback-cost]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'bench'))

import real_surveys as rs  # noqa: E402
from machine import machine_info  # noqa: E402

DATA = rs.DATA
SETS = {'brighton': DATA / 'photos' / 'brighton_beach' / 'images', 'toledo': DATA / 'photos' / 'toledo' / 'images',
        'seneca': DATA / 'photos' / 'seneca_part' / 'images', 'phantom3': DATA / 'video' / 'phantom3_village'}
VARIANTS = ('all', 'half')
PHANTOM3_NOISE_M = (1.5, 3.0)
TRIANGULATE_FROM: Path | None = None   # --triangulate-from
REPLAY_PARAMS: str | None = None       # --params


def clean_tree() -> bool:
    """No uncommitted change to the product code (photogram_ros/, config/)."""
    out = subprocess.run(['git', 'status', '--porcelain', 'photogram_ros', 'config'], cwd=ROOT, capture_output=True,
                         text=True).stdout
    return not out.strip()


# --- the phantom3 video as a photo folder and a bag -------------------------------------------------------


def video_set(dst: Path, every: int) -> Path:
    """phantom3_village's config.cfg, trajectory.txt and every `every`-th frame of rgb/ linked into `dst`."""
    src = SETS['phantom3']
    (dst / 'rgb').mkdir(parents=True, exist_ok=True)
    for name in ('config.cfg', 'trajectory.txt'):
        if not (dst / name).exists():
            (dst / name).symlink_to(src / name)
    for p in sorted((src / 'rgb').glob('*.jpg'))[::every]:
        if not (dst / 'rgb' / p.name).exists():
            (dst / 'rgb' / p.name).symlink_to(p)
    return dst


def video_photo_folder(dataset: Path, dst: Path, seed: int = 0) -> tuple[Path, Path]:
    """The frames of a Map2DFusion data set as a photo folder `dst` with a geo.txt (the trajectory plus a 3D
    fix's noise, ellipsoidal heights), and a calibration YAML from its config.cfg. Returns (folder, yaml)."""
    from photogram_ros.io.frame_import import read_map2dfusion_config, read_track
    camera, origin = read_map2dfusion_config(dataset / 'config.cfg')
    track = read_track(dataset / 'trajectory.txt')
    dst.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    sh, sv = PHANTOM3_NOISE_M
    noisy = track[:, 1:4] + rng.normal(0.0, [sh, sh, sv], (len(track), 3))
    lat, lon, h = (np.ravel(v) for v in origin.enu_to_geodetic(noisy))
    lines = ['EPSG:4326']
    for t, a, o, z in zip(track[:, 0], lat, lon, h):
        name = f'{t:.6f}.jpg'
        if (dataset / 'rgb' / name).exists():
            if not (dst / name).exists():
                (dst / name).symlink_to((dataset / 'rgb' / name).resolve())
            lines.append(f'{name} {o:.9f} {a:.9f} {z:.3f} 0 0 0 {sh:g} {sv:g}')
    (dst / 'geo.txt').write_text('\n'.join(lines) + '\n')
    yml = dst.parent / f'{dst.name}_camera.yaml'
    yml.write_text(json.dumps({
        'image_width': camera.width, 'image_height': camera.height, 'camera_name': 'phantom3',
        'camera_matrix': {'rows': 3, 'cols': 3, 'data': [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy,
                                                         0.0, 0.0, 1.0]},
        'distortion_model': 'plumb_bob', 'distortion_coefficients': {'rows': 1, 'cols': 5, 'data': [0.0] * 5}}))
    return dst, yml


def video_stamps(dataset: Path) -> dict[int, str]:
    """{stamp_ns: frame name} of a Map2DFusion data set's frames (named by their Unix time)."""
    return {int(round(float(p.stem) * 1e9)): p.name for p in (dataset / 'rgb').glob('*.jpg')}


# --- one set ------------------------------------------------------------------------------------------------


def _old_replay(row: dict) -> Path | None:
    """The trajectory.csv of an earlier run's replay whose oriented photos include every one triangulate oriented
    (its row says so), when it is still there; else None."""
    if row.get('replay_oriented_of_triangulated') != row.get('triangulate_oriented'):
        return None
    cmd = row.get('replay_command', '').split()
    if '--out' not in cmd:
        return None
    traj = Path(cmd[cmd.index('--out') + 1]) / 'trajectory.csv'
    return traj if traj.exists() else None


def tracker_and_adjuster(report: dict) -> dict:
    """What the tracker and the adjuster said (report.json): breaks, bridged, lost-tracking problems,
    not-oriented reasons."""
    nodes = report.get('nodes', {})
    tv = nodes.get('/tracker_node', {}).get('values', {})
    probs = nodes.get('/tracker_node', {}).get('problems', [])
    return {'tracker_breaks': tv.get('breaks'), 'tracker_bridged': tv.get('bridged'),
            'tracker_cross_strip_revisits': tv.get('cross_strip_revisits'),
            'tracker_cross_strip_stored': tv.get('cross_strip_stored'),
            'tracking_lost': sum('tracking lost' in str(p[-1]) for p in probs),
            'tracker_process_ms': tv.get('process_ms'),
            'not_oriented_by_reason': report.get('keyframes_not_oriented_by_reason'),
            'segments_joined_keyframes': nodes.get('/bundle_node', {}).get('values', {}).get(
                'keyframes_joined_from_a_segment'),
            'keyframes_oriented_in_flight': report.get('keyframes_oriented_in_flight')}


def run_set(name: str, variant: str, out: Path, timeout_s: float) -> dict:
    every = 2 if variant == 'half' else 1
    tag = f'{name}_{variant}'
    work = out / tag
    if not rs.REMEASURE:
        shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    row = {'set': name, 'variant': variant}
    if name == 'phantom3':
        dataset = video_set(work / 'data', every)
        folder, yml = video_photo_folder(dataset, work / 'photos')
        tri_cmd = ['triangulate', str(folder), '--out', str(work / 'triangulate'), '--camera', str(yml), '--quiet']
        bag = work / 'bag'
        imp = ['import-frames', str(dataset), '--out', str(bag), '--noise-h-m', str(PHANTOM3_NOISE_M[0]),
               '--noise-v-m', str(PHANTOM3_NOISE_M[1])]
        r_imp = rs.run_command(imp, work / 'import.log', timeout_s)
        rep_cmd = ['replay', str(bag), '--out', str(work / 'replay'), '--quiet'] + (
            ['--params', REPLAY_PARAMS] if REPLAY_PARAMS else [])
        names = video_stamps(dataset)
        photos = len(names)
        row['import_exit'] = r_imp['exit']
    else:
        folder = SETS[name]
        if every > 1:
            folder = work / 'photos'
            rs.half_overlap_block(SETS[name], folder)
        tri_cmd = ['triangulate', str(folder), '--out', str(work / 'triangulate'), '--quiet']
        rep_cmd = ['replay', str(folder), '--out', str(work / 'replay'), '--quiet'] + (
            ['--params', REPLAY_PARAMS] if REPLAY_PARAMS else [])
        names = rs.photo_stamps(folder)
        photos = rs.photo_count(folder)
    tri_known = None   # triangulate's oriented photos from a result file: (count, names or None)
    if TRIANGULATE_FROM is None:
        r_tri = rs.run_command(tri_cmd, work / 'triangulate.log', timeout_s)
        tri_poses = work / 'triangulate' / 'poses.csv'
    elif TRIANGULATE_FROM.suffix == '.jsonl':
        # triangulate's counts of an earlier run of this bench (the same photos), from its result file.
        old = [json.loads(ln) for ln in TRIANGULATE_FROM.read_text().splitlines() if ln.strip()]
        old = [o for o in old if o.get('set') == name and o.get('variant') == variant]
        if not old or old[-1].get('triangulate_oriented') is None:
            raise SystemExit(f'{TRIANGULATE_FROM} has no triangulate row for {tag}')
        o = old[-1]
        r_tri = {'exit': o.get('triangulate_exit'), 'wall_s': o.get('triangulate_wall_s'), 'from': str(TRIANGULATE_FROM)}
        tri_known = (int(o['triangulate_oriented']), o.get('triangulate_oriented_names'), _old_replay(o))
        tri_poses = None
    else:
        # triangulate's outputs of an earlier run of this bench (the same photos; triangulate does not use the
        # tracker): waited for while that run is still going.
        done = TRIANGULATE_FROM / tag / 'triangulate.run.json'
        t0 = time.monotonic()
        while not done.exists() and time.monotonic() - t0 < timeout_s:
            time.sleep(10)
        r_tri = json.loads(done.read_text()) if done.exists() else {'exit': None, 'wall_s': None}
        r_tri['from'] = str(TRIANGULATE_FROM / tag)
        tri_poses = TRIANGULATE_FROM / tag / 'triangulate' / 'poses.csv'
    r_rep = rs.run_command(rep_cmd, work / 'replay.log', timeout_s)
    traj = work / 'replay' / 'trajectory.csv'
    rep = {names.get(p.get('stamp_ns'), n) for n, p in rs.read_poses(traj).items()} if traj.exists() else set()
    rj = work / 'replay' / 'report.json'
    report = json.loads(rj.read_text()) if rj.exists() else {}
    taken = int(report.get('keyframes_taken') or 0)
    exact = taken == photos
    bounds = rep_of = None
    if tri_known is None:
        tri = set(rs.read_poses(tri_poses)) if tri_poses.exists() else set()
        n_tri = len(tri)
    else:
        n_tri, tri_names, old_rep = tri_known
        tri = set(tri_names) if tri_names is not None else (set(names.values()) if n_tri == photos else None)
        if tri is None and old_rep is not None:
            row['share_inferred_from'] = str(old_rep)
            old_rep = {names.get(p.get('stamp_ns'), n) for n, p in rs.read_poses(old_rep).items()}
            row['earlier_replay_oriented_not_now'] = sorted(old_rep - rep)
            if rep >= old_rep:
                # The earlier run's replay oriented every photo triangulate oriented, and this one every
                # photo that one did: so every photo triangulate oriented too.
                rep_of = n_tri
    if tri is not None:
        both = len(rep & tri)
    elif rep_of is not None:
        both = rep_of
    else:
        # Only triangulate's count is known: replay's oriented photos among its, at least those beyond the
        # photos it did not orient, at most all.
        bounds = (max(0, len(rep) - (photos - n_tri)), min(len(rep), n_tri))
        both, exact = bounds[0], False
    denom = n_tri if taken == photos else min(taken, n_tri)
    row.update({'photos': photos, 'triangulate_oriented': n_tri, 'replay_keyframes': taken,
                'replay_oriented': len(rep), 'replay_oriented_of_triangulated': both,
                'keyframes_triangulated': denom, 'share': round(both / denom, 4) if denom else None,
                'share_exact': exact, 'triangulate_exit': r_tri['exit'], 'replay_exit': r_rep['exit'],
                'triangulate_wall_s': r_tri['wall_s'], 'replay_wall_s': r_rep['wall_s'],
                'replay_last_line': r_rep.get('last_line', '')[:300],
                'triangulate_command': 'photogram-ros ' + ' '.join(tri_cmd),
                'replay_command': 'photogram-ros ' + ' '.join(rep_cmd),
                'triangulate_from': r_tri.get('from'),
                'triangulate_oriented_names': sorted(tri) if tri is not None else None})
    if bounds is not None:
        row['share_bounds'] = [round(b / denom, 4) if denom else None for b in bounds]
    row.update(tracker_and_adjuster(report))
    return row


def fallback_cost(name: str, variant: str) -> dict:
    """The tracker alone (in-process, frame by frame as tracker_node feeds it: EXIF fixes, the photos' JPEG bytes)
    on a photo set, features_fallback off then on, each twice (the faster run counts): CPU s in process() per
    photo and their ratio (on / off, same run), breaks bridged, by the other image, and the keyframe pairs sharing
    a track."""
    from photogram_ros.core.tracker import EncodedImage, Tracker, TrackerParams
    from photogram_ros.io.image_source import FolderSource, read_exif_gps
    src = FolderSource(SETS[name])
    cam = src.exif_intrinsics().camera
    entries = src.entries[::2] if variant == 'half' else src.entries
    data = [(read_exif_gps(p).gnss_fix(t, 5.0, 10.0), Path(p).read_bytes(), t) for p, t in entries]
    row = {'bench': 'inflight_chain_fallback_cost', 'set': name, 'variant': variant, 'photos': len(data)}
    for on in (False, True):
        best = None
        for _ in range(2):
            tr = Tracker(cam, TrackerParams(features_fallback=on))
            kfs = []
            for fix, jpeg, t in data:
                tr.add_fix(fix)
                kfs += tr.process(EncodedImage(jpeg), t)
            kfs += tr.flush()
            best = tr if best is None or tr.stats.process_s < best.stats.process_s else best
        ids = [set(k.observations['track_id'].tolist()) for k in kfs]
        linked = sum(1 for i in range(len(ids)) for j in range(i + 1, len(ids)) if ids[i] & ids[j])
        key = 'on' if on else 'off'
        row.update({f'process_s_per_photo_{key}': round(best.stats.process_s / len(data), 4),
                    f'bridged_{key}': best.stats.bridged, f'breaks_{key}': best.stats.breaks,
                    f'other_bridged_{key}': best.other_image.bridged, f'keyframes_{key}': len(kfs),
                    f'keyframe_pairs_sharing_tracks_{key}': linked})
    row['process_ratio_on_off'] = round(row['process_s_per_photo_on'] / row['process_s_per_photo_off'], 3)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--only', default=','.join(SETS), help='sets, comma separated')
    ap.add_argument('--variants', default=','.join(VARIANTS), help='variants, comma separated (all, half)')
    ap.add_argument('--out', default='/tmp/inflight_chain', help='work folder (command outputs and logs)')
    ap.add_argument('--results', default=str(ROOT / 'bench' / 'results'), help='folder of the JSON-lines file')
    ap.add_argument('--timeout-s', type=float, default=1800.0, help='per command')
    ap.add_argument('--triangulate-from', default=None,
                    help="another run's --out: take triangulate's results from there (waiting for them), or its "
                         'result file (.jsonl: the counts, and the names when it has them), instead of running it '
                         'again (triangulate does not use the tracker)')
    ap.add_argument('--params', default=None, help="replay's ROS 2 parameter file (default: the package's)")
    ap.add_argument('--remeasure', action='store_true', help='measure the outputs already in --out again')
    ap.add_argument('--fallback-cost', action='store_true',
                    help="instead: the tracker's CPU per photo with features_fallback on against off, in-process, "
                         'on the photo sets (`fallback_cost`); results in inflight_chain_fallback_cost_<commit>.jsonl')
    a = ap.parse_args(argv)
    rs.REMEASURE = a.remeasure
    global TRIANGULATE_FROM, REPLAY_PARAMS
    TRIANGULATE_FROM = Path(a.triangulate_from).resolve() if a.triangulate_from else None
    REPLAY_PARAMS = str(Path(a.params).resolve()) if a.params else None
    sets = [s for s in a.only.split(',') if s]
    variants = [v for v in a.variants.split(',') if v]
    bad = [s for s in sets if s not in SETS] + [v for v in variants if v not in VARIANTS]
    if bad:
        ap.error(f'unknown {bad}: sets {list(SETS)}, variants {list(VARIANTS)}')
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    commit = rs.git_commit()
    short = commit.split()[0].replace('+modified', '')
    results = Path(a.results) / f"inflight_chain{'_fallback_cost' if a.fallback_cost else ''}_{short}.jsonl"
    results.parent.mkdir(parents=True, exist_ok=True)
    head = {'bench': 'inflight_chain_fallback_cost' if a.fallback_cost else 'inflight_chain', 'commit': commit, 'clean_tree': clean_tree(), 'cores': os.cpu_count(),
            'replay_params': REPLAY_PARAMS, 'triangulate_from': str(TRIANGULATE_FROM) if TRIANGULATE_FROM else None,
            'machine': machine_info(), 'load_avg_before': [round(x, 2) for x in os.getloadavg()],
            'started_utc': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}
    with open(results, 'a') as fh:
        fh.write(json.dumps(head) + '\n')
    for s in sets:
        for v in variants:
            load0 = os.getloadavg()
            if a.fallback_cost and s == 'phantom3':
                continue   # video: no breaks, the fallback only at the first keyframe
            try:
                row = fallback_cost(s, v) if a.fallback_cost else run_set(s, v, out, a.timeout_s)
            except subprocess.TimeoutExpired as exc:
                row = {'set': s, 'variant': v, 'error': f'timeout after {exc.timeout} s'}
            row.update({'commit': commit, 'clean_tree': head['clean_tree'], 'cores': os.cpu_count(),
                        'load_avg_before': [round(x, 2) for x in load0],
                        'load_avg_after': [round(x, 2) for x in os.getloadavg()]})
            with open(results, 'a') as fh:
                fh.write(json.dumps(row, default=str) + '\n')
            if a.fallback_cost:
                print(f'{s} {v}: {row}', flush=True)
                continue
            print(f"{s} {v}: triangulate {row.get('triangulate_oriented')}/{row.get('photos')}, replay "
                  f"{row.get('replay_oriented')}/{row.get('replay_keyframes')} keyframes, "
                  f"{row.get('replay_oriented_of_triangulated')}/{row.get('keyframes_triangulated')} of "
                  f"triangulate's = {row.get('share')} ({'exact' if row.get('share_exact') else 'lower bound'}); "
                  f"tracking lost {row.get('tracking_lost')}", flush=True)
    print(f'results: {results}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
