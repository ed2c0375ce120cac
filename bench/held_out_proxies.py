"""Proxies of a held-out consumer-camera survey: the real photo sets of ../shared/data with geotags made as
poor as a consumer camera's own GPS makes them, through `triangulate` (and `replay`), measured against
their true (unperturbed EXIF) positions and against the same photos' unperturbed triangulation.

Sets: toledo (photos/toledo/images, 42 photos) and brighton (photos/brighton_beach/images, 18 photos). Each
proxy is a folder of links to the photos with a geo.txt beside them (io/image_source reads it instead of
the EXIF GPS; bench/real_surveys.write_geo_txt writes it), the photos taken in their time order:

- alt_walk: the EXIF altitudes plus a random walk scaled to 100 m peak to peak over the flight
  (horizontal unchanged); stated accuracies those of an EXIF geotag (5 m H, 2 m V);
- alt_walk_h: alt_walk plus a horizontal error correlated in time: a bias of 15 m in a random direction
  wandering by 8 m peak to peak per axis (a smoothed random walk), plus 2.5 m white noise per axis;
- missing_third: alt_walk_h without geotags for a third of the flight (consecutive photos, no geo.txt line);
- optimistic: alt_walk_h's errors with the geo.txt stating 5 m H / 10 m V.

Seeds are fixed (one per set and kind). Per proxy, from the files the command writes:
- oriented / photos;
- shape: the camera centres against the unperturbed triangulation of the same photos after a robust
  similarity (bench/real_surveys.robust_similarity), RMS 3D and H / V (m), and the rotation of that
  similarity (degrees: how far the block was turned, e.g. tilted after an altitude trend);
- true_rigid_h_m: the cameras' horizontal RMS distance to their TRUE positions as they are (what the user
  gets), against `baseline_true_rigid_h_m` (the unperturbed triangulation's) and `allowed_h_m`, the
  horizontal RMS distance by which the best rigid fit (rotation + translation, no scale) of the true
  positions to the perturbed geotags moves them: how well the geotags can place the block at all;
- nadir share and median tilt; the verdict (status, checks, summary) and the exit code;
- the GNSS noise the adjustment estimated (report.json gnss_noise) against the injected one: the
  per-axis RMS of the horizontal error about its mean, and the vertical error's standard deviation.

Writes OUT/held_out_proxies.jsonl (one line a run, through bench/machine.py's ResultWriter: commit, clean-tree
flag, cores, load; the result file), OUT/held_out_proxies.json and OUT/held_out_proxies.md; commands' folders and
logs stay in OUT.

    ROS_DOMAIN_ID=45 .venv/bin/python bench/held_out_proxies.py [--sets toledo,brighton]
        [--kinds alt_walk,alt_walk_h,missing_third,optimistic] [--replay toledo:alt_walk_h] [--out DIR]
        [--remeasure]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import real_surveys as rs  # noqa: E402
from bench.machine import ResultWriter  # noqa: E402
from photogram_ros.core.geodesy import LocalFrame  # noqa: E402

SETS = {'toledo': rs.TOLEDO / 'images', 'brighton': rs.BRIGHTON / 'images'}
KINDS = ('alt_walk', 'alt_walk_h', 'missing_third', 'optimistic')
SEEDS = {'toledo': 2301, 'brighton': 2302}
ALT_PTP_M = 100.0
H_BIAS_M = 15.0
H_WANDER_PTP_M = 8.0
H_NOISE_M = 2.5
STATED = {'alt_walk': (5.0, 2.0), 'alt_walk_h': (5.0, 2.0), 'missing_third': (5.0, 2.0), 'optimistic': (5.0, 10.0)}


# --- the perturbations -----------------------------------------------------------------------------------


def _walk(rng: np.random.Generator, n: int, ptp_m: float, smooth: int = 1) -> np.ndarray:
    """A random walk of n steps (moving-average smoothed over `smooth` steps), mean zero, `ptp_m` peak to peak."""
    w = np.cumsum(rng.normal(size=n + smooth - 1))
    if smooth > 1:
        w = np.convolve(w, np.ones(smooth) / smooth, mode='valid')
    w = w - w.mean()
    return w * (ptp_m / max(float(np.ptp(w)), 1e-9))


def consumer_errors(n: int, seed: int) -> dict:
    """ENU errors (m) of n geotags in time order: {'alt_walk': (n, 3), 'alt_walk_h': (n, 3), 'missing': (n,)
    bool of the third without a geotag}. One stream per seed, so every kind shares the altitude walk."""
    rng = np.random.default_rng(seed)
    dz = _walk(rng, n, ALT_PTP_M)
    a = np.zeros((n, 3))
    a[:, 2] = dz
    ang = rng.uniform(0.0, 2.0 * np.pi)
    bias = H_BIAS_M * np.array([np.cos(ang), np.sin(ang)])
    wander = np.column_stack([_walk(rng, n, H_WANDER_PTP_M, smooth=max(3, n // 8)) for _ in range(2)])
    b = a.copy()
    b[:, :2] = bias + wander + rng.normal(0.0, H_NOISE_M, (n, 2))
    third = n // 3
    start = int(rng.integers(0, n - third + 1))
    missing = np.zeros(n, bool)
    missing[start:start + third] = True
    return {'alt_walk': a, 'alt_walk_h': b, 'missing': missing}


def injected_figures(err: np.ndarray) -> dict:
    """What the estimator should find: the horizontal per-axis RMS about the mean, the vertical standard
    deviation, the mean horizontal offset and the vertical peak to peak (m)."""
    e = np.asarray(err, float)
    d = e - e.mean(axis=0)
    return {'noise_h_m': float(np.sqrt(np.mean(d[:, :2] ** 2))), 'noise_v_m': float(np.std(e[:, 2])),
            'mean_h_m': float(np.hypot(*e[:, :2].mean(axis=0))), 'ptp_v_m': float(np.ptp(e[:, 2]))}


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation and translation (no scale, Kabsch) src -> dst: (R, t)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((dst - md).T @ (src - ms))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    return R, md - R @ ms


def make_proxy(set_name: str, kind: str, dst: Path) -> dict:
    """A folder `dst` of links to the set's photos with a geo.txt of `kind`'s geotags. Returns {'truth':
    {name: (lat, lon, h)}, 'error_enu_m': {name: [e, n, u]} of the photos with a geotag, 'missing': [names],
    'stated': (h, v)}."""
    src = SETS[set_name]
    truth = rs.exif_reference(src)
    order = [name for _, name in sorted(rs.photo_stamps(src).items()) if name in truth]
    dst.mkdir(parents=True, exist_ok=True)
    for name in order:
        link = dst / name
        if not link.exists():
            link.symlink_to(src / name)
    errs = consumer_errors(len(order), SEEDS[set_name])
    err = errs['alt_walk'] if kind == 'alt_walk' else errs['alt_walk_h']
    missing = errs['missing'] if kind == 'missing_third' else np.zeros(len(order), bool)
    frame = LocalFrame(*np.mean(np.array([truth[n] for n in order]), axis=0))
    geo, used = {}, {}
    for name, e, miss in zip(order, err, missing):
        if miss:
            continue
        enu = frame.geodetic_to_enu(*truth[name]).reshape(3) + e
        lat, lon, h = frame.enu_to_geodetic(enu)
        geo[name] = (float(np.ravel(lat)[0]), float(np.ravel(lon)[0]), float(np.ravel(h)[0]))
        used[name] = [float(x) for x in e]
    h_acc, v_acc = STATED[kind]
    rs.write_geo_txt(dst / 'geo.txt', geo, h_acc, v_acc)
    return {'truth': truth, 'error_enu_m': used, 'missing': [n for n, m in zip(order, missing) if m],
            'stated': (h_acc, v_acc), 'perturbed': geo}


# --- measuring -----------------------------------------------------------------------------------------


def _poses(out: Path, pipeline: str, folder: Path) -> dict:
    f = out / ('poses.csv' if pipeline == 'triangulate' else 'trajectory.csv')
    if not f.exists():
        return {}
    poses = rs.read_poses(f)
    if pipeline == 'replay':
        names = rs.photo_stamps(folder)
        poses = {names.get(p.get('stamp_ns'), n): p for n, p in poses.items()}
    return poses


def allowed_h_m(truth: dict, perturbed: dict) -> float:
    """Horizontal RMS (m) by which the best rigid fit of the true positions to the perturbed geotags moves
    them (over the photos with a geotag)."""
    names = sorted(perturbed)
    if len(names) < 3:
        return float('nan')
    _, t_enu, p_enu = rs.paired_enu({n: dict(zip(('lat_deg', 'lon_deg', 'h_m'), truth[n])) for n in names},
                                    perturbed)
    R, t = rigid_fit(t_enu, p_enu)
    return rs.rms_hv(t_enu @ R.T + t - t_enu)[0]


def shape_figures(poses: dict, baseline: dict) -> dict:
    """The block against the unperturbed block of the same photos after a robust similarity."""
    ref = {n: (p['lat_deg'], p['lon_deg'], p['h_m']) for n, p in baseline.items()}
    names, est, base = rs.paired_enu(poses, ref)
    if len(names) < 3:
        return {'shape_n': len(names)}
    res, keep = rs.robust_similarity(est, base)
    h, v = rs.rms_hv(res[keep])
    sim = rs.umeyama(est[keep], base[keep]) if keep.sum() >= 3 else rs.umeyama(est, base)
    turn = float(np.degrees(np.arccos(np.clip((np.trace(sim.R) - 1.0) / 2.0, -1.0, 1.0))))
    tilt = float(np.degrees(np.arccos(np.clip(sim.R[2, 2], -1.0, 1.0))))
    return {'shape_n': len(names), 'shape_kept': int(keep.sum()),
            'shape_rms_3d_m': float(np.sqrt(np.mean(np.sum(res[keep] ** 2, axis=1)))), 'shape_h_m': h,
            'shape_v_m': v, 'shape_scale': float(sim.scale), 'turn_deg': turn, 'tilt_vs_baseline_deg': tilt}


def measure_run(out: Path, pipeline: str, folder: Path, truth: dict, baseline: dict | None) -> dict:
    row: dict = {}
    rep_path = out / 'report.json'
    report = json.loads(rep_path.read_text()) if rep_path.exists() else {}
    poses = _poses(out, pipeline, folder)
    row['oriented'] = len(poses)
    v = report.get('verdict') or rs._find(report, 'verdict') or {}
    if isinstance(v, dict):
        row['verdict'] = v.get('status')
        row['verdict_summary'] = v.get('summary')
        row['verdict_checks'] = {f['check']: f['status'] for f in v.get('findings', [])}
    else:
        row['verdict'] = str(v)
    g = report.get('gnss_noise') or rs._find(report, 'gnss_noise') or {}
    row['gnss_noise'] = {k: g.get(k) for k in ('stated_h_m', 'stated_v_m', 'estimated_h_m', 'estimated_v_m',
                                               'used_h_m', 'used_v_m', 'n') if k in g}
    row['gnss_rejected'] = len(g.get('rejected', []))
    names, est, ref = rs.paired_enu(poses, truth)
    if len(names) >= 3:
        row['true_rigid_h_m'], row['true_rigid_v_m'] = rs.rms_hv(est - ref)
        res, keep = rs.robust_similarity(est, ref)
        row['true_sim_h_m'], row['true_sim_v_m'] = rs.rms_hv(res[keep])
    row.update(rs.nadir_figures(poses))
    if baseline:
        row.update(shape_figures(poses, baseline))
    return row


def run_one(set_name: str, kind: str, pipeline: str, out: Path, baseline: dict | None) -> dict:
    folder = out / 'blocks' / f'{set_name}_{kind}'
    p = make_proxy(set_name, kind, folder)
    dst = out / f'{set_name}_{kind}_{pipeline}'
    if not rs.REMEASURE:
        shutil.rmtree(dst, ignore_errors=True)
    cmd = [pipeline, str(folder), '--out', str(dst)] + (['--quiet'] if pipeline == 'replay' else [])
    run = rs.run_command(cmd, out / f'{set_name}_{kind}_{pipeline}.log')
    err = np.array(list(p['error_enu_m'].values()))
    row = {'set': set_name, 'kind': kind, 'pipeline': pipeline, 'command': 'photogram-ros ' + ' '.join(cmd),
           'exit': run['exit'], 'wall_s': run['wall_s'], 'last_line': run['last_line'],
           'photos': len(p['truth']), 'geotags': len(p['error_enu_m']), 'missing': p['missing'],
           'stated_h_m': p['stated'][0], 'stated_v_m': p['stated'][1], 'injected': injected_figures(err),
           'allowed_h_m': allowed_h_m(p['truth'], p['perturbed'])}
    row.update(measure_run(dst, pipeline, folder, p['truth'], baseline))
    return row


def run_baseline(set_name: str, out: Path) -> tuple[dict, dict]:
    """The unperturbed photos (their own EXIF) through triangulate: (row, poses)."""
    src = SETS[set_name]
    dst = out / f'{set_name}_baseline_triangulate'
    if not rs.REMEASURE:
        shutil.rmtree(dst, ignore_errors=True)
    cmd = ['triangulate', str(src), '--out', str(dst)]
    run = rs.run_command(cmd, out / f'{set_name}_baseline_triangulate.log')
    truth = rs.exif_reference(src)
    row = {'set': set_name, 'kind': 'baseline', 'pipeline': 'triangulate', 'command': 'photogram-ros ' + ' '.join(cmd),
           'exit': run['exit'], 'wall_s': run['wall_s'], 'last_line': run['last_line'], 'photos': len(truth)}
    row.update(measure_run(dst, 'triangulate', src, truth, None))
    return row, _poses(dst, 'triangulate', src)


# --- the table -----------------------------------------------------------------------------------------


def _f(v, fmt='.2f'):
    return 'n/a' if v is None or (isinstance(v, float) and not np.isfinite(v)) else f'{v:{fmt}}'


def markdown(rows: list[dict], commit: str) -> str:
    lines = [f'Measured with the product code of commit {commit}.', '',
             '| set | proxy | pipeline | oriented | shape vs unperturbed (RMS 3D, m; turn deg) | H to truth rigid (m) '
             '| baseline H to truth (m) | geotags allow H (m) | nadir share (median tilt) | GNSS noise est H / V (m) '
             '| injected H / V (m) | stated H / V (m) | verdict | exit | wall (s) |', '|' + '---|' * 15]
    base = {r['set']: r for r in rows if r['kind'] == 'baseline'}
    for r in rows:
        g = r.get('gnss_noise') or {}
        inj = r.get('injected') or {}
        b = base.get(r['set'], {})
        checks = ', '.join(f'{k}:{v}' for k, v in (r.get('verdict_checks') or {}).items())
        lines.append(' | '.join([
            f"| {r['set']}", r['kind'], r['pipeline'], f"{r.get('oriented')}/{r.get('photos')}",
            f"{_f(r.get('shape_rms_3d_m'))} ({_f(r.get('turn_deg'), '.1f')})" if 'shape_rms_3d_m' in r else '—',
            _f(r.get('true_rigid_h_m')), _f(b.get('true_rigid_h_m')), _f(r.get('allowed_h_m')),
            f"{_f(r.get('nadir_share'), '.0%')} ({_f(r.get('tilt_median_deg'), '.1f')})",
            f"{_f(g.get('estimated_h_m'))} / {_f(g.get('estimated_v_m'))}",
            f"{_f(inj.get('noise_h_m'))} / {_f(inj.get('noise_v_m'))}" if inj else '—',
            f"{_f(r.get('stated_h_m'), 'g')} / {_f(r.get('stated_v_m'), 'g')}" if 'stated_h_m' in r else '5 / 2 (EXIF)',
            f"{(r.get('verdict') or 'n/a').upper()} ({checks})".replace('|', '\\|'), str(r.get('exit')),
            f"{r.get('wall_s', 0):.0f} |"]))
    lines += ['', 'Verdicts:', '']
    for r in rows:
        lines.append(f"- {r['set']} {r['kind']} {r['pipeline']}: {r.get('verdict_summary') or r.get('last_line')}")
    return '\n'.join(lines) + '\n'


def run_all(sets, kinds, replay: list[tuple[str, str]], out: Path) -> list[dict]:
    out.mkdir(parents=True, exist_ok=True)
    commit = rs.git_commit()
    rows = []
    writer = ResultWriter(out / 'held_out_proxies.jsonl', 'held_out_proxies', ['photogram_ros', 'config'])

    def keep(row):
        rows.append({**row, 'commit': commit})
        writer.write(row)
        (out / 'held_out_proxies.json').write_text(json.dumps(rows, indent=1, default=str))
        (out / 'held_out_proxies.md').write_text(markdown(rows, commit))
        g = row.get('gnss_noise') or {}
        print(f"{row['set']} {row['kind']} {row['pipeline']}: {row.get('oriented')}/{row.get('photos')}, shape "
              f"{_f(row.get('shape_rms_3d_m'))} m, H to truth {_f(row.get('true_rigid_h_m'))} m (allowed "
              f"{_f(row.get('allowed_h_m'))}), nadir {_f(row.get('nadir_share'), '.0%')}, noise "
              f"{_f(g.get('estimated_h_m'))}/{_f(g.get('estimated_v_m'))}, {row.get('verdict')}, "
              f"{row['wall_s']:.0f} s", flush=True)

    for s in sets:
        brow, bposes = run_baseline(s, out)
        keep(brow)
        for k in kinds:
            keep(run_one(s, k, 'triangulate', out, bposes))
        for rs_set, rk in replay:
            if rs_set == s:
                keep(run_one(s, rk, 'replay', out, bposes))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--sets', default=','.join(SETS), help='photo sets, comma separated')
    ap.add_argument('--kinds', default=','.join(KINDS), help='proxies, comma separated')
    ap.add_argument('--replay', default='toledo:alt_walk_h', help='set:kind pairs also run through replay ("" none)')
    ap.add_argument('--out', default='/tmp/held_out_proxies', help='output folder')
    ap.add_argument('--remeasure', action='store_true', help='measure the outputs already in --out again')
    a = ap.parse_args(argv)
    rs.REMEASURE = a.remeasure
    sets = [s for s in a.sets.split(',') if s]
    kinds = [k for k in a.kinds.split(',') if k]
    replay = [tuple(p.split(':')) for p in a.replay.split(',') if p]
    bad = [s for s in sets if s not in SETS] + [k for k in kinds if k not in KINDS] + \
          [p for p in replay if len(p) != 2 or p[0] not in SETS or p[1] not in KINDS]
    if bad:
        ap.error(f'unknown {bad}; sets {tuple(SETS)}, kinds {KINDS}')
    rows = run_all(sets, kinds, replay, Path(a.out))
    print(markdown(rows, rows[0]['commit'] if rows else rs.git_commit()))
    return 0


if __name__ == '__main__':
    sys.exit(main())
