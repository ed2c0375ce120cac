"""The block check's verdict on real sets and their fault variants, against the blocks' shape measured apart.

For every real set (../shared/data, see its README: brighton_beach 18 photos, toledo 42) and fault variant,
`photogram-ros triangulate` runs (in a child process that keeps the block check's inputs,
core/block_check.BlockInputs, beside the outputs: OUT/<run>/block_inputs.pkl), and the bench records:
- the verdict (report.json's, made when the block was oriented) and the verdict the block check gives on the
  same inputs now (core/block_check.check_block: the row's `verdict`), with `decided_by` and the summary;
- the block's shape against a reference after a similarity (Umeyama, all photos both oriented): the RMS 3D
  residual of the camera centres, and that as a share of the block's size (the largest distance between two
  reference cameras). References: toledo, an independent SfM (pycolmap 4.2.1, exhaustive matching, in
  ../shared/data/photos/toledo/peer_pycolmap.json: its camera centres are the EXIF GPS positions plus its
  per-photo residuals after its similarity); brighton (no peer camera positions: ODM gives only a cloud),
  `triangulate`'s own block of the unperturbed photos (`reference: triangulate clean`).
- broken blocks made from an oriented block's inputs (no command run; the photos' own evidence kept): tipped
  whole by 30 and 85 degrees about a horizontal axis through its centre, and folded (its last strips turned
  30 degrees about their heading at the fold), each with its own geotags and with geotags scattered 17 m.
- `holds`: the must-show of issue 44 for the row: no FAILED for a block whose shape agrees with its
  reference within 2 %, FAILED for every tipped or folded block.

Variants (triangulate): clean; half (every other photo: half the forward overlap); moved (geotags of some
photos moved 80 m, geo.txt); foreign (photos of the other set's camera added to the folder); wandering heights
(bench/held_out_proxies.py's alt_walk: the EXIF heights plus a random walk of 100 m peak to peak; toledo
alt_walk_h: plus a wandering 15 m horizontal bias); noisy (geotags scattered 17 m horizontally, stated 5 m).

`--recheck` runs no command for a run already in OUT (its .run.json): it reads its block_inputs.pkl and outputs
again and writes the rows with the block check of the code now (the orientation is what its run wrote, on
`orientation_commit`; `orientation_code_changed` says whether the code other than core/block_check.py changed
since); runs not in OUT are made. Variants `--variants` lists run in its order, clean first.

    ROS_DOMAIN_ID=N .venv/bin/python bench/block_verdicts.py --out DIR [--sets brighton,toledo]
        [--variants clean,half,moved,foreign,heights,noisy] [--recheck] [--result bench/results/F.jsonl]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import real_surveys as rs  # noqa: E402
from bench.machine import ResultWriter, tree_state  # noqa: E402

SETS = {'brighton': rs.BRIGHTON / 'images', 'toledo': rs.TOLEDO / 'images'}
VARIANTS = ('clean', 'half', 'moved', 'foreign', 'heights', 'noisy')
MOVED = {'brighton': ('DJI_0021.JPG', 'DJI_0030.JPG'), 'toledo': rs.MOVED_PHOTOS}
FOREIGN = {'brighton': ('toledo', 3), 'toledo': ('brighton', 3)}
HEIGHTS = {'brighton': 'alt_walk', 'toledo': 'alt_walk_h'}
AGREE_SHARE = 0.02            # the must-show: a block within 2 % of its reference's size is not FAILED
MODULES = ['photogram_ros', 'config']
BLOCK_CHECK = 'photogram_ros/core/block_check.py'


# --- the child: triangulate, keeping the block check's inputs ----------------------------------------------


def run_one(src: str, out: str) -> int:
    """`photogram-ros triangulate SRC --out OUT --quiet` in this process, the BlockInputs the block check was
    given pickled into OUT/block_inputs.pkl."""
    import photogram_ros.io.aerial_triangulation as atr
    from photogram_ros import cli
    seen = []
    check = atr.check_block

    def keep(inputs, *a, **k):
        seen.append(inputs)
        return check(inputs, *a, **k)
    atr.check_block = keep
    code = cli.main(['triangulate', src, '--out', out, '--quiet'])
    if seen:
        (Path(out) / 'block_inputs.pkl').write_bytes(pickle.dumps(seen[-1]))
    return code


def triangulate(folder: Path, dst: Path, log: Path, recheck: bool) -> dict:
    saved = log.with_suffix('.run.json')
    if recheck and saved.exists():
        return json.loads(saved.read_text())
    shutil.rmtree(dst, ignore_errors=True)
    state = tree_state()          # the code the run starts on
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, str(Path(__file__).resolve()), '--run-one', str(folder), str(dst)],
                       cwd=ROOT, capture_output=True, text=True, timeout=3600)
    log.write_text(f'--- stdout\n{r.stdout}\n--- stderr\n{r.stderr}')
    lines = [ln for ln in r.stdout.splitlines() if ln.strip()]
    outcome = {'exit': r.returncode, 'wall_s': round(time.monotonic() - t0, 1),
               'last_line': lines[-1] if lines else '', 'orientation_commit': state['commit'],
               'orientation_clean': state['clean']}
    saved.write_text(json.dumps(outcome))
    return outcome


# --- the variants' folders -------------------------------------------------------------------------------


def moved_block(set_name: str, dst: Path, move_m: float = rs.MOVE_M) -> dict:
    """The set's photos (linked) with a geo.txt of their EXIF positions, MOVED[set] shifted `move_m`."""
    ref, frame = rs.linked_block(SETS[set_name], dst)
    geo = dict(ref)
    for k, name in enumerate(MOVED[set_name]):
        enu = frame.geodetic_to_enu(*ref[name]).reshape(3)
        enu[:2] += move_m * np.array([(1, 0), (0, 1), (-1, 0), (0, -1)][k % 4])
        lat, lon, h = frame.enu_to_geodetic(enu)
        geo[name] = (float(np.ravel(lat)[0]), float(np.ravel(lon)[0]), float(np.ravel(h)[0]))
    rs.write_geo_txt(dst / 'geo.txt', geo)
    return {'broken': f'geotags of {", ".join(MOVED[set_name])} moved {move_m:g} m (geo.txt)'}


def foreign_block(set_name: str, dst: Path) -> dict:
    """The set's photos and FOREIGN[set] photos of the other set (another camera) in one folder."""
    other, n = FOREIGN[set_name]
    rs.linked_block(SETS[set_name], dst)
    names = sorted(rs.exif_reference(SETS[other]))[:n]
    for name in names:
        link = dst / name
        if not link.exists():
            link.symlink_to(SETS[other] / name)
    return {'broken': f'{n} photos of {other} (another camera) in the folder: {", ".join(names)}',
            'foreign': names}


def make_folder(set_name: str, variant: str, dst: Path) -> tuple[Path, dict]:
    if variant == 'clean':
        return SETS[set_name], {}
    if variant == 'half':
        ref = rs.half_overlap_block(SETS[set_name], dst)
        return dst, {'broken': f'every other photo ({len(ref)}): half the forward overlap'}
    if variant == 'moved':
        return dst, moved_block(set_name, dst)
    if variant == 'foreign':
        return dst, foreign_block(set_name, dst)
    if variant == 'heights':
        from bench import held_out_proxies as hp
        kind = HEIGHTS[set_name]
        hp.make_proxy(set_name, kind, dst)
        return dst, {'broken': f'held_out_proxies {kind}: heights wandering {hp.ALT_PTP_M:g} m peak to peak'
                               + (f', a {hp.H_BIAS_M:g} m horizontal bias wandering' if kind == 'alt_walk_h' else '')}
    if variant == 'noisy':
        rs.noisy_geotags_block(SETS[set_name], dst)
        return dst, {'broken': 'geotags scattered 17 m horizontally (geo.txt, stated 5 m)'}
    raise ValueError(f'unknown variant {variant!r}; known: {VARIANTS}')


# --- shape against the reference --------------------------------------------------------------------------


def pycolmap_centres(peer_path: Path = rs.TOLEDO / 'peer_pycolmap.json') -> dict:
    """pycolmap's camera centres of toledo as {image: (lat, lon, h)}: the EXIF GPS plus its per-photo residual
    after its similarity (ENU, m; a local frame at the photos' mean: the frames differ by well under a mm here)."""
    from photogram_ros.core.geodesy import LocalFrame
    res = json.loads(peer_path.read_text())['variants']['exhaustive']['per_image_residual_enu_m']
    exif = rs.exif_reference(SETS['toledo'])
    frame = LocalFrame(*np.mean(np.array(list(exif.values())), axis=0))
    out = {}
    for name, r in res.items():
        if name in exif:
            lat, lon, h = frame.enu_to_geodetic(frame.geodetic_to_enu(*exif[name]).reshape(3) + np.asarray(r, float))
            out[name] = (float(np.ravel(lat)[0]), float(np.ravel(lon)[0]), float(np.ravel(h)[0]))
    return out


def shape_agreement(poses: dict, reference: dict) -> dict:
    """The cameras `poses` against `reference` ({image: (lat, lon, h)}) after a similarity over every photo in
    both: RMS 3D (m), max, and the RMS as a share of the reference's size (its largest camera distance)."""
    names, est, ref = rs.paired_enu(poses, reference)
    if len(names) < 4:
        return {'shape_n': len(names)}
    return shape_of(est, ref)


def shape_of(est: np.ndarray, ref: np.ndarray) -> dict:
    from scipy.spatial.distance import pdist

    from photogram_ros.core.similarity import umeyama
    d = np.linalg.norm(umeyama(est, ref).apply(est) - ref, axis=1)
    size = float(pdist(ref).max())
    rms = float(np.sqrt(np.mean(d ** 2)))
    return {'shape_n': len(d), 'shape_rms_m': rms, 'shape_max_m': float(d.max()), 'block_size_m': size,
            'shape_share': rms / size}


# --- broken blocks from an oriented block's inputs --------------------------------------------------------


def _rot(axis: np.ndarray, deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


def _turned(b, which: np.ndarray, R: np.ndarray, c: np.ndarray):
    """`b` with the cameras `which` (and the ground each sees: the point below it at its ground height) turned
    by R about the point c; the geotags stay where they were."""
    T = np.array(b.map_T_cam, float, copy=True)
    gz = np.array(b.ground_z_m, float, copy=True)
    g = T[which, :3, 3].copy()
    g[:, 2] = gz[which]
    T[which, :3, :3] = R @ T[which, :3, :3]
    T[which, :3, 3] = (T[which, :3, 3] - c) @ R.T + c
    gz[which] = ((g - c) @ R.T + c)[:, 2]
    return dataclasses.replace(b, map_T_cam=T, ground_z_m=gz)


def tipped(b, deg: float):
    """The whole block turned `deg` about the east axis through its centre."""
    T = np.asarray(b.map_T_cam, float)
    ok = np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)
    return _turned(b, ok, _rot([1.0, 0.0, 0.0], deg), T[ok, :3, 3].mean(axis=0))


def folded(b, deg: float = 30.0):
    """The block's last strips (a third of them, at least one; core/block_check.strips_of) turned `deg`
    about their heading through the fold: the point between them and the rest. Returns (block, photos turned)."""
    from photogram_ros.core.block_check import strips_of
    T = np.asarray(b.map_T_cam, float)
    idx = np.flatnonzero(np.all(np.isfinite(T.reshape(len(T), -1)), axis=1))
    C = T[idx, :3, 3]
    strips = [s for s in strips_of(C) if len(s) >= 3]
    k = max(1, len(strips) // 3)
    turn = np.concatenate(strips[-k:])
    rest = np.setdiff1d(np.arange(len(idx)), turn)
    s0 = strips[-k]
    heading = C[s0[-1]] - C[s0[0]]
    heading[2] = 0.0
    c = 0.5 * (C[turn].mean(axis=0) + C[rest].mean(axis=0))
    which = np.zeros(len(T), bool)
    which[idx[turn]] = True
    return _turned(b, which, _rot(heading, deg), c), [b.names[i] for i in idx[turn]]


def far_geotags(b, sigma_h_m: float = 17.0, seed: int = 3):
    """`b` with its geotags scattered `sigma_h_m` horizontally and the noise estimated so (as the adjuster does
    on such geotags)."""
    rng = np.random.default_rng(seed)
    fix = np.asarray(b.fix_enu_m, float) + np.column_stack([rng.normal(0, sigma_h_m, (len(b.names), 2)),
                                                            np.zeros(len(b.names))])
    g = dict(b.gnss_noise or {})
    g.update({'stated_h_m': 5.0, 'estimated_h_m': sigma_h_m, 'used_h_m': sigma_h_m, 'n': len(b.names)})
    g.setdefault('stated_v_m', 2.0)
    g.setdefault('estimated_v_m', g.get('used_v_m') or 2.0)
    g.setdefault('used_v_m', g['estimated_v_m'])
    g.setdefault('rejected', [])
    return dataclasses.replace(b, fix_enu_m=fix, gnss_noise=g)


# --- rows ------------------------------------------------------------------------------------------------


def verdict_of(b) -> dict:
    from photogram_ros.core.block_check import check_block
    v = check_block(b)
    return {'status': v.status, 'decided_by': v.decided_by, 'summary': v.summary[:400],
            'checks': {f.check: f.status for f in v.findings}}


def centres_enu(b) -> tuple[list, np.ndarray]:
    T = np.asarray(b.map_T_cam, float)
    ok = np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)
    return [n for n, k in zip(b.names, ok) if k], T[ok, :3, 3]


def orientation_changed(commit: str) -> bool | None:
    """Whether the product code other than core/block_check.py changed between `commit` and the tree now."""
    try:
        r = subprocess.run(['git', 'diff', '--name-only', commit, '--', *MODULES, f':(exclude){BLOCK_CHECK}'],
                           cwd=ROOT, capture_output=True, text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        return None
    return bool(r.stdout.strip())


def holds(row: dict) -> bool | None:
    """The must-show for this row: broken (tipped/folded) -> FAILED; shape within AGREE_SHARE -> not FAILED."""
    st = (row.get('verdict') or {}).get('status')
    if st is None:
        return None
    if row.get('kind') in ('tipped', 'folded'):
        return st == 'failed'
    share = row.get('shape_share')
    if share is None:
        return None
    return st != 'failed' if share <= AGREE_SHARE else None


def measure_variant(set_name: str, variant: str, out: Path, recheck: bool, references: dict) -> tuple[dict, object]:
    folder, extra = make_folder(set_name, variant, out / 'blocks' / f'{set_name}_{variant}')
    dst = out / f'{set_name}_{variant}'
    run = triangulate(folder, dst, out / f'{set_name}_{variant}.log', recheck)
    row = {'set': set_name, 'variant': variant, 'kind': 'triangulate', **extra, **run,
           'photos': rs.photo_count(folder)}
    rep = json.loads((dst / 'report.json').read_text()) if (dst / 'report.json').exists() else {}
    rv = rep.get('verdict') or {}
    row['report_verdict'] = {'status': rv.get('status'), 'decided_by': rv.get('decided_by'),
                             'summary': (rv.get('summary') or '')[:400]}
    poses = rs.read_poses(dst / 'poses.csv') if (dst / 'poses.csv').exists() else {}
    row['oriented'] = len(poses)
    ref_name, ref = references.get(set_name, (None, None))
    if variant == 'clean' and ref is None:
        references[set_name] = ('triangulate clean', {n: (p['lat_deg'], p['lon_deg'], p['h_m'])
                                                      for n, p in poses.items()})
        ref_name, ref = None, None
    row['reference'] = ref_name
    if ref is not None and poses:
        row.update(shape_agreement(poses, ref))
    pkl = dst / 'block_inputs.pkl'
    inputs = pickle.loads(pkl.read_bytes()) if pkl.exists() else None
    if inputs is not None:
        row['verdict'] = verdict_of(inputs)
    commit = run.get('orientation_commit')
    row['orientation_code_changed'] = orientation_changed(commit) if commit else None
    row['holds'] = holds(row)
    return row, inputs


def broken_rows(set_name: str, variant: str, inputs, base_row: dict, geotag_kinds=('own',)) -> list[dict]:
    """The run's block tipped 30 and 85 degrees and folded, with its own geotags ('own') and/or with them
    scattered 17 m ('scattered 17 m')."""
    rows = []
    names0, C0 = centres_enu(inputs)
    for geotags in geotag_kinds:
        b = inputs if geotags == 'own' else far_geotags(inputs)
        cases = [('tipped', f'tipped {d:g} degrees whole', tipped(b, d), []) for d in (30.0, 85.0)]
        fb, turned = folded(b)
        cases.append(('folded', 'folded 30 degrees along its last strips', fb, turned))
        for kind, what, bb, photos in cases:
            names, C = centres_enu(bb)
            row = {'set': set_name, 'variant': variant, 'kind': kind, 'broken': f'{what}; geotags {geotags}',
                   'geotags': geotags, 'photos_turned': photos, 'from_run': base_row.get('variant'),
                   'orientation_commit': base_row.get('orientation_commit'),
                   'orientation_code_changed': base_row.get('orientation_code_changed'),
                   'reference': 'the block before it was broken', **shape_of(C, C0),
                   'verdict': verdict_of(bb)}
            row['holds'] = holds(row)
            rows.append(row)
    return rows


def line(row: dict) -> str:
    v = row.get('verdict') or {}
    share = row.get('shape_share')
    return (f"{row['set']} {row['variant']} {row['kind']}{' (' + row['broken'] + ')' if row.get('broken') else ''}: "
            f"{str(v.get('status')).upper()} by {v.get('decided_by')}; shape "
            f"{'n/a' if share is None else f'{100 * share:.2f} %'} of the block ({row.get('reference')}); "
            f"holds {row.get('holds')}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--out', default='/tmp/block_verdicts', help='output folder (runs, logs, block_verdicts.jsonl)')
    ap.add_argument('--sets', default=','.join(SETS), help='sets, comma separated')
    ap.add_argument('--variants', default=','.join(VARIANTS), help='variants, comma separated')
    ap.add_argument('--recheck', action='store_true', help='reuse the runs already in OUT: the block check of the code '
                                                           'now on the inputs each run kept')
    ap.add_argument('--result', default=None, help='result file (default OUT/block_verdicts.jsonl)')
    ap.add_argument('--run-one', nargs=2, metavar=('SRC', 'OUT'), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.run_one:
        return run_one(*a.run_one)
    sets = [s for s in a.sets.split(',') if s]
    variants = [v for v in a.variants.split(',') if v]
    bad = [s for s in sets if s not in SETS] + [v for v in variants if v not in VARIANTS]
    if bad:
        ap.error(f'unknown {bad}; sets {tuple(SETS)}, variants {VARIANTS}')
    if 'clean' in variants:
        variants = ['clean'] + [v for v in variants if v != 'clean']
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    references = {'toledo': ('pycolmap 4.2.1 (peer_pycolmap.json)', pycolmap_centres())}
    w = ResultWriter(a.result or out / 'block_verdicts.jsonl', 'block_verdicts', MODULES)
    failed_must = 0
    for s in sets:
        for v in variants:
            row, inputs = measure_variant(s, v, out, a.recheck, references)
            w.write(row)
            print(line(row), flush=True)
            failed_must += row['holds'] is False
            if inputs is not None and v in ('clean', 'noisy', 'heights'):
                kinds = ('own', 'scattered 17 m') if v == 'clean' else ('own',)
                for r in broken_rows(s, v, inputs, row, kinds):
                    w.write(r)
                    print(line(r), flush=True)
                    failed_must += r['holds'] is False
    print(f'{failed_must} rows break the must-show' if failed_must else 'every row holds the must-show')
    return 1 if failed_must else 0


if __name__ == '__main__':
    sys.exit(main())
