"""Offline aerial triangulation of a flight bag or a photo folder, and its outputs.

`triangulate(input, out, options)` reads the keyframes (io/bag_keyframes.py for a bag,
io/photo_block.py for a folder of photos), adds the control (the flight's ArUco targets file for a
bag, or an OpenDroneMap gcp_list.txt), runs the incremental aerial triangulation
(core/incremental.py) keyframe by keyframe, gives the photos that did not register in sequence a
second chance against the whole block, makes a full adjustment (self-calibrating the intrinsics
asked for), and writes into `out`:
- poses.csv: each oriented image in the output CRS and WGS84, omega-phi-kappa (io/trajectory.py);
- sparse.ply and sparse.las: the tie points, ellipsoidal heights;
- report.md/.html/.json: the adjustment's figures (core/at_report.py) and every assumption made.
The output CRS is the one asked for, else the GCP file's, else the UTM zone of the origin.

A photo folder of more than `options.split.split_photos` photos is adjusted by split-merge
(`split_merge_block`): overlapping sub-blocks (core/split_merge.py), each adjusted as above as one
task of the runner (a Dask cluster with --workers/--scheduler; each sub-block's own outputs in
out/sub_blocks/NN), merged into one block by a similarity per sub-block, checked as one block.

Progress (io/progress.py) goes to `progress(text)`: each step as it starts, and the photos of the
features, the pairs of the matching and the photos added to the incremental adjustment counted with a
percent and an ETA; split-merge counts the sub-blocks done across the cluster.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from photogram_ros.core.block_check import check_block, inputs_from_at
from photogram_ros.core.at_report import (build_report, convergence, focal_determination, gnss_figures,
                                        intrinsics_sigma)
from photogram_ros.core.control import ControlRow, ControlVettingOptions, unchecked_vetting, vet_control
from photogram_ros.io.at_report import write_report
from photogram_ros.core.geodesy import LocalFrame, utm_epsg
from photogram_ros.core.incremental import (DISTORTION_TERMS, PASS_GROWTH_RATIO, SELF_CALIBRATION_BASE, IncrementalAT,
                                           IncrementalOptions)
from photogram_ros.core.photo_matching import MatchingOptions
from photogram_ros.core.split_merge import SplitMergeOptions
from photogram_ros.core.triangulation import near_the_cameras
from photogram_ros.errors import ConfigError
from photogram_ros.io.export import GeoCloud, enu_to_crs, write_las, write_ply
from photogram_ros.io.keyframe_block import KeyframeBlock
from photogram_ros.io.progress import Progress, Steps, sayer
from photogram_ros.io.trajectory import POSES_COLUMNS, write_trajectory_csv


@dataclass
class TriangulateOptions:
    camera: str | None = None                 # calibration YAML; default: the bag's camera_info / the EXIF
    targets: str | None = None                # a bag's control file of ArUco targets (io/control_file.py)
    gcp: str | None = None                    # OpenDroneMap gcp_list.txt (its MTP* rows: manual tie points)
    mtp: str | None = None                    # manual tie points: "px py image name" rows (io/control_file.py)
    check_names: tuple = ()                   # check points besides CHK*
    crs: str | None = None                    # output CRS
    gcp_sigma_enu_m: tuple = (0.02, 0.02, 0.03)
    neighbours: int = 8                       # photos matched with each photo
    window: int = 10                          # sliding-window size
    lever_arm_cam_m: tuple = (0.0, 0.0, 0.0)  # antenna in the camera frame
    # Intrinsics refined in the final adjustment ('f', 'k1', ...); None: automatic (`auto_self_calibration`).
    self_calibrate: tuple | None = None
    matching: MatchingOptions = field(default_factory=MatchingOptions)   # photos: features and matching
    exif_altitude: str | None = None          # 'msl', 'ellipsoidal', 'relative' or None (msl, checked)
    takeoff_h_m: float | None = None          # for exif_altitude 'relative'
    takeoff_heights: str = 'msl'              # reference of takeoff_h_m: 'msl' or 'ellipsoidal'
    vetting: ControlVettingOptions = field(default_factory=ControlVettingOptions)   # control rows and heights
    workers: int = 1                          # photos: local Dask worker processes (1: this process, no Dask)
    scheduler: str | None = None              # photos: an existing Dask cluster, tcp://HOST:PORT
    # photos: blocks above split.split_photos adjusted as overlapping sub-blocks and merged; None: never split
    split: SplitMergeOptions | None = field(default_factory=SplitMergeOptions)

    def check(self) -> None:
        from photogram_ros.params import from_dict
        from_dict(IncrementalOptions, {'window_size': self.window}, 'triangulate --window')   # its declared range
        if self.takeoff_h_m is not None and self.exif_altitude != 'relative':
            raise ConfigError('--takeoff-altitude-m is only used with --exif-altitude relative (EXIF altitudes '
                              'above the take-off point): add that, or drop --takeoff-altitude-m')
        if self.exif_altitude == 'relative' and self.takeoff_h_m is None:
            raise ConfigError('--exif-altitude relative needs the take-off point\'s height: --takeoff-altitude-m H '
                              '(m above mean sea level; add --takeoff-heights ellipsoidal for a WGS84 height)')


@dataclass
class TriangulateResult:
    out: Path
    report: dict                # report.json's figures
    registered: int             # images oriented
    inputs: int                 # images given
    tie_points: int
    damage: list = field(default_factory=list)   # a damaged bag: what was read and lost (exit 3)
    verdict: dict = field(default_factory=dict)  # core/block_check.py BlockVerdict.to_dict()


# Labels and units of the photo block's jobs (io/photo_block.py's names for them).
PHOTO_JOBS = {'features': ('features', 'photos'), 'matching pairs': ('matching', 'pairs'),
              'matching more pairs for weakly linked photos': ('matching more pairs for weakly linked photos',
                                                               'pairs'),
             'sub-blocks': ('adjustment of the sub-blocks', 'sub-blocks')}


class CountedRunner:
    """A runner of io/dask_cluster.py whose named jobs report through io/progress.py (percent and ETA,
    to `say`; None: silent) instead of the runner's own lines."""

    def __init__(self, runner, say):
        self.runner, self.say = runner, say
        self.workers, self.where = runner.workers, runner.where

    def run(self, fn, calls, what=None, log=None, keep=False, on_result=None, extra=None) -> list:
        calls = list(calls)
        if what is None or self.say is None:
            return self.runner.run(fn, calls, None, None, keep, on_result)
        label, unit = PHOTO_JOBS.get(what, (what, 'pieces'))
        where = f' on {self.workers} workers{self.where}' if self.workers > 1 else ''
        prog = Progress(f'triangulate: {label}{where}', len(calls), unit, self.say)

        text = (lambda: extra().lstrip(', ')) if extra else ''   # extra(): ', 12 verified'

        def counted(k, result):
            if on_result is not None:
                on_result(k, result)
            prog.add(1, text)

        out = self.runner.run(fn, calls, None, None, keep, counted)
        prog.finish(text)
        return out

    def release(self, handles) -> None:
        self.runner.release(handles)


def triangulate(src: str | Path, out: str | Path, opt: TriangulateOptions, log=None,
                progress=True) -> TriangulateResult:
    """Aerial triangulation of the bag or photo folder `src` into the folder `out` (see the module
    docstring); log(text): warnings and what was read; progress: True (progress lines to `log`), False
    (none) or a say(text) function for them."""
    opt.check()
    t0 = time.monotonic()
    src = Path(src)
    control_set = None
    say = sayer(progress, log)
    steps = Steps('triangulate', None, say)
    if (src / 'metadata.yaml').exists():
        steps.start('reading the bag\'s keyframes')
        from photogram_ros.io.bag_keyframes import read_bag_keyframes
        from photogram_ros.io.control_file import read_control_file
        if opt.targets:
            control_set = read_control_file(opt.targets, opt.check_names)
        block = read_bag_keyframes(src, opt.camera, control_set, log)
        if opt.exif_altitude:
            block.assumptions.append(f'--exif-altitude {opt.exif_altitude} ignored: a bag has no EXIF')
        if opt.workers != 1 or opt.scheduler:
            block.assumptions.append('--workers/--scheduler ignored: a bag\'s keyframes are read in this process')
    else:
        from photogram_ros.io.dask_cluster import open_runner
        from photogram_ros.io.photo_block import read_photo_block
        steps.start('features and matching of the photos')
        gcp_origin = None
        if opt.gcp:
            from photogram_ros.io.control_file import read_gcp_list
            gcp_origin = read_gcp_list(opt.gcp, opt.check_names).central_origin()
        with open_runner(opt.workers, opt.scheduler, log) as runner:
            counted = CountedRunner(runner, say)
            block = read_photo_block(src, opt.camera, opt.neighbours, opt.exif_altitude, opt.takeoff_h_m,
                                     opt.takeoff_heights, log, opt.matching, counted, gcp_origin)
            if opt.split is not None and len(block.records) > opt.split.split_photos:
                if any(r.fix is not None for r in block.records):
                    return split_merge_block(block, out, opt, counted, log, t0, steps)
                block.assumptions.append('not split into sub-blocks: without positions the photos cannot be '
                                         'grouped, the block is adjusted whole')
    return adjust_block(block, out, opt, control_set, log, t0, steps=steps)


def _self_calibration(at: IncrementalAT, before, refine: tuple, assumptions: list, log=None) -> dict:
    """The refined intrinsics before and after, with their a-posteriori sigmas and correlations with the
    block's height; a focal length the block does not determine is said so, with no sigma."""
    after = at.camera
    self_cal = {k: {'before': float(getattr(before, k)), 'after': float(getattr(after, k))}
                for k in ('fx', 'fy', 'cx', 'cy')}
    self_cal.update({n: {'before': before.dist[i], 'after': after.dist[i]}
                     for i, n in enumerate(('k1', 'k2', 'p1', 'p2', 'k3'))})
    sig = intrinsics_sigma(at, refine)
    corr = sig.get('height_correlation', {})
    for name, v in sig.items():
        if name in ('s0_px', 'height_correlation'):
            continue
        for key in (('fx', 'fy') if name == 'f' else (name,)):
            if key in self_cal:
                self_cal[key]['sigma'] = v
                if name in corr:
                    self_cal[key]['height_correlation'] = corr[name]
    if 's0_px' in sig:
        self_cal['s0_px'] = sig['s0_px']
    sf = f" +- {sig['f']:.2f}" if 'f' in sig else ''
    focal = focal_determination(at, sig)
    if focal:
        self_cal['focal'] = focal
    if focal.get('determined') is False:
        for key in ('fx', 'fy'):
            self_cal[key]['sigma_unreliable'] = self_cal[key].pop('sigma', None)
        sf = ' (not determined)'
        note = (f'focal length NOT DETERMINED by this block: {focal["reason"]}; the focal and the ground\'s '
                f'depth trade off (correlation of f with the block\'s height {corr["f"]:+.3f}; the covariance\'s '
                f'{sig["f"]:.1f} px sigma hides it): fx {before.fx:.1f} -> {after.fx:.1f} px is not a measurement. '
                'Keep f fixed (drop f from --self-calibrate), or add GCPs with surveyed heights or oblique photos')
        assumptions.append(note)
        if log is not None:
            log(f'warning: {note}')
    elif focal:
        sf += f' (determined {focal["reason"]}; correlation with the block\'s height {corr["f"]:+.3f})'
    parts = [f'fx {before.fx:.2f} -> {after.fx:.2f}{sf} px'] if 'f' in refine else []
    parts += [f'{n} {getattr(before, n):.2f} -> {getattr(after, n):.2f}' + (f' +- {sig[n]:.2f}' if n in sig else '')
              + ' px' for n in ('cx', 'cy') if n in refine]
    for i, n in enumerate(('k1', 'k2', 'p1', 'p2', 'k3')):
        if n in refine:
            parts.append(f'{n} {before.dist[i]:.5f} -> {after.dist[i]:.5f}'
                         + (f' +- {sig[n]:.5f}' if n in sig else ''))
    assumptions.append(f'self-calibration of {", ".join(refine)} in the final adjustment: {"; ".join(parts)} '
                       '(sigmas a posteriori, scaled by the variance of unit weight; parameters not refined have none)')
    return self_cal


PRECISE_GEOTAG_SIGMA_H_M = 0.1   # geotags stated this good (RTK, PPK) hold the cameras where they were


def auto_self_calibration(block: KeyframeBlock, n_gcps: int, assumptions: list) -> tuple:
    """What `--self-calibrate auto` refines: nothing for a calibrated camera; for a camera from the EXIF
    (distortion unknown, taken as zero; principal point at the image centre) k1 and k2; f as well with 3 or
    more GCPs and cameras with a fix (the GCPs' heights fix the ground's depth below the cameras' own; without
    either the focal of a near-nadir block trades off with its depth); and the principal point (cx, cy) when the geotags are RTK/PPK-precise (median stated horizontal
    sigma <= PRECISE_GEOTAG_SIGMA_H_M): with the cameras held where they were, a principal point off by
    d px moves the ground by height x d / f, the other way on each flight line flown the other way."""
    if not block.camera_from_exif:
        return ()
    with_fix = sum(r.fix is not None for r in block.records)
    refine = ('f', 'k1', 'k2') if n_gcps >= 3 and with_fix >= 3 else ('k1', 'k2')
    if 'f' in refine:
        why = f'f too: {n_gcps} GCPs give the ground\'s depth below the geotagged cameras'
    elif with_fix >= 3:
        why = 'f held at its EXIF value: without 3 GCPs with heights a near-nadir block does not determine it'
    else:
        why = ('f held at its EXIF value: without geotags the cameras\' heights trade off with it (the GCPs fix '
               'the ground, not how far above it the cameras are)')
    sig_h = [float(np.sqrt(0.5 * (r.fix.cov_enu_m2[0][0] + r.fix.cov_enu_m2[1][1]))) for r in block.records
             if r.fix is not None]
    if sig_h and float(np.median(sig_h)) <= PRECISE_GEOTAG_SIGMA_H_M:
        refine += ('cx', 'cy')
        why += (f'; the principal point too: the geotags are precise ({np.median(sig_h) * 100:.1f} cm stated, '
                'median) and hold the cameras')
    assumptions.append(f'self-calibration (auto): the EXIF gives no distortion, so {", ".join(refine)} are candidates '
                       '(a distortion term is kept only when it pays: see the selection); '
                       f'{why} (--self-calibrate none or a list to choose)')
    return refine


def _triangulate_records(block: KeyframeBlock, opt: TriangulateOptions, control: list, target_obs: dict,
                         refine: tuple, log=None, what: str = '', tie_obs: dict | None = None,
                         steps: Steps | None = None) -> tuple[IncrementalAT, object]:
    """One incremental AT of the block's records (target observations `target_obs` and manual tie points
    `tie_obs` by photo name), the unregistered photos retried, and the full adjustment refining `refine`:
    (at, its StepReport). `steps`: where its steps and the photos added are said."""
    steps = steps or Steps('triangulate', None, None)
    lever = tuple(opt.lever_arm_cam_m)
    tie_obs = tie_obs or {}
    ties = {n for obs in tie_obs.values() for n in obs}
    # The distortion to be refined is refined in the pass too, at each 1.5-fold growth of the block: an uncalibrated
    # lens bends a long block away from its geotags (bench/notes_photo_triangulation_scale.md).
    in_pass = tuple(t for t in refine if t in DISTORTION_TERMS)
    at = IncrementalAT(block.camera, IncrementalOptions(
        window_size=opt.window, lever_arm_cam_m=lever, pass_self_calibration=','.join(in_pass),
        growth_ratio=PASS_GROWTH_RATIO if in_pass else 0.0), block.origin, control, ties=ties)
    added = steps.progress(f'aerial triangulation{what}', len(block.records), 'photos added')
    oriented = (lambda: f'{len(at.registered)} oriented')
    for rec in block.records:
        rec.target_uv = {**target_obs.get(rec.name, {}), **tie_obs.get(rec.name, {})}
        at.add_keyframe(rec)
        added.add(1, oriented)
    added.finish(oriented)
    n_retry = at.retry_unregistered()     # photos that did not register in sequence: a second chance
    if log is not None and n_retry:
        log(f'aerial triangulation{what}: {n_retry} more oriented against the whole block')
    t_full = time.monotonic()
    steps.start(f'full adjustment{what}')
    rep_adj = at.full_adjustment(refine_intrinsics=refine, stepwise=opt.self_calibrate is None)
    if log is not None:
        log(f'full adjustment{what}{" with self-calibration of " + ", ".join(refine) if refine else ""}: '
            f'{rep_adj.status}, {time.monotonic() - t_full:.1f} s')
    return at, rep_adj


def _control_rows(block: KeyframeBlock, opt: TriangulateOptions, control_set, origin):
    """(control points, rows, heights as written, CRS, manual tie point rows) of a bag's targets (their
    detections in the records) or of opt.gcp, and the MTPs of opt.gcp and opt.mtp."""
    from photogram_ros.io.control_file import read_gcp_list, read_tie_list
    ties = read_tie_list(opt.mtp) if opt.mtp else []
    if control_set is not None:
        rows = [ControlRow(0, rec.name, n, np.asarray(uv, float)) for rec in block.records
                for n, uv in rec.target_uv.items()]
        return control_set.in_map(origin), rows, {}, None, ties
    if opt.gcp:
        gcps = read_gcp_list(opt.gcp, opt.check_names)
        return (gcps.in_map(origin, opt.gcp_sigma_enu_m), gcps.rows, gcps.file_heights, gcps.crs,
                gcps.tie_rows + ties)
    return [], [], {}, None, ties


def _tie_obs(rows: list, images: set, assumptions: list, log=None) -> dict:
    """{image: {MTP name: uv}} of the manual tie point rows in photos of the set with points in two or
    more of them; the others are named in the assumptions."""
    from photogram_ros.io.control_file import tie_uv
    obs = tie_uv([r for r in rows if r.image in images])
    missing = sorted({r.image for r in rows if r.image not in images})
    count: dict = {}
    for o in obs.values():
        for n in o:
            count[n] = count.get(n, 0) + 1
    lone = sorted(n for n, c in count.items() if c < 2)
    notes = []
    if missing:
        notes.append(f'{sum(r.image not in images for r in rows)} manual tie point rows name photos not in the set '
                     f'({", ".join(missing[:6])}{", ..." if len(missing) > 6 else ""})')
    if lone:
        notes.append(f'manual tie points in one photo only, not used: {", ".join(lone)}')
    for note in notes:
        assumptions.append(f'control: {note}')
        if log is not None:
            log(f'warning: control: {note}')
    obs = {img: {n: uv for n, uv in o.items() if n not in lone} for img, o in obs.items()}
    used = sorted({n for o in obs.values() for n in o})
    if used:
        assumptions.append(f'{len(used)} manual tie points ({", ".join(used)}) adjusted as tie points measured by '
                           'hand (robust-loss scale of their own, kept through outlier removal; their residuals '
                           'per photo under "Manual tie points")')
    return {img: o for img, o in obs.items() if o}


def adjust_block(block: KeyframeBlock, out: str | Path, opt: TriangulateOptions, control_set=None,
                 log=None, t0: float | None = None, progress=True, steps: Steps | None = None) -> TriangulateResult:
    """Incremental AT of the block's records, a full adjustment, then poses, sparse cloud and report.

    control_set: a bag's ControlSet, whose observations are already in the records; else opt.gcp.
    With control rows the block is first adjusted on its GNSS alone, every row and point is checked
    against it (core/control.py vet_control: rows naming the wrong photo, heights the GNSS contradicts),
    and the block is adjusted again with the control that passed.
    progress: as triangulate()'s; `steps`: the job's Steps so far (then `progress` is not used).
    """
    return _adjust_and_write(block, out, opt, control_set, log, t0, progress, steps)[0]


def _adjust_and_write(block: KeyframeBlock, out: str | Path, opt: TriangulateOptions, control_set=None,
                      log=None, t0: float | None = None, progress=True,
                      steps: Steps | None = None) -> tuple[TriangulateResult, IncrementalAT, object, dict]:
    """adjust_block(), and its adjusted IncrementalAT, BlockInputs and control: {'vetting' (ControlVetting or
    None), 'control' (the ControlPoints as adjusted), 'target_obs' (the GCP observations used, by photo)}."""
    steps = steps or Steps('triangulate', None, sayer(progress, log))
    out = Path(out)
    origin, assumptions = block.origin, block.assumptions
    control, rows, file_heights, gcp_crs, tie_rows = _control_rows(block, opt, control_set, origin)
    tie_obs = _tie_obs(tie_rows, {r.name for r in block.records}, assumptions, log)
    crs = opt.crs or gcp_crs or f'EPSG:{utm_epsg(origin.lat_deg, origin.lon_deg)}'
    t_at = time.monotonic()
    vet, gnss_without, target_obs = None, None, {}
    at = rep_adj = None
    if rows:
        refine0 = (tuple(opt.self_calibrate) if opt.self_calibrate is not None
                   else auto_self_calibration(block, 0, []))
        at, rep_adj = _triangulate_records(block, opt, [], {}, refine0, log, ' (GNSS only, to check the control)',
                                           tie_obs, steps)
        steps.start('checking the control against the GNSS-only block')
        P0 = np.array([at.points[t] for t in at.points if t >= 0]).reshape(-1, 3)
        if at.georeferenced and not at.georef_provisional:
            vet = vet_control(at.camera, {at.kfs[k].name: at.kfs[k].map_T_cam for k in at.registered},
                              {r.name for r in block.records}, rows, control, at.fix_sigma_enu_m(), P0, file_heights,
                              opt.vetting)
        else:   # a single line (its roll about it only the GCPs fix) or no GNSS: nothing to judge the control by
            vet = unchecked_vetting(at.camera, {at.kfs[k].name: at.kfs[k].map_T_cam for k in at.registered},
                                    {r.name for r in block.records}, rows, control, 'the photos\' GNSS does not fix '
                                    'the block (a single line, or too few fixes)', file_heights)
        gnss_without = gnss_figures(np.array(list(at.gnss_residuals().values())))
        control = vet.control_points(control)
        for note in vet.notes:
            assumptions.append(f'control: {note}')
            if log is not None:
                log(f'warning: control: {note}')
        used = {n for n, p in vet.points.items() if p.role == 'gcp' and p.use in ('full', 'horizontal')}
        target_obs = {img: {n: uv for n, uv in obs.items() if n in used} for img, obs in vet.accepted_uv().items()}
        target_obs = {k: v for k, v in target_obs.items() if v}
        if not used:
            at.set_control(control)   # the GNSS-only block is the result: check points from the vetted rows
    n_gcps = sum(p.role == 'gcp' and p.use == 'full' for p in vet.points.values()) if vet else \
        sum(c.role == 'gcp' for c in control)
    refine = (tuple(opt.self_calibrate) if opt.self_calibrate is not None
              else auto_self_calibration(block, n_gcps, assumptions))
    if at is None or target_obs:
        at, rep_adj = _triangulate_records(block, opt, control, target_obs, refine, log, tie_obs=tie_obs, steps=steps)
    res, inputs = _finish_block(block, out, opt, at, rep_adj, refine, control, vet,
                                gnss_without if vet is not None and target_obs else None, crs, t0, t_at, steps, log)
    return res, at, inputs, {'vetting': vet, 'control': control, 'target_obs': target_obs}


def _finish_block(block: KeyframeBlock, out: Path, opt: TriangulateOptions, at: IncrementalAT, rep_adj, refine: tuple,
                  control: list, vet, gnss_without_gcps, crs: str, t0: float | None, t_at: float, steps: Steps,
                  log=None, extra_findings=(), extra: dict | None = None) -> tuple[TriangulateResult, object]:
    """The adjusted block `at` (its final adjustment's StepReport `rep_adj`, the intrinsics it refined) written
    into `out`: poses, sparse cloud, report (with the control vetting `vet`) and the block check, its verdict
    with `extra_findings` (core/block_check.py Finding) beside the check's own; `extra`: more report keys
    (its 'timing_s' added to the report's, its 'verdict_figures' to the verdict's figures). Returns (result,
    the block check's BlockInputs)."""
    origin, assumptions = block.origin, block.assumptions
    before = block.camera
    refine = at.self_calibration.kept if at.self_calibration is not None else refine
    self_cal = _self_calibration(at, before, refine, assumptions, log) if refine else None
    conv = convergence(at, rep_adj.status)
    if conv is not None:
        assumptions.append(conv['text'])
        if log is not None:
            log(f'warning: {conv["text"]}')
    adj = {'status': rep_adj.status, **({'matters': conv['matters'], 'text': conv['text']} if conv else {})}
    for j in at.segment_joins:
        how = (f'through {j["mtps"]} manual tie points' if j['through'] == 'mtp' else
               'through its GNSS alone (no tie point joins it to the rest: its position relative to the block is '
               'only as good as the GNSS; manual tie points across the gap would tie it)')
        assumptions.append(f'a part of {j["keyframes"]} photos that shares no automatic tie point with the rest of the '
                           f'block joined it {how}')
    lost = [kf.name for kf in at.kfs if kf.map_T_cam is None]
    if lost:
        assumptions.append(f'{len(lost)} photos could not be oriented (blurred or without overlap): {lost[:10]}')
    lever = tuple(opt.lever_arm_cam_m)
    assumptions.append('lever arm antenna-camera ' + str(lever) + ' m in the camera frame')
    P = np.array([at.points[t] for t in at.points if t >= 0]).reshape(-1, 3)
    if block.exif_geodetic is not None:
        note = relative_exif_note(origin, P, block.exif_geodetic, _trusted_ground(control, vet))
        if note:
            assumptions.append(note)
            if log is not None:
                log(f'warning: {note}')
    steps.start('writing the poses, the sparse cloud and the report')
    P = _write_poses_and_cloud(out, [at.kfs[k].name for k in at.registered],
                               [at.kfs[k].map_T_cam for k in at.registered], P, origin, crs, assumptions)
    rep = build_report(at, assumptions, vetting=vet, gnss_without_gcps=gnss_without_gcps)
    inputs = inputs_from_at(at, len(block.records), adj, block.expect_nadir, block.excluded)
    ck = rep['check']['rmse']
    if ck.get('n'):
        inputs.check_rmse_hv_m = (ck['horizontal_m'], ck['vertical_m'], ck['n'])
    verdict = _with_findings(check_block(inputs), extra_findings)
    extra = dict(extra or {})
    verdict.figures.update(extra.pop('verdict_figures', {}))
    if log is not None and verdict.status != 'ok':
        log(f'warning: block check: {verdict.summary}')
    rep['verdict'] = verdict.to_dict()
    if at.gnss_noise:
        rep['gnss_noise'] = dict(at.gnss_noise)
    rep['crs'] = crs
    rep['adjustment_status'] = rep_adj.status
    if conv is not None:
        rep['convergence'] = conv
    if block.stats:
        rep['matching'] = block.stats
    if block.damage:
        rep['bag_damage'] = list(block.damage)
    now = time.monotonic()
    rep['timing_s'] = {'reading_and_matching': round(t_at - (t0 if t0 is not None else t_at), 2),
                       'aerial_triangulation': round(now - t_at, 2),
                       'total': round(now - (t0 if t0 is not None else t_at), 2)}
    if self_cal is not None:
        rep['self_calibration'] = self_cal
    rep['timing_s'].update(extra.pop('timing_s', {}))
    rep.update(extra)
    write_report(rep, out)
    steps.finish()
    return (TriangulateResult(out, rep, len(at.registered), block.n_inputs or len(block.records), len(P),
                              list(block.damage), rep['verdict']), inputs)


def _with_findings(verdict, findings) -> object:
    """core/block_check.py BlockVerdict with `findings` added, worst first, its status the worst of all."""
    from photogram_ros.core.block_check import STATUS_ORDER, BlockVerdict
    findings = list(verdict.findings) + list(findings)
    if len(findings) == len(verdict.findings):
        return verdict
    status = 'ok'
    for f in findings:
        status = f.status if STATUS_ORDER.index(f.status) > STATUS_ORDER.index(status) else status
    findings.sort(key=lambda f: -STATUS_ORDER.index(f.status))
    return BlockVerdict(status, findings, dict(verdict.figures))


def _write_poses_and_cloud(out: Path, names: list, map_T_cams: list, P: np.ndarray, origin: LocalFrame, crs: str,
                           assumptions: list) -> np.ndarray:
    """poses.csv of the oriented photos, and sparse.ply / sparse.las of the tie points P (map ENU, m) near
    the cameras (the others are said in the assumptions); returns the points written."""
    out.mkdir(parents=True, exist_ok=True)
    Ts = np.array(map_T_cams).reshape(-1, 4, 4)
    write_trajectory_csv(out / 'poses.csv', POSES_COLUMNS, list(names), Ts, origin, crs)
    near = near_the_cameras(P, Ts[:, :3, 3])
    if not near.all():
        assumptions.append(f'{int((~near).sum())} of {len(P)} tie points lie more than 10 times the usual camera '
                           'distance from every camera (rays almost parallel): left out of sparse.ply / sparse.las')
        P = P[near]
    e, n, h = enu_to_crs(origin, P, crs)
    cloud = GeoCloud(e, n, h, np.full((len(P), 3), 200, np.uint8), np.ones(len(P), np.uint32),
                     np.ones(len(P), np.float32), crs, 'ellipsoidal')
    write_ply(cloud, out / 'sparse.ply')
    write_las(cloud, out / 'sparse.las')
    return P


def _trusted_ground(control: list, vet) -> list:
    """Surveyed points whose heights may stand for the ground in the EXIF-altitude check: those the
    GNSS-only block agrees with, and, when every GCP disagrees by the same amount (the photos' altitudes
    are then the suspect), those too; never heights that look like placeholders."""
    if vet is None:
        return [c.map_xyz for c in control]
    out = []
    for c in control:
        p = vet.points.get(c.name)
        if p is None or p.use == 'unused' or p.placeholder:
            continue
        if p.vertical == 'agrees' or (p.vertical == 'contradicted' and vet.height_suspect == 'photo_altitudes'):
            out.append(c.map_xyz)
    return out


def relative_exif_note(origin: LocalFrame, points_map_m, photos_geodetic, control_map_m=None) -> str | None:
    """The report's warning when EXIF altitudes read as MSL put the ground where no survey is.

    `points_map_m`: adjusted tie points (N, 3) in the map (ENU, m); `photos_geodetic`: (M, 3) lat_deg, lon_deg,
    h_m (ellipsoidal) of the photos from their EXIF as MSL; `control_map_m`: surveyed GCP/check
    points (map ENU), which are the ground when given: a block strained between GCPs and wrong
    photo heights has tie points anywhere.
    """
    from photogram_ros.core import geoid
    from photogram_ros.io import image_source as isrc
    if control_map_m is not None and len(control_map_m):
        P, what = np.asarray(control_map_m, float).reshape(-1, 3), 'median GCP/check point'
    else:
        P, what = points_map_m[np.all(np.isfinite(points_map_m), axis=1)], 'median tie point'
    if not len(P):
        return None
    lat, lon, h = origin.enu_to_geodetic(P)
    ground_msl_m = float(np.median(geoid.ellipsoid_to_msl_m(lat, lon, h)))
    # Back through the same geoid: exactly the EXIF altitudes as written.
    photo_alt_m = float(np.median(geoid.ellipsoid_to_msl_m(*photos_geodetic.T)))
    if not isrc.exif_altitudes_look_relative(ground_msl_m, photo_alt_m):
        return None
    return (f'EXIF altitudes look relative to the take-off point, not MSL: the ground ({what}) is at '
            f'{ground_msl_m:.1f} m MSL and the photos\' EXIF altitude (median) {photo_alt_m:.1f} m '
            f'(rule: ground within {isrc.GROUND_NEAR_SEA_LEVEL_M:.0f} m of 0 m MSL with the photos '
            f'{isrc.MIN_FLYING_HEIGHT_M:.0f} m or more above it, ground below {isrc.GROUND_BELOW_SEA_LEVEL_M:.0f} m '
            'MSL, or photos below the ground). Heights here are then off by about the take-off height (with GCPs, '
            'the whole block is strained): rerun with --exif-altitude relative --takeoff-altitude-m H (the take-off '
            'point\'s height above MSL; add --takeoff-heights ellipsoidal for a WGS84 one), or with '
            '--exif-altitude msl if the site really lies there')


# --- split-merge: a large photo block adjusted as overlapping sub-blocks (core/split_merge.py) ---------------

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
        res, at, inputs, ctl = _adjust_and_write(block, out, opt, None, None, t0, progress=False)
    except (PhotogramError, np.linalg.LinAlgError, ValueError) as e:
        sub = SubBlock(index, names, status='failed', summary=f'FAILED: its adjustment stopped: {e}')
        return SubBlockRun(sub, {}, None, time.monotonic() - t0, time.process_time() - c0)
    ids, P = at.points.arrays()
    keep = ids >= 0                 # tie points (targets have negative ids)
    checks = {p['name']: (np.asarray(p['surveyed_map_m'], float) + np.asarray(p['residual_m'], float), p['images'])
              for p in res.report['check']['points']}
    v = res.verdict
    sub = SubBlock(index, names, {at.kfs[k].name: at.kfs[k].map_T_cam for k in at.registered},
                   np.asarray(ids[keep], np.int64), np.asarray(P[keep], float).reshape(-1, 3), checks,
                   v.get('status', 'ok'), v.get('summary', ''))
    return SubBlockRun(sub, res.report, inputs, time.monotonic() - t0, time.process_time() - c0, at.camera,
                       tuple(float(x) for x in at.gnss_sigma_scale_hv), tuple(float(x) for x in at.gnss_bias_enu),
                       tuple(at.kfs[k].name for k in sorted(at.gnss_rejected)), ctl['vetting'], list(ctl['control']))


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
                       log=None) -> dict:
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
    control, rows, _, _, tie_rows = _control_rows(block, opt, None, block.origin)
    tie_obs = _tie_obs(tie_rows, names, notes, log)
    vet = _merged_vetting(good, core_of) if rows else None
    target_obs: dict = {}
    if vet is not None:
        control = vet.control_points(control)
        used = {n for n, p in vet.points.items() if p.role == 'gcp' and p.use in ('full', 'horizontal')}
        target_obs = {img: {n: uv for n, uv in obs.items() if n in used} for img, obs in vet.accepted_uv().items()}
        target_obs = {k: v for k, v in target_obs.items() if v}
    n_gcps = (sum(p.role == 'gcp' and p.use == 'full' for p in vet.points.values()) if vet is not None else
              sum(c.role == 'gcp' for c in control))
    refine = (tuple(opt.self_calibrate) if opt.self_calibrate is not None
              else auto_self_calibration(block, n_gcps, notes))
    stepwise = opt.self_calibrate is None
    chosen = sub_blocks_selection(good, refine) if stepwise and refine else None
    if chosen is not None:
        refine, stepwise = chosen, False
        notes.append(f'self-calibration of the global adjustment: {", ".join(refine) or "none"} refined; the '
                     'distortion held at the sub-blocks\' photo-weighted mean, as their stepwise selections determined '
                     'it (' + '; '.join(f'sub-block {r.sub.index} kept '
                                        f'{", ".join(r.report["self_calibration_selection"]["kept"]) or "none"}'
                                        for r in good) + ')')
    w = np.array([len(r.sub.map_T_cam) for r in good], float)
    camera = mean_camera([r.camera for r in good], w)
    ties = {n for o in tie_obs.values() for n in o}
    at = IncrementalAT(camera, IncrementalOptions(window_size=opt.window, lever_arm_cam_m=tuple(opt.lever_arm_cam_m),
                                                  spill_frozen=False), block.origin, control, ties=ties)
    tuv = {nm: {**target_obs.get(nm, {}), **tie_obs.get(nm, {})} for nm in names}
    gate_px = opt.split.seed_gate_px if opt.split is not None else None
    seed = at.seed(block.records, mr.map_T_cam, mr.point_ids, mr.points_map_m, tuv, gate_px)
    at.gnss_sigma_scale_hv = np.sum(w[:, None] * np.array([r.gnss_scale_hv for r in good]), axis=0) / w.sum()
    at.gnss_bias_enu = np.sum(w[:, None] * np.array([r.gnss_bias_enu_m for r in good]), axis=0) / w.sum()
    rejected = {n for r in good for n in r.gnss_rejected}
    at.gnss_rejected = {kf.kid for kf in at.kfs if kf.name in rejected}
    if log is not None:
        log(f'split-merge: global adjustment of {seed["oriented"]} photos, {seed["points"]} tie points '
            f'({seed["observations_left_out"]} of {seed["observations"]} observations beyond '
            f'{gate_px or 2 * at.opt.max_reprojection_px:.1f} px of the merged block left out), GCPs {len(seed["gcps"])}'
            + (f', self-calibrating {", ".join(refine)}' if refine else ''))
    n_solves = len(at.solves)
    rep_adj = at.full_adjustment(refine_intrinsics=refine, stepwise=stepwise)
    solves = at.solves[n_solves:]
    after = {at.kfs[k].name: at.kfs[k].map_T_cam for k in at.registered}
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


def split_merge_block(block: KeyframeBlock, out: str | Path, opt: TriangulateOptions, runner, log=None,
                      t0: float | None = None, steps: Steps | None = None) -> TriangulateResult:
    """A photo block above opt.split.split_photos photos: overlapping sub-blocks (core/split_merge.py
    partition), each adjusted by adjust_sub_block as one task of `runner` (io/dask_cluster.py; its
    report in out/sub_blocks/NN), merged (core/split_merge.py merge), and the merged block written as
    adjust_block writes one (poses.csv, sparse.ply/.las, report) and checked as one: the block check of
    the merged cameras, with the merge's findings (a failed sub-block, an overlap that disagrees) and
    each sub-block's own verdict beside it."""
    from photogram_ros.core.at_report import gnss_figures, rmse_xyz
    from photogram_ros.core.block_check import BlockInputs, Finding
    from photogram_ros.core.evaluation import ce90_le90
    from photogram_ros.core.split_merge import merge, partition
    from photogram_ros.errors import PhotogramError
    t0 = t0 if t0 is not None else time.monotonic()
    steps = steps or Steps('triangulate', None, None)
    out = Path(out)
    sm = opt.split
    origin, recs = block.origin, block.records
    pos = np.full((len(recs), 3), np.nan)
    for i, r in enumerate(recs):
        if r.fix is not None:
            pos[i] = origin.geodetic_to_enu(r.fix.lat_deg, r.fix.lon_deg, r.fix.h_m)
    part = partition(pos, sm)
    steps.start(f'split-merge: {len(recs)} photos in {part.n} overlapping sub-blocks')
    if log is not None:
        log(f'split-merge: {len(recs)} photos > {sm.split_photos}: {part.n} sub-blocks of '
            f'{", ".join(str(len(m)) for m in part.members)} photos (overlap radius {part.overlap_m:.1f} m)')
    t_at = time.monotonic()
    calls = [(k, _sub_block(block, m), out / 'sub_blocks' / f'{k:02d}', opt) for k, m in enumerate(part.members)]
    runs = runner.run(adjust_sub_block, calls, 'sub-blocks')
    t_merge = time.monotonic()
    steps.start('merging the sub-blocks')
    core_of = {recs[i].name: int(part.labels[i]) for i in range(len(recs))}
    mr = merge([r.sub for r in runs], sm, core_of)
    sims = mr.similarities
    surveyed = {p['name']: p['surveyed_map_m'] for r in runs for p in r.report.get('check', {}).get('points', [])}
    checks_rep = [{'name': name, 'residual_m': (X - np.asarray(surveyed[name])).tolist(), 'images': n_img,
                   'reprojection_rms_px': None, 'surveyed_map_m': surveyed[name]}
                  for name, (X, n_img) in sorted(mr.checks.items())]
    ck = rmse_xyz(np.array([c['residual_m'] for c in checks_rep]))
    if log is not None and ck.get('n'):
        log(f'split-merge: merged block\'s check points {ck["horizontal_m"] * 100:.2f} / '
            f'{ck["vertical_m"] * 100:.2f} cm (H / V, n={ck["n"]}) before the global adjustment')
    merge_findings = list(mr.findings) + [Finding('sub_block', 'warning', f'sub-block {r.sub.index}: {r.sub.summary}')
                                          for r in runs if r.sub.status == 'warning']
    sm_rep = {'sub_blocks': [{'index': r.sub.index, 'photos': len(r.sub.names), 'oriented': len(r.sub.map_T_cam),
                              'status': r.sub.status, 'summary': r.sub.summary, 'wall_s': round(r.wall_s, 2),
                              'cpu_s': round(r.cpu_s, 2), 'check_rmse': r.report.get('check', {}).get('rmse'),
                              'camera': r.report.get('camera')} for r in runs],
              'overlap_radius_m': part.overlap_m, 'overlaps': mr.overlaps, 'left_out': mr.left_out,
              'similarities': [None if s is None else {'scale': s.scale, 'R': s.R.tolist(), 't_m': s.t.tolist()}
                               for s in sims],
              'merged_check_rmse': ck}
    glob, why = None, ''
    t_global = time.monotonic()
    if sm.global_adjustment and mr.map_T_cam:
        steps.start(f'global adjustment of the merged block ({len(mr.map_T_cam)} photos)')
        try:
            glob = _global_adjustment(block, mr, runs, core_of, opt, log)
        except (PhotogramError, np.linalg.LinAlgError, ValueError) as e:
            why = f'it stopped: {e}'
        if glob is not None and glob['rep_adj'].status == 'failed':
            why, glob = f'its solver failed ({glob["figures"]["solves"]} solves)', None
    t_global_end = time.monotonic()
    if glob is not None:
        sm_rep['global_adjustment'] = glob['figures']
        gf = glob['figures']
        mv = gf['camera_moves']
        block.assumptions.append(
            f'split-merge adjustment: {len(recs)} photos (more than {sm.split_photos}) in {part.n} overlapping '
            f'sub-blocks (k-means of the geotags, overlap radius {part.overlap_m:.1f} m), each adjusted on its own '
            'GNSS and the GCPs it sees (its report in sub_blocks/NN), merged by one similarity each over all overlaps '
            '(shared cameras and tie points); then one global adjustment of the whole block (every photo\'s GNSS, '
            'the GCPs, the self-calibration) from the merged poses, tie points and the sub-blocks\' mean camera: '
            f'{gf["solves"]} solves, {gf["iterations"]} iterations, {gf["wall_s"]:.0f} s; it moved the cameras '
            f'{mv.get("centre_rms_m", 0.0) * 100:.1f} cm RMS (max {mv.get("centre_max_m", 0.0) * 100:.1f} cm) and '
            f'{mv.get("attitude_rms_deg", 0.0):.3f} deg RMS. Control rows and points as each photo\'s own sub-block '
            'vetted them against its GNSS-only adjustment')
        for r in runs:
            block.assumptions.append(f'sub-block {r.sub.index}: {len(r.sub.names)} photos, {len(r.sub.map_T_cam)} '
                                     f'oriented, {r.wall_s:.0f} s; {r.sub.summary or r.sub.status}')
        _, _, _, gcp_crs, _ = _control_rows(block, opt, None, origin)
        crs = opt.crs or gcp_crs or f'EPSG:{utm_epsg(origin.lat_deg, origin.lon_deg)}'
        extra = {'split_merge': sm_rep,
                 'verdict_figures': {'split_merge': {'sub_blocks': part.n, 'overlaps': mr.overlaps,
                                                     'left_out': mr.left_out, 'global_adjustment': gf['status']}},
                 'timing_s': {'sub_blocks': round(t_merge - t_at, 2), 'merge': round(t_global - t_merge, 2),
                              'global_adjustment': round(t_global_end - t_global, 2)}}
        return _finish_block(block, out, opt, glob['at'], glob['rep_adj'], glob['refine'], glob['control'],
                             glob['vetting'], None, crs, t0, t_at, steps, log, merge_findings, extra)[0]
    if why:
        merge_findings.append(Finding('global_adjustment', 'warning', f'the global adjustment after the merge did '
                                      f'not finish ({why}): the merged block without it is the result'))
        if log is not None:
            log(f'warning: split-merge: the global adjustment did not finish ({why})')
    # The merged block's figures: each photo's from the sub-block its pose came from.
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
    # The block check of the merged cameras.
    names = [r.name for r in recs]
    n = len(names)
    T = np.full((n, 4, 4), np.nan)
    fix, sig, gz = np.full((n, 3), np.nan), np.full((n, 2), np.nan), np.full(n, np.nan)
    by_run = {r.sub.index: r for r in runs}
    for i, name in enumerate(names):
        if name in mr.map_T_cam:
            T[i] = mr.map_T_cam[name]
        k = mr.source.get(name, int(part.labels[i]))
        inp = by_run[k].inputs if k in by_run else None
        j = inp.names.index(name) if inp is not None and name in inp.names else None
        if j is not None:
            fix[i], sig[i] = inp.fix_enu_m[j], inp.fix_sigma_hv_m[j]
            if np.isfinite(inp.ground_z_m[j]) and sims[k] is not None:
                gz[i] = sims[k].apply(np.array([[*inp.map_T_cam[j, :2, 3], inp.ground_z_m[j]]]))[0, 2]
        elif np.isfinite(pos[i]).all():
            fix[i] = pos[i]
    statuses = [r.report.get('adjustment_status', 'failed') for r in runs if r.inputs is not None]
    adj = {'status': 'failed' if not statuses else
           next((s for s in statuses if s in ('failed', 'diverged')), statuses[0])}
    inputs = BlockInputs(names, T, fix, sig, gz, _merged_gnss_noise(runs), adj, block.expect_nadir,
                         block.n_inputs or n, dict(block.excluded),
                         (ck['horizontal_m'], ck['vertical_m'], ck['n']) if ck.get('n') else None)
    verdict = _with_findings(check_block(inputs), merge_findings)
    verdict.figures['split_merge'] = {'sub_blocks': part.n, 'overlaps': mr.overlaps, 'left_out': mr.left_out,
                                      'global_adjustment': 'failed' if why else 'off'}
    if log is not None and verdict.status != 'ok':
        log(f'warning: block check: {verdict.summary}')
    # Outputs.
    _, _, _, gcp_crs, _ = _control_rows(block, opt, None, origin)
    crs = opt.crs or gcp_crs or f'EPSG:{utm_epsg(origin.lat_deg, origin.lon_deg)}'
    steps.start('writing the poses, the sparse cloud and the report')
    oriented = [nm for nm in names if nm in mr.map_T_cam]
    assumptions = list(block.assumptions)
    P = _write_poses_and_cloud(out, oriented, [mr.map_T_cam[nm] for nm in oriented], mr.points_map_m, origin, crs,
                               assumptions)
    assumptions.append(
        f'split-merge adjustment: {len(recs)} photos (more than {sm.split_photos}) in {part.n} overlapping sub-blocks '
        f'(k-means of the geotags, overlap radius {part.overlap_m:.1f} m), each adjusted on its own GNSS and the GCPs '
        'it sees (its report in sub_blocks/NN), merged by one similarity each over all overlaps (shared cameras and '
        'tie points); each photo\'s pose from its own sub-block, tie and check points averaged over their copies; no '
        f'global adjustment after the merge ({why or "split.global_adjustment off"}). Each sub-block self-calibrates '
        'its own camera: the camera here is sub-block 0\'s; check points are intersected in each sub-block with its '
        'camera')
    for r in runs:
        assumptions.append(f'sub-block {r.sub.index}: {len(r.sub.names)} photos, {len(r.sub.map_T_cam)} oriented, '
                           f'{r.wall_s:.0f} s; {r.sub.summary or r.sub.status}')
    obs = [p['observations'] for p in per_image]
    rms = [p['reprojection_rms_px'] for p in per_image]
    tot = sum(o for o, x in zip(obs, rms) if x is not None)
    rms_px = (float(np.sqrt(sum(o * x * x for o, x in zip(obs, rms) if x is not None) / tot)) if tot else None)
    gres = np.array([p['gnss_residual_enu_m'] for p in per_image if p['gnss_residual_enu_m'] is not None])
    gcps = sorted(gcp_rows.values(), key=lambda g: g['name'])
    r0 = next((r.report for r in runs if r.report), {})
    now = time.monotonic()
    rep = {
        'format': 'photogram_ros aerial triangulation report v1',
        'origin': origin.to_dict(),
        'frame': 'map: ENU at origin (x east, y north, z up), m; heights ellipsoidal',
        'georeferenced': True, 'keyframes': n, 'registered': len(oriented), 'points': int(len(mr.point_ids)),
        'observations': int(sum(obs)), 'camera': r0.get('camera', {}), 'reprojection_rms_px': rms_px,
        'gnss': {'rmse': gnss_figures(gres), 'estimated_bias_enu_m': [0.0, 0.0, 0.0]},
        'gcp': {'points': gcps, 'rmse': rmse_xyz(np.array([g['residual_m'] for g in gcps])), 'redundancy': []},
        'check': {'points': checks_rep, 'rmse': ck,
                  'ce90_le90': ce90_le90(np.array([c['residual_m'] for c in checks_rep]))},
        'mtp': {'points': []},
        'reprojection_histogram': {'n': 0, 'counts': [], 'edges_px': []},
        'per_image': per_image, 'assumptions': assumptions, 'verdict': verdict.to_dict(), 'crs': crs,
        'adjustment_status': adj['status'],
        'split_merge': sm_rep,
        'timing_s': {'reading_and_matching': round(t_at - t0, 2), 'aerial_triangulation': round(now - t_at, 2),
                     'sub_blocks': round(t_merge - t_at, 2), 'merge': round(t_global - t_merge, 2),
                     'global_adjustment': round(t_global_end - t_global, 2),
                     'total': round(now - t0, 2)},
    }
    if block.stats:
        rep['matching'] = block.stats
    write_report(rep, out)
    steps.finish()
    return TriangulateResult(out, rep, len(oriented), block.n_inputs or n, len(P), [], rep['verdict'])
