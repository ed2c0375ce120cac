"""The split-merge action: a large photo block adjusted as overlapping sub-blocks (core/split_merge.py).

`split_merge_block` partitions the photos by their geotags into overlapping sub-blocks, adjusts each as a block of
its own (`adjust_sub_block`, io/aerial_triangulation.py, one task of a runner of io/dask_cluster.py; each
sub-block's own outputs in out/sub_blocks/NN), merges them into one block by a similarity per sub-block, adjusts the
merged block as one (`_global_adjustment`) and writes and checks it as one block.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from photogram_ros.core.at_report import gnss_figures, rmse_xyz
from photogram_ros.core.block_check import Finding, check_block
from photogram_ros.core.evaluation import ce90_le90
from photogram_ros.core.geodesy import utm_epsg
from photogram_ros.core.incremental import SELF_CALIBRATION_BASE, IncrementalAT
from photogram_ros.errors import ConfigError
from photogram_ros.io.aerial_triangulation import (TriangulateOptions, TriangulateResult, adjust_and_write,
                                                   control_rows, finish_block, heights_keys, manual_tie_obs,
                                                   with_findings, write_poses_and_cloud)
from photogram_ros.io.at_report import write_report
from photogram_ros.io.keyframe_block import KeyframeBlock
from photogram_ros.io.progress import Steps


@dataclass
class SubBlockRun:
    """What one sub-block's adjustment sends back (small: no IncrementalAT crosses the cluster)."""
    sub: object                 # core/split_merge.py SubBlock
    report: dict                # its report.json's figures (also written to out/sub_blocks/NN)
    inputs: object | None       # core/block_check.py BlockInputs of its photos (None: it failed)
    wall_s: float
    cpu_s: float                # this process's CPU time in it (the worker's, on a cluster)
    # What the global adjustment after the merge starts from: the sub-block's self-calibrated camera, its GNSS
    # noise scale (h, v) and bias (ENU m), the photos whose fix it did not use, its control vetting
    # (core/control.py ControlVetting or None) and the control points as it adjusted them.
    camera: object | None = None
    gnss_scale_hv: tuple = (1.0, 1.0)
    gnss_bias_enu_m: tuple = (0.0, 0.0, 0.0)
    gnss_rejected: tuple = ()
    vetting: object | None = None
    control: list = field(default_factory=list)


def adjust_sub_block(index: int, block: KeyframeBlock, out: str | Path, opt: TriangulateOptions) -> SubBlockRun:
    """One sub-block adjusted as a block of its own (GNSS, control vetting, GCPs it sees, full adjustment)
    into `out` (its own poses.csv and report); an adjustment that raises is a failed sub-block."""
    from photogram_ros.core.split_merge import SubBlock
    from photogram_ros.errors import PhotogramError
    t0, c0 = time.monotonic(), time.process_time()
    names = [r.name for r in block.records]
    try:
        res, at, inputs, ctl = adjust_and_write(block, out, opt, None, None, t0, progress=False)
    except (PhotogramError, np.linalg.LinAlgError, ValueError) as e:
        sub = SubBlock(index, names, status='failed', summary=f'FAILED: its adjustment stopped: {e}')
        return SubBlockRun(sub, {}, None, time.monotonic() - t0, time.process_time() - c0)
    ids, P = at.block.point_arrays()
    keep = ids >= 0                 # tie points (targets have negative ids)
    checks = {p['name']: (np.asarray(p['surveyed_map_m'], float) + np.asarray(p['residual_m'], float), p['images'])
              for p in res.report['check']['points']}
    v = res.verdict
    sub = SubBlock(index, names, at.block.poses_by_name(),
                   np.asarray(ids[keep], np.int64), np.asarray(P[keep], float).reshape(-1, 3), checks,
                   v.get('status', 'ok'), v.get('summary', ''))
    return SubBlockRun(sub, res.report, inputs, time.monotonic() - t0, time.process_time() - c0, at.block.camera,
                       tuple(float(x) for x in at.datum.sigma_scale_hv), tuple(float(x) for x in at.datum.bias_enu),
                       tuple(at.datum.rejected_names()), ctl['vetting'], list(ctl['control']))


def _sub_block(block: KeyframeBlock, idx) -> KeyframeBlock:
    """The photos `idx` of the block as a block of their own, in the same map frame."""
    return KeyframeBlock(block.camera, block.origin, [block.records[i] for i in idx], list(block.assumptions),
                         len(idx), None, block.camera_from_exif, {}, [], block.expect_nadir, {})


def _merged_gnss_noise(runs: list) -> dict:
    """The sub-blocks' GNSS noise estimates as one: the photo-weighted RMS of each figure, the rejected
    geotags of all."""
    out: dict = {}
    runs = [r for r in runs if r.inputs is not None and r.inputs.gnss_noise]
    if not runs:
        return out
    w = np.array([len(r.sub.names) for r in runs], float)
    for key in ('used_h_m', 'used_v_m', 'estimated_h_m', 'estimated_v_m', 'stated_h_m', 'stated_v_m'):
        vals = [r.inputs.gnss_noise.get(key) for r in runs]
        if all(v is not None for v in vals):
            out[key] = float(np.sqrt(np.sum(w * np.square(vals)) / w.sum()))
    ns = [r.inputs.gnss_noise.get('n') for r in runs]
    if all(n is not None for n in ns):
        out['n'] = int(sum(ns))
    out['rejected'] = sorted({n for r in runs for n in r.inputs.gnss_noise.get('rejected', [])})
    return out


def _merged_vetting(runs: list, core_of: dict):
    """One core/control.py ControlVetting of the whole block from the sub-blocks' (each against its own
    GNSS-only adjustment): each control row's fate from the sub-block whose core holds its photo (else from
    one that has the photo), each point's use from the sub-block that had the most usable rows of it, the
    faults of all. None when no sub-block vetted control."""
    from photogram_ros.core.control import ControlVetting
    vets = {r.sub.index: r.vetting for r in runs if r.vetting is not None}
    if not vets:
        return None
    ref = next(iter(vets.values()))
    rows = []
    for i, f in enumerate(ref.rows):
        pick = vets.get(core_of.get(f.row.image))
        if pick is None or len(pick.rows) != len(ref.rows):
            pick = next((v for v in vets.values() if len(v.rows) == len(ref.rows)
                         and v.rows[i].fate != 'photo_not_in_set'), ref)
        rows.append(pick.rows[i])
    points = {}
    for v in vets.values():
        for name, p in v.points.items():
            if name not in points or p.usable_rows > points[name].usable_rows:
                points[name] = p
    notes = list(dict.fromkeys(n for v in vets.values() for n in v.notes))
    wrong = {k: w for v in vets.values() for k, w in v.wrong_photos.items()}
    suspect = next((v.height_suspect for v in vets.values() if v.height_suspect), '')
    return ControlVetting(rows, points, wrong, suspect, notes)


def sub_blocks_selection(runs: list, candidates: tuple) -> tuple | None:
    """What the global adjustment after the merge refines of `candidates` when every sub-block chose its own
    self-calibration stepwise (its report's `self_calibration_selection`): the base terms (f, cx, cy among the
    candidates), which hang on the whole block's datum (its GCP heights, its geotags). The distortion terms stay
    at the sub-blocks' photo-weighted mean (`mean_camera`), the camera the global adjustment starts from: each
    sub-block determined them on its own photos. None when a sub-block made no stepwise selection (the global
    adjustment then makes its own)."""
    sels = [r.report.get('self_calibration_selection') for r in runs]
    if not sels or any(not s or s.get('method') != 'stepwise' for s in sels):
        return None
    return tuple(c for c in candidates if c in SELF_CALIBRATION_BASE)


def _global_adjustment(block: KeyframeBlock, mr, runs: list, core_of: dict, opt: TriangulateOptions,
                       control: tuple, log=None) -> dict:
    """The merged block (core/split_merge.py MergeResult `mr`) adjusted as one block: an IncrementalAT seeded
    with the merged poses and tie points (core/incremental.py IncrementalAT.seed) and the sub-blocks' mean camera,
    GNSS noise scale, bias and rejected fixes, its GCP observations and control points as the sub-blocks vetted
    them (`_merged_vetting`), then the single block's final adjustment (`full_adjustment`: GNSS noise, bias,
    the self-calibration opt.self_calibrate names, else what the sub-blocks chose (`sub_blocks_selection`) of
    `auto_self_calibration`'s candidates, else a stepwise selection of its own). Returns {'at', 'rep_adj',
    'refine', 'control', 'vetting', 'figures'}; figures: the solves, their iterations, wall and CPU time, the
    seed, and how far it moved the cameras from the merged block (core/split_merge.py camera_moves)."""
    from photogram_ros.core.split_merge import camera_moves, mean_camera
    t0, c0 = time.monotonic(), time.process_time()
    good = [r for r in runs if r.inputs is not None and r.camera is not None and r.sub.index not in mr.left_out]
    if not good:
        raise ConfigError('no sub-block to start the global adjustment from')
    names = {r.name for r in block.records}
    notes: list = []
    control, vet, target_obs, tie_obs, n_gcps = _global_control(control, good, core_of, names, notes, log)
    refine, stepwise, chosen = _global_refine(block, opt, good, n_gcps, notes)
    w = np.array([len(r.sub.map_T_cam) for r in good], float)
    camera = mean_camera([r.camera for r in good], w)
    ties = {n for o in tie_obs.values() for n in o}
    at = IncrementalAT(camera, replace(opt.adjustment, spill_frozen=False), block.origin, control, ties=ties)
    tuv = {nm: {**target_obs.get(nm, {}), **tie_obs.get(nm, {})} for nm in names}
    gate_px = opt.split.seed_gate_px if opt.split is not None else None
    seed = at.seed(block.records, mr.map_T_cam, mr.point_ids, mr.points_map_m, tuv, gate_px)
    at.datum.adopt(np.sum(w[:, None] * np.array([r.gnss_scale_hv for r in good]), axis=0) / w.sum(),
                   np.sum(w[:, None] * np.array([r.gnss_bias_enu_m for r in good]), axis=0) / w.sum(),
                   {n for r in good for n in r.gnss_rejected})
    if log is not None:
        log(f'split-merge: global adjustment of {seed["oriented"]} photos, {seed["points"]} tie points '
            f'({seed["observations_left_out"]} of {seed["observations"]} observations beyond '
            f'{gate_px or 2 * opt.adjustment.max_reprojection_px:.1f} px of the merged block left out), GCPs {len(seed["gcps"])}'
            + (f', self-calibrating {", ".join(refine)}' if refine else ''))
    n_solves = len(at.adjustment.solve_log())
    rep_adj = at.full_adjustment(refine_intrinsics=refine, stepwise=stepwise)
    solves = at.adjustment.solve_log()[n_solves:]
    after = at.block.poses_by_name()
    figures = {'status': rep_adj.status, 'solves': len(solves),
               'iterations': int(sum(s['iterations'] for s in solves)),
               'solve_iterations': [s['iterations'] for s in solves],
               'wall_s': round(time.monotonic() - t0, 2), 'cpu_s': round(time.process_time() - c0, 2),
               'seed': {k: v for k, v in seed.items() if k != 'gcps'}, 'gcps': seed['gcps'],
               'camera_moves': camera_moves(mr.map_T_cam, after),
               'refine': list(refine), 'refine_chosen_by': ('given' if opt.self_calibrate is not None else
                                                            'sub_blocks' if chosen is not None else
                                                            'stepwise' if refine else 'none'),
               'camera_start': {'fx': camera.fx, 'fy': camera.fy, 'cx': camera.cx, 'cy': camera.cy,
                                'dist': list(camera.dist)}}
    if log is not None:
        mv = figures['camera_moves']
        log(f'split-merge: global adjustment {rep_adj.status}: {figures["solves"]} solves, {figures["iterations"]} '
            f'iterations, {figures["wall_s"]:.1f} s; cameras moved {mv.get("centre_rms_m", 0.0) * 100:.2f} cm RMS '
            f'(max {mv.get("centre_max_m", 0.0) * 100:.2f} cm), {mv.get("attitude_rms_deg", 0.0):.4f} deg RMS')
    block.assumptions.extend(notes)
    return {'at': at, 'rep_adj': rep_adj, 'refine': refine, 'control': control, 'vetting': vet, 'figures': figures}


def _global_control(control_of_file: tuple, good: list, core_of: dict, names: set, notes: list, log=None):
    """(control points, merged vetting or None, GCP observations used by photo, manual tie point observations by
    photo, GCPs used in full) of the global adjustment: the control of the file (`control_rows`) as the sub-blocks
    vetted it."""
    control, rows, _, _, tie_rows = control_of_file
    tie_obs = manual_tie_obs(tie_rows, names, notes, log)
    vet = _merged_vetting(good, core_of) if rows else None
    target_obs: dict = {}
    if vet is not None:
        control = vet.control_points(control)
        used = {n for n, p in vet.points.items() if p.role == 'gcp' and p.use in ('full', 'horizontal')}
        target_obs = {img: {n: uv for n, uv in obs.items() if n in used} for img, obs in vet.accepted_uv().items()}
        target_obs = {k: v for k, v in target_obs.items() if v}
    n_gcps = (sum(p.role == 'gcp' and p.use == 'full' for p in vet.points.values()) if vet is not None else
              sum(c.role == 'gcp' for c in control))
    return control, vet, target_obs, tie_obs, n_gcps


def _global_refine(block: KeyframeBlock, opt: TriangulateOptions, good: list, n_gcps: int, notes: list):
    """(intrinsics refined, stepwise, the sub-blocks' choice or None) of the global adjustment."""
    refine = opt.refine(block, n_gcps, notes)
    stepwise = opt.self_calibrate is None
    chosen = sub_blocks_selection(good, refine) if stepwise and refine else None
    if chosen is not None:
        refine, stepwise = chosen, False
        notes.append(f'self-calibration of the global adjustment: {", ".join(refine) or "none"} refined; the '
                     'distortion held at the sub-blocks\' photo-weighted mean, as their stepwise selections determined '
                     'it (' + '; '.join(f'sub-block {r.sub.index} kept '
                                        f'{", ".join(r.report["self_calibration_selection"]["kept"]) or "none"}'
                                        for r in good) + ')')
    return refine, stepwise, chosen


def split_merge_block(block: KeyframeBlock, out: str | Path, opt: TriangulateOptions, runner, log=None,
                      t0: float | None = None, steps: Steps | None = None) -> TriangulateResult:
    """A photo block above opt.split.split_photos photos: overlapping sub-blocks (core/split_merge.py
    partition), each adjusted by adjust_sub_block as one task of `runner` (io/dask_cluster.py; its
    report in out/sub_blocks/NN), merged (core/split_merge.py merge), then adjusted as one block from the merged
    poses and tie points (`_global_adjustment`, when opt.split.global_adjustment) and written as adjust_block
    writes one; without the global adjustment (off, or it did not finish) the merged block itself is written
    (`_write_merged`). Either is checked as one block: the block check of the merged cameras, with the merge's
    findings (a failed sub-block, an overlap that disagrees) and each sub-block's own verdict beside it."""
    from photogram_ros.core.split_merge import merge, partition
    t0 = t0 if t0 is not None else time.monotonic()
    steps = steps or Steps('triangulate', None, None)
    out = Path(out)
    sm = opt.split
    # The control file read once: its points and rows for the global adjustment, its CRS for the output.
    control = control_rows(block, opt, None, block.origin)
    crs = opt.crs or control[3] or f'EPSG:{utm_epsg(block.origin.lat_deg, block.origin.lon_deg)}'
    pos = _geotag_positions(block)
    part = partition(pos, sm)
    steps.start(f'split-merge: {len(block.records)} photos in {part.n} overlapping sub-blocks')
    if log is not None:
        log(f'split-merge: {len(block.records)} photos > {sm.split_photos}: {part.n} sub-blocks of '
            f'{", ".join(str(len(m)) for m in part.members)} photos (overlap radius {part.overlap_m:.1f} m)')
    t_at = time.monotonic()
    calls = [(k, _sub_block(block, m), out / 'sub_blocks' / f'{k:02d}', opt) for k, m in enumerate(part.members)]
    runs = runner.run(adjust_sub_block, calls, 'sub-blocks')
    t_merge = time.monotonic()
    steps.start('merging the sub-blocks')
    core_of = {r.name: int(part.labels[i]) for i, r in enumerate(block.records)}
    mr = merge([r.sub for r in runs], sm, core_of)
    checks_rep, ck = _merged_checks(runs, mr, log)
    findings = _merge_findings(runs, mr)
    sm_rep = _split_merge_figures(runs, part, mr, ck)
    glob, why = None, ''
    t_global = time.monotonic()
    if sm.global_adjustment and mr.map_T_cam:
        steps.start(f'global adjustment of the merged block ({len(mr.map_T_cam)} photos)')
        glob, why = _try_global_adjustment(block, mr, runs, core_of, opt, control, log)
    timing = {'sub_blocks': round(t_merge - t_at, 2), 'merge': round(t_global - t_merge, 2),
              'global_adjustment': round(time.monotonic() - t_global, 2)}
    if glob is not None:
        return _write_global(block, out, opt, crs, glob, runs, part, mr, sm_rep, findings, timing, t0, t_at, steps,
                             log)
    if why:
        findings.append(Finding('global_adjustment', 'warning', f'the global adjustment after the merge did '
                                f'not finish ({why}): the merged block without it is the result'))
        if log is not None:
            log(f'warning: split-merge: the global adjustment did not finish ({why})')
    merged = _Merged(runs, part, mr, pos, ck, checks_rep, sm_rep, why)
    return _write_merged(block, out, opt, crs, merged, findings, timing, t0, t_at, steps, log)


def _geotag_positions(block: KeyframeBlock) -> np.ndarray:
    """(N, 3) map ENU (m) of each photo's geotag, NaN without one."""
    pos = np.full((len(block.records), 3), np.nan)
    for i, r in enumerate(block.records):
        if r.fix is not None:
            pos[i] = block.origin.geodetic_to_enu(r.fix.lat_deg, r.fix.lon_deg, r.fix.h_m)
    return pos


def _merged_checks(runs: list, mr, log=None) -> tuple[list, dict]:
    """The merged block's check points (each the mean of its sub-blocks' copies) against their surveys: (rows as
    the report lists them, their RMSE)."""
    surveyed = {p['name']: p['surveyed_map_m'] for r in runs for p in r.report.get('check', {}).get('points', [])}
    checks_rep = [{'name': name, 'residual_m': (X - np.asarray(surveyed[name])).tolist(), 'images': n_img,
                   'reprojection_rms_px': None, 'surveyed_map_m': surveyed[name]}
                  for name, (X, n_img) in sorted(mr.checks.items())]
    ck = rmse_xyz(np.array([c['residual_m'] for c in checks_rep]))
    if log is not None and ck.get('n'):
        log(f'split-merge: merged block\'s check points {ck["horizontal_m"] * 100:.2f} / '
            f'{ck["vertical_m"] * 100:.2f} cm (H / V, n={ck["n"]}) before the global adjustment')
    return checks_rep, ck


def _merge_findings(runs: list, mr) -> list:
    """The merge's findings and each sub-block's warning (core/block_check.py Finding)."""
    return list(mr.findings) + [Finding('sub_block', 'warning', f'sub-block {r.sub.index}: {r.sub.summary}')
                                for r in runs if r.sub.status == 'warning']


def _split_merge_figures(runs: list, part, mr, ck: dict) -> dict:
    """The report's `split_merge`: each sub-block, the overlaps, the similarities, the merged check points."""
    return {'sub_blocks': [{'index': r.sub.index, 'photos': len(r.sub.names), 'oriented': len(r.sub.map_T_cam),
                            'status': r.sub.status, 'summary': r.sub.summary, 'wall_s': round(r.wall_s, 2),
                            'cpu_s': round(r.cpu_s, 2), 'check_rmse': r.report.get('check', {}).get('rmse'),
                            'camera': r.report.get('camera')} for r in runs],
            'overlap_radius_m': part.overlap_m, 'overlaps': mr.overlaps, 'left_out': mr.left_out,
            'similarities': [None if s is None else {'scale': s.scale, 'R': s.R.tolist(), 't_m': s.t.tolist()}
                             for s in mr.similarities],
            'merged_check_rmse': ck}


def _try_global_adjustment(block: KeyframeBlock, mr, runs: list, core_of: dict, opt: TriangulateOptions,
                           control: tuple, log=None) -> tuple[dict | None, str]:
    """(`_global_adjustment`'s result, '') or (None, why it did not finish)."""
    from photogram_ros.errors import PhotogramError
    glob, why = None, ''
    try:
        glob = _global_adjustment(block, mr, runs, core_of, opt, control, log)
    except (PhotogramError, np.linalg.LinAlgError, ValueError) as e:
        why = f'it stopped: {e}'
    if glob is not None and glob['rep_adj'].status == 'failed':
        why, glob = f'its solver failed ({glob["figures"]["solves"]} solves)', None
    return glob, why


def _write_global(block: KeyframeBlock, out: Path, opt: TriangulateOptions, crs: str, glob: dict, runs: list, part, mr,
                  sm_rep: dict, findings: list, timing: dict, t0: float, t_at: float, steps: Steps,
                  log=None) -> TriangulateResult:
    """The globally adjusted block written as adjust_block writes one (io/aerial_triangulation.py finish_block),
    with the split-merge figures and assumptions."""
    sm = opt.split
    sm_rep['global_adjustment'] = glob['figures']
    gf = glob['figures']
    mv = gf['camera_moves']
    block.assumptions.append(
        f'split-merge adjustment: {len(block.records)} photos (more than {sm.split_photos}) in {part.n} overlapping '
        f'sub-blocks (k-means of the geotags, overlap radius {part.overlap_m:.1f} m), each adjusted on its own '
        'GNSS and the GCPs it sees (its report in sub_blocks/NN), merged by one similarity each over all overlaps '
        '(shared cameras and tie points); then one global adjustment of the whole block (every photo\'s GNSS, '
        'the GCPs, the self-calibration) from the merged poses, tie points and the sub-blocks\' mean camera: '
        f'{gf["solves"]} solves, {gf["iterations"]} iterations, {gf["wall_s"]:.0f} s; it moved the cameras '
        f'{mv.get("centre_rms_m", 0.0) * 100:.1f} cm RMS (max {mv.get("centre_max_m", 0.0) * 100:.1f} cm) and '
        f'{mv.get("attitude_rms_deg", 0.0):.3f} deg RMS. Control rows and points as each photo\'s own sub-block '
        'vetted them against its GNSS-only adjustment')
    block.assumptions.extend(_sub_block_lines(runs))
    extra = {'split_merge': sm_rep,
             'verdict_figures': {'split_merge': {'sub_blocks': part.n, 'overlaps': mr.overlaps,
                                                 'left_out': mr.left_out, 'global_adjustment': gf['status']}},
             'timing_s': timing}
    return finish_block(block, out, opt, glob['at'], glob['rep_adj'], glob['refine'], glob['control'],
                        glob['vetting'], None, crs, t0, t_at, steps, log, findings, extra)[0]


def _sub_block_lines(runs: list) -> list[str]:
    """One assumption line per sub-block: its photos, how many oriented, its time and verdict."""
    return [f'sub-block {r.sub.index}: {len(r.sub.names)} photos, {len(r.sub.map_T_cam)} oriented, '
            f'{r.wall_s:.0f} s; {r.sub.summary or r.sub.status}' for r in runs]


@dataclass
class _Merged:
    """The merged block without a global adjustment, as `_write_merged` writes it."""
    runs: list
    part: object                # core/split_merge.py Partition
    mr: object                  # core/split_merge.py MergeResult
    pos: np.ndarray             # (N, 3) geotags, map ENU m
    ck: dict                    # the merged check points' RMSE
    checks_rep: list
    sm_rep: dict
    why: str                    # why there is no global adjustment ('' when it was off)


def _write_merged(block: KeyframeBlock, out: Path, opt: TriangulateOptions, crs: str, m: _Merged, findings: list,
                  timing: dict, t0: float, t_at: float, steps: Steps, log=None) -> TriangulateResult:
    """The merged block itself as the result: each photo's figures from the sub-block its pose came from, the
    block check of the merged cameras, poses, sparse cloud and report."""
    per_image, gcp_rows = _merged_per_image(m.runs, m.mr)
    inputs, adj = _merged_inputs(block, m)
    verdict = with_findings(check_block(inputs), findings)
    verdict.figures['split_merge'] = {'sub_blocks': m.part.n, 'overlaps': m.mr.overlaps, 'left_out': m.mr.left_out,
                                      'global_adjustment': 'failed' if m.why else 'off'}
    if log is not None and verdict.status != 'ok':
        log(f'warning: block check: {verdict.summary}')
    steps.start('writing the poses, the sparse cloud and the report')
    names = [r.name for r in block.records]
    oriented = [nm for nm in names if nm in m.mr.map_T_cam]
    assumptions = list(block.assumptions)
    P = write_poses_and_cloud(out, oriented, [m.mr.map_T_cam[nm] for nm in oriented], m.mr.points_map_m,
                              block.origin, crs, assumptions, opt.heights)
    assumptions.extend(_merged_assumptions(block, opt, m))
    rep = _merged_report(block, m, per_image, gcp_rows, oriented, assumptions, verdict, crs, adj)
    now = time.monotonic()
    rep['timing_s'] = {'reading_and_matching': round(t_at - t0, 2), 'aerial_triangulation': round(now - t_at, 2),
                       **timing, 'total': round(now - t0, 2)}
    if block.stats:
        rep['matching'] = block.stats
    rep.update(heights_keys(crs, opt.heights))
    write_report(rep, out)
    steps.finish()
    return TriangulateResult(out, rep, len(oriented), block.n_inputs or len(names), len(P), [], rep['verdict'])


def _merged_per_image(runs: list, mr) -> tuple[list, dict]:
    """(per-image rows, GCP rows by name) of the merged block: each photo's from the sub-block its pose came from,
    each GCP's from the sub-block that saw it in the most images."""
    per_image, gcp_rows = [], {}
    for r in runs:
        k = r.sub.index
        for p in r.report.get('per_image', []):
            if mr.source.get(p['image']) == k:
                q = dict(p)
                q['position_map_m'] = [float(v) for v in mr.map_T_cam[p['image']][:3, 3]]
                q['sub_block'] = k
                per_image.append(q)
        for g in r.report.get('gcp', {}).get('points', []):
            if g.get('residual_m') is not None and g['images'] > gcp_rows.get(g['name'], {}).get('images', -1):
                gcp_rows[g['name']] = dict(g, sub_block=k)
    return per_image, gcp_rows


def _merged_inputs(block: KeyframeBlock, m: _Merged):
    """(core/block_check.py BlockInputs of the merged cameras, the adjustment's {'status'}): each photo's fix,
    sigma and ground height from the sub-block its pose came from."""
    from photogram_ros.core.block_check import BlockInputs
    runs, mr, sims = m.runs, m.mr, m.mr.similarities
    names = [r.name for r in block.records]
    n = len(names)
    T = np.full((n, 4, 4), np.nan)
    fix, sig, gz = np.full((n, 3), np.nan), np.full((n, 2), np.nan), np.full(n, np.nan)
    by_run = {r.sub.index: r for r in runs}
    for i, name in enumerate(names):
        if name in mr.map_T_cam:
            T[i] = mr.map_T_cam[name]
        k = mr.source.get(name, int(m.part.labels[i]))
        inp = by_run[k].inputs if k in by_run else None
        j = inp.names.index(name) if inp is not None and name in inp.names else None
        if j is not None:
            fix[i], sig[i] = inp.fix_enu_m[j], inp.fix_sigma_hv_m[j]
            if np.isfinite(inp.ground_z_m[j]) and sims[k] is not None:
                gz[i] = sims[k].apply(np.array([[*inp.map_T_cam[j, :2, 3], inp.ground_z_m[j]]]))[0, 2]
        elif np.isfinite(m.pos[i]).all():
            fix[i] = m.pos[i]
    statuses = [r.report.get('adjustment_status', 'failed') for r in runs if r.inputs is not None]
    adj = {'status': 'failed' if not statuses else
           next((s for s in statuses if s in ('failed', 'diverged')), statuses[0])}
    ck = m.ck
    inputs = BlockInputs(names, T, fix, sig, gz, _merged_gnss_noise(runs), adj, block.expect_nadir,
                         block.n_inputs or n, dict(block.excluded),
                         (ck['horizontal_m'], ck['vertical_m'], ck['n']) if ck.get('n') else None)
    return inputs, adj


def _merged_assumptions(block: KeyframeBlock, opt: TriangulateOptions, m: _Merged) -> list[str]:
    """What the merged block without a global adjustment assumes, and each sub-block's line."""
    return [f'split-merge adjustment: {len(block.records)} photos (more than {opt.split.split_photos}) in '
            f'{m.part.n} overlapping sub-blocks (k-means of the geotags, overlap radius {m.part.overlap_m:.1f} m), '
            'each adjusted on its own GNSS and the GCPs it sees (its report in sub_blocks/NN), merged by one '
            'similarity each over all overlaps (shared cameras and tie points); each photo\'s pose from its own '
            'sub-block, tie and check points averaged over their copies; no global adjustment after the merge '
            f'({m.why or "split.global_adjustment off"}). Each sub-block self-calibrates its own camera: the camera '
            'here is sub-block 0\'s; check points are intersected in each sub-block with its camera',
            *_sub_block_lines(m.runs)]


def _merged_report(block: KeyframeBlock, m: _Merged, per_image: list, gcp_rows: dict, oriented: list,
                   assumptions: list, verdict, crs: str, adj: dict) -> dict:
    """report.json of the merged block without a global adjustment (its timing added by the caller)."""
    obs = [p['observations'] for p in per_image]
    rms = [p['reprojection_rms_px'] for p in per_image]
    tot = sum(o for o, x in zip(obs, rms) if x is not None)
    rms_px = (float(np.sqrt(sum(o * x * x for o, x in zip(obs, rms) if x is not None) / tot)) if tot else None)
    gres = np.array([p['gnss_residual_enu_m'] for p in per_image if p['gnss_residual_enu_m'] is not None])
    gcps = sorted(gcp_rows.values(), key=lambda g: g['name'])
    r0 = next((r.report for r in m.runs if r.report), {})
    return {
        'format': 'photogram_ros aerial triangulation report v1',
        'origin': block.origin.to_dict(),
        'frame': 'map: ENU at origin (x east, y north, z up), m; heights ellipsoidal',
        'georeferenced': True, 'keyframes': len(block.records), 'registered': len(oriented),
        'points': int(len(m.mr.point_ids)),
        'observations': int(sum(obs)), 'camera': r0.get('camera', {}), 'reprojection_rms_px': rms_px,
        'gnss': {'rmse': gnss_figures(gres), 'estimated_bias_enu_m': [0.0, 0.0, 0.0]},
        'gcp': {'points': gcps, 'rmse': rmse_xyz(np.array([g['residual_m'] for g in gcps])), 'redundancy': []},
        'check': {'points': m.checks_rep, 'rmse': m.ck,
                  'ce90_le90': ce90_le90(np.array([c['residual_m'] for c in m.checks_rep]))},
        'mtp': {'points': []},
        'reprojection_histogram': {'n': 0, 'counts': [], 'edges_px': []},
        'per_image': per_image, 'assumptions': assumptions, 'verdict': verdict.to_dict(), 'crs': crs,
        'adjustment_status': adj['status'],
        'split_merge': m.sm_rep,
    }
