"""Where the in-flight poses are against the final adjustment's and against `triangulate`'s, on every real photo set.

Issue #43: on seneca_part the final adjustment at the end of the flight moved the keyframes fused into the live map
by metres and degrees. This bench flies each real photo set in ../shared/data/photos (brighton_beach, toledo,
seneca_part) through the in-flight chain without ROS: core/tracker.py's Tracker, then core/incremental.py's
IncrementalAT keyframe by keyframe (what tracker_node and bundle_node chain in `replay`), with the options `replay`
gives a photo folder (tracker keyframe_overlap 0.8 and features_fallback, bundle window_size 10,
final_self_calibration auto, pass_self_calibration k1,k2, growth_ratio 1.5; EXIF GPS sigmas 5 m / 2 m). It records
each keyframe's pose after every keyframe of the flight and after the end-of-flight adjustment
(`retry_unregistered`, `full_adjustment`), and measures:
- keyframes, oriented at the flight's end (before the end-of-flight adjustment) and at the end;
- the in-flight poses against the final ones and against triangulate's (both georeferenced: no transform; camera
  centre in m, rotation in deg, p50/p95/max): `first` (a keyframe's first pose, provisional ones included),
  `first_final` (its first pose after the georeference was final: what stereo fuses), `last_in_flight`; and the
  final poses against triangulate's;
- the full adjustments the off-GNSS test asked for (core/incremental.py off_gnss_sigma), the chain's wall time.
Old code against new in the same session: the old a clean checkout (`git worktree add /tmp/georef_base 11db4eb`, a
.venv link), run as a child with PYTHONPATH to it. triangulate's poses (the reference) come from the old code's
`triangulate` of each set, run once and cached in --cache.

    .venv/bin/python bench/georef_inflight.py [--base /tmp/georef_base] [--cache /tmp/georef_cache]
        [--only seneca_part]

Rows: bench/results/georef_inflight_<commit>.jsonl, one per set and code (old / new).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'bench'))
DATA = ROOT.parent / 'shared' / 'data' / 'photos'
SETS = ('brighton_beach', 'toledo', 'seneca_part')
MODULES = ['photogram_ros/core', 'photogram_ros/io/image_source.py']


def fly(folder: Path, out: Path, off_gnss_sigma: float | None = None) -> None:
    """The child: the in-flight chain over the photos of `folder` with the code on PYTHONPATH; each keyframe's pose
    history as JSON in `out`."""
    from photogram_ros.core.incremental import AUTO_CANDIDATES, PASS_GROWTH_RATIO, IncrementalAT, IncrementalOptions
    from photogram_ros.core.incremental import KeyframeRecord
    from photogram_ros.core.tracker import Tracker, TrackerParams
    from photogram_ros.io.image_source import FolderSource

    src = FolderSource(str(folder))
    camera = src.exif_intrinsics().camera
    photos = list(src)
    names = {p.stamp_ns: Path(p.path).name for p in photos}
    at = IncrementalAT(camera, IncrementalOptions(window_size=10, final_self_calibration='auto',
                                                  pass_self_calibration=','.join(AUTO_CANDIDATES),
                                                  growth_ratio=PASS_GROWTH_RATIO,
                                                  **({} if off_gnss_sigma is None else
                                                     {'off_gnss_sigma': off_gnss_sigma})))
    tr = Tracker(camera, TrackerParams(keyframe_overlap=0.8, features_fallback=True))
    hist: dict[int, list] = {}
    step = 0

    def snap():
        for k in at.registered:
            kf = at.kfs[k]
            h = hist.setdefault(kf.stamp_ns, [])
            if not h or not np.allclose(h[-1][2], kf.map_T_cam, atol=1e-9):
                h.append((step, bool(at.georef_provisional), kf.map_T_cam.tolist()))

    def adjust(new):
        nonlocal step
        for k in new:
            at.add_keyframe(KeyframeRecord(k.stamp_ns, k.observations['track_id'].astype(np.int64),
                                           np.column_stack([k.observations['u'], k.observations['v']]), k.fix))
            step += 1
            if at.georeferenced:
                snap()

    t0 = time.perf_counter()
    for p in photos:
        tr.add_fix(p.gps.gnss_fix(p.stamp_ns, 5.0, 2.0))
        adjust(tr.process(p.image, p.stamp_ns))
    adjust(tr.flush())
    flight_end, oriented_in_flight = step, len(at.registered)
    at.retry_unregistered()
    at.full_adjustment()
    step += 1
    snap()
    o = at.origin
    out.write_text(json.dumps({
        'flight_end': flight_end, 'keyframes': len(at.kfs), 'oriented_in_flight': oriented_in_flight,
        'oriented_at_end': len(at.registered), 'wall_s': round(time.perf_counter() - t0, 1),
        'off_gnss_adjustments': getattr(at, 'off_gnss_adjustments', None),
        'camera_dist': list(at.camera.dist), 'origin': [o.lat_deg, o.lon_deg, o.h_m],
        'names': {str(s): n for s, n in names.items()}, 'hist': {str(s): h for s, h in hist.items()}}))


def triangulate_poses(code: Path, folder: Path, cache: Path, env: dict) -> Path:
    """poses.csv of `triangulate` (the code at `code`) of the photos in `folder`, run once into `cache`."""
    dst = cache / f'tri_{folder.parent.name}'
    if not (dst / 'poses.csv').exists():
        log = cache / f'tri_{folder.parent.name}.log'
        with open(log, 'w') as fh:
            subprocess.run([str(code / '.venv' / 'bin' / 'photogram-ros'), 'triangulate', str(folder), '--out', str(dst)],
                           cwd=code, env={**env, 'PYTHONPATH': str(code)}, stdout=fh, stderr=subprocess.STDOUT,
                           check=True, timeout=3600)
    return dst / 'poses.csv'


def read_reference(path: Path, origin) -> dict:
    """{image: (centre in the map of `origin`, map_R_cam)} from a poses.csv (omega-phi-kappa in ENU)."""
    from photogram_ros.core.rotations import map_R_cam_from_opk
    ref = {}
    with open(path, newline='') as fh:
        for r in csv.DictReader(fh):
            h = r['h_m'] if 'h_m' in r else r['h_ellipsoid_m']
            C = np.asarray(origin.geodetic_to_enu(float(r['lat_deg']), float(r['lon_deg']), float(h)), float).reshape(3)
            R = map_R_cam_from_opk(*np.radians([float(r['omega_deg']), float(r['phi_deg']), float(r['kappa_deg'])]))
            ref[r['image']] = (C, R)
    return ref


def _rot_deg(A, B) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(A.T @ B) - 1.0) / 2.0, -1.0, 1.0))))


def _stats(v: list, digits: int = 2) -> dict:
    if not v:
        return {'n': 0, 'p50': None, 'p95': None, 'max': None}
    return {'n': len(v), 'p50': round(float(np.percentile(v, 50)), digits),
            'p95': round(float(np.percentile(v, 95)), digits), 'max': round(float(np.max(v)), digits)}


def summarise(doc: dict, ref: dict) -> dict:
    """The figures of one flight (`fly`'s JSON) against its final poses and triangulate's `ref`."""
    fe = doc['flight_end']
    picks = {'first': lambda h: h[0], 'first_final': lambda h: next((x for x in h if not x[1] and x[0] <= fe), None),
             'last_in_flight': lambda h: ([x for x in h if x[0] <= fe] or [None])[-1], 'final': lambda h: h[-1]}
    out = {}
    for name, pick in picks.items():
        vs_final_m, vs_final_deg, vs_tri_m, vs_tri_deg = [], [], [], []
        for s, h in doc['hist'].items():
            x, fin = pick(h), h[-1]
            if x is None:
                continue
            T, F = np.array(x[2]), np.array(fin[2])
            if name != 'final':
                vs_final_m.append(float(np.linalg.norm(T[:3, 3] - F[:3, 3])))
                vs_final_deg.append(_rot_deg(T[:3, :3], F[:3, :3]))
            r = ref.get(doc['names'][s])
            if r is not None:
                vs_tri_m.append(float(np.linalg.norm(T[:3, 3] - r[0])))
                vs_tri_deg.append(_rot_deg(T[:3, :3], r[1]))
        if name != 'final':
            out[f'{name}_vs_final'] = {'centre_m': _stats(vs_final_m), 'rotation_deg': _stats(vs_final_deg)}
        out[f'{name}_vs_triangulate'] = {'centre_m': _stats(vs_tri_m), 'rotation_deg': _stats(vs_tri_deg)}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--base', default='/tmp/georef_base', help='clean checkout of the old code (with a .venv link)')
    ap.add_argument('--cache', default='/tmp/georef_cache', help='triangulate outputs and the flights\' JSON')
    ap.add_argument('--only', default=','.join(SETS), help='comma-separated photo sets')
    ap.add_argument('--off-gnss-sigma', type=float, default=None,
                    help='the new code\'s off_gnss_sigma (default: its own default); the old code keeps its own')
    ap.add_argument('--child', nargs=2, metavar=('FOLDER', 'OUT'), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        fly(Path(a.child[0]), Path(a.child[1]), a.off_gnss_sigma)
        return 0
    from machine import ResultWriter, tree_state

    from photogram_ros.core.geodesy import LocalFrame
    cache, base = Path(a.cache), Path(a.base)
    cache.mkdir(parents=True, exist_ok=True)
    commit = tree_state()['commit'][:7]
    w = ResultWriter(ROOT / 'bench' / 'results' / f'georef_inflight_{commit}.jsonl', 'georef_inflight', MODULES)
    env = {k: v for k, v in os.environ.items() if k != 'PYTHONPATH'}
    base_commit = subprocess.run(['git', 'rev-parse', 'HEAD'], cwd=base, capture_output=True, text=True).stdout.strip()
    for name in a.only.split(','):
        folder = DATA / name / 'images'
        tri = triangulate_poses(base, folder, cache, env)
        for code, root in (('old', base), ('new', ROOT)):
            sig = a.off_gnss_sigma if code == 'new' else None
            out = cache / f'fly_{name}_{code}_{commit if code == "new" else base_commit[:7]}_{sig}.json'
            log = out.with_suffix('.log')
            with open(log, 'w') as fh:
                subprocess.run([sys.executable, str(Path(__file__).resolve()), '--child', str(folder), str(out)]
                               + ([] if sig is None else ['--off-gnss-sigma', str(sig)]),
                               cwd=root, env={**env, 'PYTHONPATH': str(root)}, stdout=fh, stderr=subprocess.STDOUT,
                               check=True, timeout=3600)
            doc = json.loads(out.read_text())
            ref = read_reference(tri, LocalFrame(*doc['origin']))
            row = {'set': name, 'code': code, 'code_commit': base_commit if code == 'old' else commit,
                   'off_gnss_sigma': sig if sig is not None else 'default',
                   'reference': f'triangulate of {base_commit[:7]} ({tri})',
                   **{k: doc[k] for k in ('keyframes', 'oriented_in_flight', 'oriented_at_end', 'wall_s',
                                          'off_gnss_adjustments', 'camera_dist')},
                   **summarise(doc, ref)}
            w.write(row)
            f, ff = row['first_final_vs_final'], row['first_final_vs_triangulate']
            print(f'{name} {code}: {doc["oriented_in_flight"]}/{doc["keyframes"]} in flight, {doc["oriented_at_end"]} '
                  f'at the end; first final pose vs final {f["centre_m"]["p50"]}/{f["centre_m"]["p95"]} m, '
                  f'{f["rotation_deg"]["p50"]}/{f["rotation_deg"]["p95"]} deg; vs triangulate '
                  f'{ff["centre_m"]["p50"]}/{ff["centre_m"]["p95"]} m, {ff["rotation_deg"]["p50"]}/'
                  f'{ff["rotation_deg"]["p95"]} deg; {doc["wall_s"]} s', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
