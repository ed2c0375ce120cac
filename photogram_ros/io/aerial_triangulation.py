"""Offline aerial triangulation of a block of keyframes (a flight bag's or a photo folder's), and its outputs.

`adjust_block(block, out, options)` runs the incremental aerial triangulation (core/incremental.py) keyframe by
keyframe with the control (the flight's ArUco targets file for a bag, or an OpenDroneMap gcp_list.txt), gives the
photos that did not register in sequence a second chance against the whole block, makes a full adjustment
(self-calibrating the intrinsics asked for), and writes into `out`:
- poses.csv: each oriented image in the output CRS and WGS84, omega-phi-kappa (io/trajectory.py);
- sparse.ply and sparse.las: the tie points;
all heights in the datum `options.heights` asks (WGS84 ellipsoidal, or orthometric above EGM2008; poses.csv's
lat_deg/lon_deg/h_m stay WGS84 ellipsoidal), said in the report ('heights', 'crs_with_heights');
- report.md/.html/.json: the adjustment's figures (core/at_report.py) and every assumption made.
The output CRS is the one asked for, else the GCP file's, else the UTM zone of the origin.

The actions beside it: io/triangulate_action.py `triangulate` reads a bag or a photo folder and calls this one or
io/split_merge_action.py `split_merge_block` (a large photo block as overlapping sub-blocks, each adjusted here).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from photogram_ros.core.block_check import Finding, check_block, inputs_from_at
from photogram_ros.core.at_report import (build_report, convergence, focal_determination, gnss_figures,
                                          undetermined_focal,
                                        intrinsics_sigma)
from photogram_ros.core.control import ControlRow, ControlVettingOptions, unchecked_vetting, vet_control
from photogram_ros.io.at_report import write_report
from photogram_ros.core.geodesy import LocalFrame, utm_epsg
from photogram_ros.core.incremental import DISTORTION_TERMS, PASS_GROWTH_RATIO, IncrementalAT, IncrementalOptions
from photogram_ros.core.photo_matching import MatchingOptions
from photogram_ros.core.split_merge import SplitMergeOptions
from photogram_ros.core.triangulation import near_the_cameras
from photogram_ros.errors import ConfigError
from photogram_ros.io.export import GeoCloud, enu_to_crs, write_las, write_ply
from photogram_ros.io.keyframe_block import KeyframeBlock
from photogram_ros.io.progress import Steps, sayer
from photogram_ros.io.trajectory import POSES_COLUMNS, write_trajectory_csv


def is_targets_file(path) -> bool:
    """A control file of ArUco targets ("name marker_id x y z [sigma_h_m sigma_v_m]" rows, as `replay --gcp` reads
    it), not an OpenDroneMap gcp_list.txt ("x y z px py image [name]" rows): told by its first row after the CRS
    line. False for a file that cannot be read (the gcp_list.txt reader then says why)."""
    import re
    try:
        with open(path, encoding='utf-8', errors='replace') as f:
            rows = [ln.split('#', 1)[0].strip() for ln in f]
    except OSError:
        return False
    rows = [r for r in rows if r.strip(';, \t"\'')]
    if len(rows) < 2:
        return False
    tokens = [t for t in re.split(r'[\s,;]+', rows[1]) if t]

    def number(t):
        try:
            float(t)
            return True
        except ValueError:
            return False
    return len(tokens) in (5, 7) and not number(tokens[0]) and tokens[1].isdigit()


@dataclass
class TriangulateOptions:
    """Everything `triangulate` is asked, validated when it is made (`photogram-ros triangulate` makes it once from
    its arguments) and handed down whole: each stage reads its own part (`matching`, `adjustment`, `vetting`,
    `split`) or field, and nothing below re-reads, re-defaults or re-checks it."""

    camera: str | None = None                 # calibration YAML; default: the bag's camera_info / the EXIF
    targets: str | None = None                # a bag's control file of ArUco targets (io/control_file.py)
    gcp: str | None = None                    # OpenDroneMap gcp_list.txt (its MTP* rows: manual tie points)
    mtp: str | None = None                    # manual tie points: "px py image name" rows (io/control_file.py)
    check_names: tuple = ()                   # check points besides CHK*
    crs: str | None = None                    # output CRS
    gcp_sigma_enu_m: tuple = (0.02, 0.02, 0.03)
    neighbours: int | None = None             # photos matched with each photo; None: matching.neighbours
    window: int = 10                          # sliding-window size
    lever_arm_cam_m: tuple = (0.0, 0.0, 0.0)  # antenna in the camera frame
    # Intrinsics refined in the final adjustment ('f', 'k1', ...); None: automatic (`auto_self_calibration`).
    self_calibrate: tuple | None = None
    matching: MatchingOptions = field(default_factory=MatchingOptions)   # photos: features and matching
    exif_altitude: str | None = None          # 'msl', 'ellipsoidal', 'relative' or None (msl, checked)
    takeoff_h_m: float | None = None          # for exif_altitude 'relative'
    takeoff_heights: str = 'msl'              # reference of takeoff_h_m: 'msl' or 'ellipsoidal'
    vetting: ControlVettingOptions = field(default_factory=ControlVettingOptions)   # control rows and heights
    # vertical datum of the targets file's heights (io/control_file.HEIGHTS; a gcp_list.txt's CRS says its own)
    control_heights: str = 'auto'
    workers: int = 1                          # photos: local Dask worker processes (1: this process, no Dask)
    scheduler: str | None = None              # photos: an existing Dask cluster, tcp://HOST:PORT
    # photos: blocks above split.split_photos adjusted as overlapping sub-blocks and merged; None: never split
    split: SplitMergeOptions | None = field(default_factory=SplitMergeOptions)
    # the heights of poses.csv's z and the sparse cloud written: 'ellipsoidal' or 'orthometric' (io/crs_tags.HEIGHTS)
    heights: str = 'ellipsoidal'
    # The incremental adjustment's options (window, lever arm), made and validated here from the fields above.
    adjustment: IncrementalOptions = field(init=False, repr=False)

    def __post_init__(self) -> None:
        from photogram_ros.params import from_dict
        if self.takeoff_h_m is not None and self.exif_altitude != 'relative':
            raise ConfigError('--takeoff-altitude-m is only used with --exif-altitude relative (EXIF altitudes '
                              'above the take-off point): add that, or drop --takeoff-altitude-m')
        if self.exif_altitude == 'relative' and self.takeoff_h_m is None:
            raise ConfigError('--exif-altitude relative needs the take-off point\'s height: --takeoff-altitude-m H '
                              '(m above mean sea level; add --takeoff-heights ellipsoidal for a WGS84 height)')
        from photogram_ros.io.control_file import HEIGHTS
        if self.gcp and not self.targets and is_targets_file(self.gcp):
            # --gcp means "the control file" in every command: a targets file (replay --gcp's format) is one.
            self.targets, self.gcp = self.gcp, None
        from photogram_ros.io.crs_tags import HEIGHTS as OUTPUT_HEIGHTS
        if self.heights not in OUTPUT_HEIGHTS:
            raise ConfigError(f'--heights {self.heights!r}: one of {", ".join(OUTPUT_HEIGHTS)}')
        if self.control_heights not in HEIGHTS:
            raise ConfigError(f'--gcp-heights {self.control_heights!r}: one of {", ".join(HEIGHTS)} (the vertical '
                              'datum of the control file\'s heights)')
        if self.control_heights != 'auto' and self.gcp and not self.targets:
            raise ConfigError(f'--gcp-heights {self.control_heights}: a gcp_list.txt ({self.gcp}) says the datum of '
                              'its heights by the CRS of its first line (a compound one, e.g. EPSG:32632+3855, for '
                              'EGM2008 heights): drop --gcp-heights, or name that CRS in the file')
        self.check_names = tuple(self.check_names)
        self.lever_arm_cam_m = tuple(self.lever_arm_cam_m)
        if self.self_calibrate is not None:
            self.self_calibrate = tuple(self.self_calibrate)
        if self.neighbours is not None:
            self.matching = from_dict(MatchingOptions, {**self.matching.__dict__, 'neighbours': int(self.neighbours)},
                                      'triangulate --neighbours')
        self.neighbours = self.matching.neighbours
        self.adjustment = from_dict(IncrementalOptions, {'window_size': self.window,
                                                         'lever_arm_cam_m': self.lever_arm_cam_m},
                                    'triangulate --window/--lever-arm-cam')

    def refine(self, block: KeyframeBlock, n_gcps: int, assumptions: list) -> tuple:
        """The intrinsics the final adjustment refines: those asked for, else `auto_self_calibration`'s."""
        if self.self_calibrate is not None:
            return self.self_calibrate
        return auto_self_calibration(block, n_gcps, assumptions)


@dataclass
class TriangulateResult:
    out: Path
    report: dict                # report.json's figures
    registered: int             # images oriented
    inputs: int                 # images given
    tie_points: int
    damage: list = field(default_factory=list)   # a damaged bag: what was read and lost (exit 3)
    verdict: dict = field(default_factory=dict)  # core/block_check.py BlockVerdict.to_dict()


def _self_calibration(at: IncrementalAT, before, refine: tuple, assumptions: list, log=None) -> dict:
    """The refined intrinsics before and after, with their a-posteriori sigmas and correlations with the
    block's height; a focal length the block does not determine is said so, with no sigma."""
    after = at.block.camera
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


# `--self-calibrate auto` holding an undetermined f: a refined focal within this fraction of the given one is held
# by adjusting the block again from where it is (the final adjustment, 25 s on the simulator's 104-photo survey);
# farther, the block is triangulated again with f held (the incremental pass and the final: 2 min there).
FOCAL_READJUST_MAX = 0.05
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
    tie_obs = tie_obs or {}
    ties = {n for obs in tie_obs.values() for n in obs}
    # The distortion to be refined is refined in the pass too, at each 1.5-fold growth of the block: an uncalibrated
    # lens bends a long block away from its geotags (bench/notes_photo_triangulation_scale.md).
    in_pass = tuple(t for t in refine if t in DISTORTION_TERMS)
    at = IncrementalAT(block.camera, replace(opt.adjustment, pass_self_calibration=','.join(in_pass),
                                            growth_ratio=PASS_GROWTH_RATIO if in_pass else 0.0),
                       block.origin, control, ties=ties)
    added = steps.progress(f'aerial triangulation{what}', len(block.records), 'photos added')
    oriented = (lambda: f'{at.block.n_oriented} oriented')
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


def control_rows(block: KeyframeBlock, opt: TriangulateOptions, control_set, origin, gcps=None):
    """(control points, rows, heights as written, CRS, manual tie point rows) of a bag's targets (their
    detections in the records) or of opt.gcp (`gcps`: that file as io/control_file.py read_gcp_list read it
    already; None: read here), and the MTPs of opt.gcp and opt.mtp."""
    from photogram_ros.io.control_file import read_gcp_list, read_tie_list
    ties = read_tie_list(opt.mtp) if opt.mtp else []
    if control_set is not None:
        rows = [ControlRow(0, rec.name, n, np.asarray(uv, float)) for rec in block.records
                for n, uv in rec.target_uv.items()]
        return control_set.in_map(origin), rows, {}, None, ties
    if opt.gcp:
        gcps = gcps if gcps is not None else read_gcp_list(opt.gcp, opt.check_names)
        return (gcps.in_map(origin, opt.gcp_sigma_enu_m), gcps.rows, gcps.file_heights, gcps.crs,
                gcps.tie_rows + ties)
    return [], [], {}, None, ties


def manual_tie_obs(rows: list, images: set, assumptions: list, log=None) -> dict:
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
                 log=None, t0: float | None = None, progress=True, steps: Steps | None = None,
                 gcps=None) -> TriangulateResult:
    """Incremental AT of the block's records, a full adjustment, then poses, sparse cloud and report.

    control_set: a bag's ControlSet, whose observations are already in the records; else opt.gcp (`gcps`: as
    read already, or None).
    With control rows the block is first adjusted on its GNSS alone, every row and point is checked
    against it (core/control.py vet_control: rows naming the wrong photo, heights the GNSS contradicts),
    and the block is adjusted again with the control that passed.
    progress: as triangulate()'s; `steps`: the job's Steps so far (then `progress` is not used).
    """
    return adjust_and_write(block, out, opt, control_set, log, t0, progress, steps, gcps)[0]


def adjust_and_write(block: KeyframeBlock, out: str | Path, opt: TriangulateOptions, control_set=None,
                      log=None, t0: float | None = None, progress=True, steps: Steps | None = None,
                      gcps=None) -> tuple[TriangulateResult, IncrementalAT, object, dict]:
    """adjust_block(), and its adjusted IncrementalAT, BlockInputs and control: {'vetting' (ControlVetting or
    None), 'control' (the ControlPoints as adjusted), 'target_obs' (the GCP observations used, by photo)}."""
    steps = steps or Steps('triangulate', None, sayer(progress, log))
    out = Path(out)
    origin, assumptions = block.origin, block.assumptions
    control, rows, file_heights, gcp_crs, tie_rows = control_rows(block, opt, control_set, origin, gcps)
    tie_obs = manual_tie_obs(tie_rows, {r.name for r in block.records}, assumptions, log)
    crs = opt.crs or gcp_crs or f'EPSG:{utm_epsg(origin.lat_deg, origin.lon_deg)}'
    t_at = time.monotonic()
    vet, gnss_without, target_obs = None, None, {}
    at = rep_adj = None
    if rows:
        at, rep_adj = _triangulate_records(block, opt, [], {}, opt.refine(block, 0, []), log, ' (GNSS only, to check the control)',
                                           tie_obs, steps)
        steps.start('checking the control against the GNSS-only block')
        P0 = at.block.tie_point_cloud()
        if at.georeferenced and not at.georef_provisional:
            vet = vet_control(at.block.camera, at.block.poses_by_name(),
                              {r.name for r in block.records}, rows, control, at.fix_sigma_enu_m(), P0, file_heights,
                              opt.vetting)
        else:   # a single line (its roll about it only the GCPs fix) or no GNSS: nothing to judge the control by
            vet = unchecked_vetting(at.block.camera, at.block.poses_by_name(),
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
    refine = opt.refine(block, n_gcps, assumptions)
    if at is None or target_obs:
        at, rep_adj = _triangulate_records(block, opt, control, target_obs, refine, log, tie_obs=tie_obs, steps=steps)
    kept = at.self_calibration.kept if at.self_calibration is not None else refine
    if opt.self_calibrate is None and (focal := undetermined_focal(at, kept)):   # auto: f only where determined
        note = (f'self-calibration (auto): f held at {block.camera.fx:.1f} px: refined, it went to '
                f'{at.block.camera.fx:.1f} px, which the block does not determine ({focal["reason"]}: the focal '
                'trades off with the cameras\' height above the ground), so the block was adjusted again with f fixed')
        assumptions.append(note)
        if log is not None:
            log(f'warning: {note}')
        refine = tuple(r for r in refine if r != 'f')
        if abs(at.block.camera.fx / block.camera.fx - 1.0) <= FOCAL_READJUST_MAX:
            # A focal that moved little left the block's shape near the one it has with f given: adjusted again from
            # it (the final adjustment alone); one that ran far bent it, and the block is triangulated again.
            steps.start('full adjustment with f held')
            t_full = time.monotonic()
            at.block.hold_given_focal()
            rep_adj = at.full_adjustment(refine_intrinsics=refine, stepwise=True)
            if log is not None:
                log(f'full adjustment with f held: {rep_adj.status}, {time.monotonic() - t_full:.1f} s')
        else:
            at, rep_adj = _triangulate_records(block, opt, control, target_obs, refine, log, tie_obs=tie_obs,
                                               steps=steps)
    res, inputs = finish_block(block, out, opt, at, rep_adj, refine, control, vet,
                                gnss_without if vet is not None and target_obs else None, crs, t0, t_at, steps, log)
    return res, at, inputs, {'vetting': vet, 'control': control, 'target_obs': target_obs}


def finish_block(block: KeyframeBlock, out: Path, opt: TriangulateOptions, at: IncrementalAT, rep_adj, refine: tuple,
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
    if self_cal is not None and self_cal.get('focal', {}).get('determined') is False:
        extra_findings = (*extra_findings, Finding('self_calibration', 'warning', 'the focal length was refined and the '
                          f'block does not determine it ({self_cal["focal"]["reason"]}): its heights are uncertain by '
                          'as much as the focal moved; keep f fixed, or add GCPs with surveyed heights or oblique photos'))
    conv = convergence(at, rep_adj.status)
    if conv is not None:
        assumptions.append(conv['text'])
        if log is not None:
            log(f'warning: {conv["text"]}')
    adj = {'status': rep_adj.status, **({'matters': conv['matters'], 'text': conv['text']} if conv else {})}
    for j in at.segments.joins_made():
        how = (f'through {j["mtps"]} manual tie points' if j['through'] == 'mtp' else
               f'through {j["ties"]} automatic tie points shared across the gap' if j['through'] == 'ties' else
               'through its GNSS alone (no tie point joins it to the rest: its position relative to the block is '
               'only as good as the GNSS; manual tie points across the gap would tie it)')
        assumptions.append(f'a part of {j["keyframes"]} photos that shares no automatic tie point with the rest of the '
                           f'block joined it {how}')
    lost = [kf.name for kf in at.block.keyframes() if kf.map_T_cam is None]
    if lost:
        assumptions.append(f'{len(lost)} photos could not be oriented (blurred or without overlap): {lost[:10]}')
    assumptions.append('lever arm antenna-camera ' + str(opt.lever_arm_cam_m) + ' m in the camera frame')
    P = at.block.tie_point_cloud()
    if block.exif_geodetic is not None:
        note = relative_exif_note(origin, P, block.exif_geodetic, _trusted_ground(control, vet))
        if note:
            assumptions.append(note)
            if log is not None:
                log(f'warning: {note}')
    steps.start('writing the poses, the sparse cloud and the report')
    P = write_poses_and_cloud(out, at.block.oriented_names(), at.block.oriented_poses(), P, origin, crs,
                               assumptions, opt.heights)
    rep = build_report(at, assumptions, vetting=vet, gnss_without_gcps=gnss_without_gcps)
    inputs = inputs_from_at(at, len(block.records), adj, block.expect_nadir, block.excluded)
    ck = rep['check']['rmse']
    if ck.get('n'):
        inputs.check_rmse_hv_m = (ck['horizontal_m'], ck['vertical_m'], ck['n'])
    verdict = with_findings(check_block(inputs), extra_findings)
    extra = dict(extra or {})
    verdict.figures.update(extra.pop('verdict_figures', {}))
    if log is not None and verdict.status != 'ok':
        log(f'warning: block check: {verdict.summary}')
    rep['verdict'] = verdict.to_dict()
    noise = at.rounds.noise_estimate()
    if noise:
        rep['gnss_noise'] = noise
    rep['crs'] = crs
    rep.update(heights_keys(crs, opt.heights))
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
    return (TriangulateResult(out, rep, at.block.n_oriented, block.n_inputs or len(block.records), len(P),
                              list(block.damage), rep['verdict']), inputs)


def with_findings(verdict, findings) -> object:
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


def heights_keys(crs: str, heights: str) -> dict:
    """The report's statement of the heights write_poses_and_cloud wrote: 'heights' and 'crs_with_heights' (the CRS
    compound with EGM2008 height for orthometric ones, io/crs_tags.crs_with_heights)."""
    from photogram_ros.io.crs_tags import crs_with_heights
    return {'heights': heights, 'crs_with_heights': crs_with_heights(crs, heights) if crs else None}


def write_poses_and_cloud(out: Path, names: list, map_T_cams: list, P: np.ndarray, origin: LocalFrame, crs: str,
                          assumptions: list, heights: str = 'ellipsoidal') -> np.ndarray:
    """poses.csv of the oriented photos, and sparse.ply / sparse.las of the tie points P (map ENU, m) near
    the cameras (the others are said in the assumptions), their heights per `heights` ('ellipsoidal' or
    'orthometric': poses.csv's z and the cloud above EGM2008, the CRS compound with EGM2008 height); returns
    the points written."""
    out.mkdir(parents=True, exist_ok=True)
    Ts = np.array(map_T_cams).reshape(-1, 4, 4)
    write_trajectory_csv(out / 'poses.csv', POSES_COLUMNS, list(names), Ts, origin, crs, heights=heights)
    near = near_the_cameras(P, Ts[:, :3, 3])
    if not near.all():
        assumptions.append(f'{int((~near).sum())} of {len(P)} tie points lie more than 10 times the usual camera '
                           'distance from every camera (rays almost parallel): left out of sparse.ply / sparse.las')
        P = P[near]
    e, n, h = enu_to_crs(origin, P, crs, heights)
    cloud = GeoCloud(e, n, h, np.full((len(P), 3), 200, np.uint8), np.ones(len(P), np.uint32),
                     np.ones(len(P), np.float32), crs, heights)
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
            '--exif-altitude orthometric (EGM2008, the EXIF standard\'s MSL) if the site really lies there')
