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

Progress (io/progress.py) goes to `progress(text)`: each step as it starts, and the photos of the
features, the pairs of the matching and the photos added to the incremental adjustment counted with a
percent and an ETA.
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
from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions
from photogram_ros.core.photo_matching import MatchingOptions
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

    def check(self) -> None:
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
                                                               'pairs')}


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
        with open_runner(opt.workers, opt.scheduler, log) as runner:
            block = read_photo_block(src, opt.camera, opt.neighbours, opt.exif_altitude, opt.takeoff_h_m,
                                     opt.takeoff_heights, log, opt.matching, CountedRunner(runner, say))
    res = adjust_block(block, out, opt, control_set, log, t0, steps=steps)
    return res


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
    more GCPs (their heights fix the ground's depth; without them the focal of a near-nadir block trades off
    with it); and the principal point (cx, cy) when the geotags are RTK/PPK-precise (median stated horizontal
    sigma <= PRECISE_GEOTAG_SIGMA_H_M): with the cameras held where they were, a principal point off by
    d px moves the ground by height x d / f, the other way on each flight line flown the other way."""
    if not block.camera_from_exif:
        return ()
    refine = ('f', 'k1', 'k2') if n_gcps >= 3 else ('k1', 'k2')
    why = (f'f too: {n_gcps} GCPs give the ground\'s depth' if 'f' in refine else
           'f held at its EXIF value: without 3 GCPs with heights a near-nadir block does not determine it')
    sig_h = [float(np.sqrt(0.5 * (r.fix.cov_enu_m2[0][0] + r.fix.cov_enu_m2[1][1]))) for r in block.records
             if r.fix is not None]
    if sig_h and float(np.median(sig_h)) <= PRECISE_GEOTAG_SIGMA_H_M:
        refine += ('cx', 'cy')
        why += (f'; the principal point too: the geotags are precise ({np.median(sig_h) * 100:.1f} cm stated, '
                'median) and hold the cameras')
    assumptions.append(f'self-calibration (auto): the EXIF gives no distortion, so {", ".join(refine)} are refined; '
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
    at = IncrementalAT(block.camera, IncrementalOptions(window_size=opt.window, lever_arm_cam_m=lever), block.origin,
                       control, ties=ties)
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
    rep_adj = at.full_adjustment(refine_intrinsics=refine)
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
    before = block.camera
    if at is None or target_obs:
        at, rep_adj = _triangulate_records(block, opt, control, target_obs, refine, log, tie_obs=tie_obs, steps=steps)
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
    out.mkdir(parents=True, exist_ok=True)
    kfs = [at.kfs[k] for k in at.registered]
    write_trajectory_csv(out / 'poses.csv', POSES_COLUMNS, [kf.name for kf in kfs],
                         np.array([kf.map_T_cam for kf in kfs]).reshape(-1, 4, 4), origin, crs)
    near = near_the_cameras(P, np.array([kf.map_T_cam[:3, 3] for kf in kfs]).reshape(-1, 3))
    if not near.all():
        assumptions.append(f'{int((~near).sum())} of {len(P)} tie points lie more than 10 times the usual camera '
                           'distance from every camera (rays almost parallel): left out of sparse.ply / sparse.las')
        P = P[near]
    e, n, h = enu_to_crs(origin, P, crs)
    cloud = GeoCloud(e, n, h, np.full((len(P), 3), 200, np.uint8), np.ones(len(P), np.uint32),
                     np.ones(len(P), np.float32), crs, 'ellipsoidal')
    write_ply(cloud, out / 'sparse.ply')
    write_las(cloud, out / 'sparse.las')
    rep = build_report(at, assumptions, vetting=vet,
                       gnss_without_gcps=gnss_without if vet is not None and target_obs else None)
    inputs = inputs_from_at(at, len(block.records), adj, block.expect_nadir, block.excluded)
    ck = rep['check']['rmse']
    if ck.get('n'):
        inputs.check_rmse_hv_m = (ck['horizontal_m'], ck['vertical_m'], ck['n'])
    verdict = check_block(inputs)
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
    write_report(rep, out)
    steps.finish()
    return TriangulateResult(out, rep, len(at.registered), block.n_inputs or len(block.records), len(P),
                             list(block.damage), rep['verdict'])


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
