"""PPK geotagging figures on simulated flights (issue #45): the shutter's delay, and DJI RTK photos' XMP weights.

1. Event delay: `simulate` a PPK survey (the tiny preset's two lines made 120 m long) flown at 12 m/s whose
   shutter opens 30 ms after the event marks the MRK writes, exposures at 2.5 fps (each halfway between two
   5 Hz epochs), the .pos the true antenna track (its error model off) or the RTK-fixed error model; `geotag`
   with and without `--event-delay-ms 30`, linear and cubic: the camera positions' error against the truth
   (median, 90 %, max; along-track median) over every photo, over the photos where the true track is smooth
   (acceleration <= SPEED_STEP_MPS2 within SPEED_STEP_WINDOW_S: lines and turns), of those the straight-line
   ones (<= LINE_MPS2), and over the photos at one of the simulator's instant speed changes (parked to
   12 m/s at take-off, 12 to 2.5 m/s into and out of a turn, to a stop at the end), with the worst photo
   and what a linear interpolation of the .pos epochs misses of the true antenna there (the track's limit).
2. DJI RTK photos: `simulate --rtk-photos` (EXIF GPS = the RTK camera centre, XMP RtkFlag/RtkStd*); `triangulate`
   without GCPs (every target a check point) on (a) the XMP, (b) the same photos with a hand-made geo.txt of the
   same positions and sigmas, (c) a third of the photos FLOAT (flag 34, 0.5 / 0.8 m stated) at their true
   positions, (d) the same third FLOAT and 1 m off (the fixed photos' errors the same in all); each row has its
   ratio to (a). `--georeference proposed` runs (c) and (d) again with the change to
   IncrementalAT._try_georeference that `proposed_georeference` emulates (only the precise fixes,
   GnssDatum.similarity_fixes, in the similarity that places the block); rows say which (`georeference`).

3. The authors' way (`--layouts`): each trajectory + MRK pair of tests/data/trajectories (and `--real-waypoint FILE`,
   a real Waypoint export, with events every 2 s and the MRK offsets of the pair) placed by `geotag` with linear
   and cubic interpolation, against the camera positions a public M300 + Waypoint workflow computes (latitude,
   longitude and H-Ell interpolated linearly in GPS time, then the offset east = E, north = N, up = -V):
   median and max (mm), over all exposures and over those where the track accelerates less than 1 m/s^2.

One JSON line per result, with the commit, whether the product code was clean, the cores and the load:
    .venv/bin/python bench/ppk_formats.py [--preset tiny] [--out bench/results/ppk_formats_<commit>.jsonl]
        [--skip-delay] [--cases rtk_xmp,rtk_xmp_third_float_1m] [--georeference as_is,proposed]
        [--layouts [--real-waypoint PPK_Trajectory.txt]]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine import machine_info  # noqa: E402

from photogram_ros.core.exposure_positions import ExposureOptions  # noqa: E402
from photogram_ros.io.geotag import GeotagInput, geotag  # noqa: E402
from photogram_ros.sim.scenario import preset, simulate  # noqa: E402
from photogram_ros.sim.truth import GroundTruth  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def git(*args) -> str:
    return subprocess.run(['git', *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()


# Above this acceleration (m/s^2) within SPEED_STEP_WINDOW_S of an exposure the simulator's flight changes its
# speed at once (flight.state: parked before take-off then at full speed, full speed into a 2.5 m/s turn and out of
# it): a velocity step no 5 Hz track carries. A survey multirotor's manoeuvres stay under it (its turns 0.8 m/s^2).
SPEED_STEP_MPS2 = 3.0
# At or under this the true track is a straight line at constant speed (the attitude jitter's lever-arm wobble only).
LINE_MPS2 = 0.3
# The epochs an exposure's interpolation reads lie within this of it: the two around it (0.1 s away at 5 Hz with
# the exposure between them) and, for cubic, one more on either side (0.3 s).
SPEED_STEP_WINDOW_S = 0.3


def truth_acceleration_mps2(t_s, t_truth_s, antenna_enu_m, window_s: float = SPEED_STEP_WINDOW_S) -> np.ndarray:
    """The largest acceleration of the true antenna (samples `antenna_enu_m` at `t_truth_s`) within `window_s`
    of each time in `t_s` (central differences of the samples, so a step in speed shows on the samples
    either side of it)."""
    t_truth_s = np.asarray(t_truth_s, float)
    v = np.gradient(np.asarray(antenna_enu_m, float), t_truth_s, axis=0)
    acc = np.linalg.norm(np.gradient(v, t_truth_s, axis=0), axis=1)
    return np.array([acc[np.abs(t_truth_s - t) <= window_s + 1e-6].max(initial=0.0) for t in np.atleast_1d(t_s)])


def _stats(prefix: str, e: np.ndarray) -> dict:
    if len(e) == 0:
        return {f'{prefix}photos': 0}
    return {f'{prefix}photos': len(e), f'{prefix}median_m': round(float(np.median(e)), 5),
            f'{prefix}p90_m': round(float(np.percentile(e, 90)), 5), f'{prefix}max_m': round(float(e.max()), 5)}


def split_by_motion(err_m, acc_mps2, limit_mps2: float = SPEED_STEP_MPS2, line_mps2: float = LINE_MPS2) -> dict:
    """Error figures over every photo; over the photos whose true track is smooth around them (acceleration
    <= limit_mps2: lines and turns), and of those the ones on a straight line (<= line_mps2); and over the
    photos at one of the simulator's speed steps (> limit_mps2)."""
    err_m, acc_mps2 = np.asarray(err_m, float), np.asarray(acc_mps2, float)
    smooth = acc_mps2 <= limit_mps2
    return {**_stats('', err_m), **_stats('smooth_', err_m[smooth]), **_stats('line_', err_m[acc_mps2 <= line_mps2]),
            **_stats('speed_step_', err_m[~smooth]), 'speed_step_limit_mps2': limit_mps2, 'line_limit_mps2': line_mps2}


def delay_run(where: Path, sigma_scale: float, fps: float = 2.5, line_length_m: float = 120.0) -> list[dict]:
    """The tiny preset's two lines, line_length_m long, flown at 12 m/s with a 30 ms shutter delay; exposures at
    fps (2.5: every one halfway between two 5 Hz epochs, where interpolation is weakest)."""
    from photogram_ros.core.exposure_positions import gps_s_to_utc_unix
    from photogram_ros.core.geodesy import ecef_to_geodetic
    from photogram_ros.io.trajectory_formats import read_trajectory
    from photogram_ros.sim.scenario import START_UNIX_S
    root = where / f'delay_{sigma_scale:g}'
    simulate(preset('tiny', fps=fps, ppk=True, speed_mps=12.0, ppk_shutter_delay_ms=30.0, ppk_sigma_scale=sigma_scale,
                    line_length_m=line_length_m), root)
    truth = GroundTruth.load(root)
    ppk = root / 'ppk'
    frame = {f'IMG_{f.index:04d}.JPG': f for f in truth.frames}
    t_truth = np.array([f['t_fix_unix_s'] for f in truth.fixes]) - START_UNIX_S
    ant_truth = np.array([f['antenna_enu'] for f in truth.fixes])
    vel_truth = np.gradient(ant_truth, t_truth, axis=0)
    # the .pos epochs in the map frame, for an independent linear interpolation at the exposures
    track = read_trajectory(ppk / 'flight.pos', require_fix=False)
    pos_enu = np.array([truth.origin.geodetic_to_enu(*ecef_to_geodetic(*x)) for x in track.ecef_m])
    t_pos = np.array([gps_s_to_utc_unix(t) for t in track.t_gps_s]) - START_UNIX_S
    rows = []
    for delay_ms, how in ((0.0, 'linear'), (30.0, 'linear'), (30.0, 'cubic')):
        res = geotag(GeotagInput(str(ppk / 'flight.pos'), str(ppk / 'Timestamp.MRK'), str(ppk), str(root / 'geo.txt'),
                                 options=ExposureOptions(event_delay_s=delay_ms * 1e-3, interpolation=how)))
        names = [n for n, _ in res.rows]
        t_exp = np.array([frame[n].stamp_ns * 1e-9 - START_UNIX_S for n in names])
        err = np.array([truth.origin.geodetic_to_enu(pe.lat_deg, pe.lon_deg, pe.h_m) - frame[n].map_T_cam[:3, 3]
                        for n, pe in res.rows])
        e = np.linalg.norm(err, axis=1)
        v = np.array([[np.interp(t, t_truth, vel_truth[:, k]) for k in range(3)] for t in t_exp])
        along = np.abs(np.sum(err * v, axis=1)) / np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        acc = truth_acceleration_mps2(t_exp, t_truth, ant_truth)
        # what any linear interpolation of the .pos epochs misses at the exposure (the track's own limit)
        lin = np.array([[np.interp(t, t_pos, pos_enu[:, k]) for k in range(3)] for t in t_exp])
        lin_miss = np.linalg.norm(lin - np.array([frame[n].antenna_enu for n in names]), axis=1)
        w = int(np.argmax(e))
        rows.append({'case': 'event_delay', 'interpolation': how, 'speed_mps': 12.0, 'shutter_delay_ms': 30.0,
                     'event_delay_ms': delay_ms, 'track_error_scale': sigma_scale, 'fps': fps,
                     'line_length_m': line_length_m,
                     **split_by_motion(e, acc),
                     'along_track_median_m': round(float(np.median(along)), 5),
                     'worst': {'photo': names[w], 't_from_takeoff_s': round(float(t_exp[w]), 3),
                               'truth_acc_mps2': round(float(acc[w]), 2), 'error_m': round(float(e[w]), 5),
                               'along_track_m': round(float(along[w]), 5),
                               'linear_interpolation_of_epochs_misses_m': round(float(lin_miss[w]), 5)},
                     'speed_step_each': [{'photo': names[k], 't_from_takeoff_s': round(float(t_exp[k]), 3),
                                          'truth_acc_mps2': round(float(acc[k]), 2), 'error_m': round(float(e[k]), 5),
                                          'linear_interpolation_of_epochs_misses_m': round(float(lin_miss[k]), 5)}
                                         for k in np.flatnonzero(acc > SPEED_STEP_MPS2)]})
        sys.stderr.write(json.dumps(rows[-1]) + '\n')
    return rows


DATA = ROOT / 'tests' / 'data' / 'trajectories'
LAYOUT_PAIRS = (('waypoint_m300_5hz.txt', 'm300_Timestamp.MRK'),)


def _ecef(lat, lon, h) -> np.ndarray:
    from pyproj import Transformer
    tr = Transformer.from_crs('EPSG:4979', 'EPSG:4978', always_xy=True)
    return np.column_stack(tr.transform(np.asarray(lon), np.asarray(lat), np.asarray(h)))


def authors_way(track, t_gps_s: np.ndarray, offsets_ned_m: np.ndarray) -> np.ndarray:
    """Camera ECEF as the M300 + Waypoint workflow computes it: lat, lon, h linear in time, then E, N, -V."""
    from photogram_ros.core.geodesy import ecef_R_enu, ecef_to_geodetic
    llh = np.array([ecef_to_geodetic(*x) for x in track.ecef_m])
    lat, lon, h = (np.interp(t_gps_s, track.t_gps_s, llh[:, k]) for k in range(3))
    ant = _ecef(lat, lon, h)
    return np.array([a + ecef_R_enu(la, lo) @ np.array([o[1], o[0], -o[2]])
                     for a, la, lo, o in zip(ant, lat, lon, offsets_ned_m)])


def layouts_run(where: Path, real_waypoint: str | None, real_source: str = '') -> list[dict]:
    from photogram_ros.core.exposure_positions import CameraEvent, place_exposures
    from photogram_ros.io.camera_events import read_mrk
    from photogram_ros.io.trajectory_formats import read_trajectory
    pairs = [(DATA / a, DATA / b, 'tests/data/trajectories (layout of a real M300 Waypoint export, simulated epochs)')
             for a, b in LAYOUT_PAIRS]
    if real_waypoint:
        pairs.append((Path(real_waypoint), None, f'{real_waypoint}: {real_source or "a real Waypoint export"}; '
                      'events every 2 s with the MRK offsets of the first pair'))
    rows = []
    for traj, mrk, source in pairs:
        track = read_trajectory(traj, require_fix=False)
        if mrk is not None:
            events = [r.event for r in read_mrk(mrk)]
        else:
            offs = [r.event.offset_ned_m for r in read_mrk(DATA / LAYOUT_PAIRS[0][1])]
            times = np.arange(track.t_gps_s[0] + 0.4 + 0.137, track.t_gps_s[-1] - 0.4, 2.0)
            events = [CameraEvent(k + 1, float(x), k + 1, offs[k % len(offs)], where='bench')
                      for k, x in enumerate(times)]
        t = np.array([e.t_gps_s for e in events])
        ref = authors_way(track, t, np.array([e.offset_ned_m for e in events]))
        # the track's acceleration around each event (second differences of the epochs)
        v = np.gradient(track.ecef_m, track.t_gps_s, axis=0)
        acc = np.linalg.norm(np.gradient(v, track.t_gps_s, axis=0), axis=1)
        acc_at = np.interp(t, track.t_gps_s, acc)
        for how in ('linear', 'cubic'):
            placed = place_exposures(track, events, ExposureOptions(interpolation=how))
            ours = _ecef([p.lat_deg for p in placed.placed], [p.lon_deg for p in placed.placed],
                         [p.h_m for p in placed.placed])
            k = [events.index(p.event) for p in placed.placed]
            d = np.linalg.norm(ours - ref[k], axis=1) * 1000
            calm = d[acc_at[k] < 1.0]
            rows.append({'case': 'authors_way', 'file': traj.name, 'source': source, 'format': track.format,
                         'interpolation': how, 'exposures': len(events), 'placed': len(placed.placed),
                         'median_mm': round(float(np.median(d)), 4), 'max_mm': round(float(d.max()), 4),
                         'calm_exposures': len(calm),
                         'calm_median_mm': round(float(np.median(calm)), 4) if len(calm) else None,
                         'calm_max_mm': round(float(calm.max()), 4) if len(calm) else None})
            sys.stderr.write(json.dumps(rows[-1]) + '\n')
    return rows


@contextlib.contextmanager
def proposed_georeference():
    """Measures the change proposed for core/incremental.py (`IncrementalAT._try_georeference`, not this
    branch's to edit): the similarity that georeferences the block takes only the fixes
    `GnssDatum.similarity_fixes` selects (`ks = self.datum.similarity_fixes(ks, 3)` after the GCP-only
    branch), while every adjustment keeps every fix at its stated sigma. Emulated here by holding the other fixes
    out while `_try_georeference` runs and putting them back for the adjustments it calls. Bench only."""
    from photogram_ros.core.incremental import IncrementalAT
    names = ('_try_georeference', '_apply_georeference', '_pass_adjustment', '_georeference_by_gcps')
    orig = {n: getattr(IncrementalAT, n) for n in names}
    hidden: list[dict] = []

    def show(kfs, held):
        for k, fix in held.items():
            kfs[k].fix_enu = fix

    def try_georeference(self, *a, **kw):
        kfs = self.block.kfs
        ks = [k for k in self.block.registered if kfs[k].fix_enu is not None]
        held = {k: kfs[k].fix_enu for k in set(ks) - set(self.datum.similarity_fixes(ks, 3))}
        for k in held:
            kfs[k].fix_enu = None
        hidden.append(held)
        try:
            return orig['_try_georeference'](self, *a, **kw)
        finally:
            show(kfs, hidden.pop())

    def with_every_fix(name):
        def call(self, *a, **kw):
            held = hidden.pop() if hidden else {}
            show(self.block.kfs, held)
            hidden.append({})          # nested calls: every fix is shown already
            try:
                return orig[name](self, *a, **kw)
            finally:
                hidden.pop()
                for k in held:
                    self.block.kfs[k].fix_enu = None
                hidden.append(held)
        return call

    IncrementalAT._try_georeference = try_georeference
    for n in names[1:]:
        setattr(IncrementalAT, n, with_every_fix(n))
    try:
        yield
    finally:
        for n, f in orig.items():
            setattr(IncrementalAT, n, f)


def _triangulate(folder: Path, out: Path) -> dict:
    from photogram_ros.io.aerial_triangulation import TriangulateOptions
    from photogram_ros.io.triangulate_action import triangulate
    names = sorted({ln.split()[6] for ln in (folder / 'gcp_list.txt').read_text().splitlines()[1:]})
    triangulate(str(folder), str(out), TriangulateOptions(gcp=str(folder / 'gcp_list.txt'), check_names=tuple(names)))
    return json.loads((out / 'report.json').read_text())


RTK_CASES = {'rtk_xmp': {}, 'rtk_xmp_third_float_0m': {'rtk_float_every': 3, 'rtk_float_offset_m': 0.0},
             'rtk_xmp_third_float_1m': {'rtk_float_every': 3, 'rtk_float_offset_m': 1.0}}


def geotag_height_lean(folder: Path, rep: dict) -> dict:
    """How the geotags' height errors (the simulator's `rtk_truth.json`) lean across the block, weighted as
    their XMP states (1 / RtkStdHgt^2): the slope (dz/dE, dz/dN, mrad) of a plane fitted to them over the adjusted
    cameras' horizontal positions, and what that lean moves the ground by at the block's depth (the cameras'
    mean height above the check points, m): without GCPs the block takes its tilt from the fixes' heights, so
    its check points shift by about this much. Beside it the check points' mean residual (ENU, m). Empty without
    `rtk_truth.json` or check points."""
    truth_file = Path(folder) / 'rtk_truth.json'
    points = rep.get('check', {}).get('points', [])
    if not truth_file.exists() or not points:
        return {}
    truth = json.loads(truth_file.read_text())
    rows = [(p['position_map_m'], truth[p['image']]) for p in rep.get('per_image', []) if p['image'] in truth]
    xy_m = np.array([r[0][:2] for r in rows], float)
    dz_m = np.array([r[1]['error_enu_m'][2] for r in rows], float)
    w = 1.0 / np.array([r[1]['sd_neu_m'][2] for r in rows], float)
    A = np.column_stack([np.ones(len(rows)), xy_m - xy_m.mean(axis=0)])
    slope = np.linalg.lstsq(A * w[:, None], dz_m * w, rcond=None)[0][1:]
    depth_m = float(np.mean([r[0][2] for r in rows]) - np.mean([p['surveyed_map_m'][2] for p in points]))
    return {'geotag_height_lean_mrad': [round(float(v) * 1e3, 4) for v in slope], 'block_depth_m': round(depth_m, 2),
            'lean_ground_shift_m': [round(float(v) * depth_m, 4) for v in slope],
            'check_mean_enu_m': [round(float(v), 4) for v in np.mean([p['residual_m'] for p in points], axis=0)]}


def rtk_runs(where: Path, name: str, cases=tuple(RTK_CASES) + ('rtk_hand_geo_txt',),
             georeference=('as_is',), seed: int | None = None) -> list[dict]:
    """`triangulate` on each case of the RTK photo survey (preset `name`), for each georeference mode: 'as_is'
    (the product code) and 'proposed' (`proposed_georeference`; not run again on the clean survey, whose fixes
    all state the same sigmas, when 'as_is' ran it). Each row has its check-point RMSE and its ratio to the clean
    survey's, and how its geotags' heights lean (`geotag_height_lean`). seed: the simulator's (None: the preset's)."""
    from photogram_ros.sim.photos import write_geo_txt_from_exif_and_rtk_xmp
    seeded = {} if seed is None else {'seed': seed}
    folders = {}
    for case in cases:
        if case == 'rtk_hand_geo_txt':
            continue
        simulate(preset(name, fps=1.0, rtk_photos=True, **seeded, **RTK_CASES[case]), where / case)
        folders[case] = where / case / 'rtk'
    if 'rtk_hand_geo_txt' in cases:
        hand = where / 'rtk_hand' / 'rtk'
        if 'rtk_xmp' not in folders:
            simulate(preset(name, fps=1.0, rtk_photos=True, **seeded), where / 'rtk_xmp')
        shutil.copytree(where / 'rtk_xmp' / 'rtk', hand)
        write_geo_txt_from_exif_and_rtk_xmp(hand)
        folders['rtk_hand_geo_txt'] = hand
    rows = []
    clean = None
    for mode in georeference:
        for case, folder in folders.items():
            if mode == 'proposed' and case in ('rtk_xmp', 'rtk_hand_geo_txt') and clean is not None:
                continue      # every photo's sigmas alike: the proposed selection takes every fix, nothing changes
            with proposed_georeference() if mode == 'proposed' else contextlib.nullcontext():
                rep = _triangulate(folder, where / f'tri_{case}_{mode}')
            ck = rep['check']['rmse']
            row = {'case': case, 'preset': name, 'georeference': mode, 'photos': len(list(folder.glob('*.JPG'))),
                   'check_n': ck['n'], 'check_h_m': round(ck['horizontal_m'], 4),
                   'check_v_m': round(ck['vertical_m'], 4), 'verdict': rep.get('verdict', {}).get('status'),
                   'rtk_flags': rep.get('matching', {}).get('rtk_flags'), 'gnss_noise': rep.get('gnss_noise'),
                   'seed': preset(name, **seeded).seed, **geotag_height_lean(folder, rep)}
            if case == 'rtk_xmp':
                clean = row
            elif clean is not None:
                row['ratio_to_clean_h'] = round(row['check_h_m'] / clean['check_h_m'], 3)
                row['ratio_to_clean_v'] = round(row['check_v_m'] / clean['check_v_m'], 3)
            rows.append(row)
            sys.stderr.write(json.dumps(row) + '\n')
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--preset', default='tiny', help='simulator preset of the RTK photo survey')
    ap.add_argument('--out', help='JSON lines file (default bench/results/ppk_formats_<commit>.jsonl)')
    ap.add_argument('--skip-rtk', action='store_true')
    ap.add_argument('--skip-delay', action='store_true')
    ap.add_argument('--cases', default=','.join(tuple(RTK_CASES) + ('rtk_hand_geo_txt',)),
                    help='RTK photo survey cases, comma-separated (rtk_xmp first: the others get their ratio to it)')
    ap.add_argument('--layouts', action='store_true', help='the authors\' way on the M300 layout (section 3)')
    ap.add_argument('--real-waypoint', help='a real Waypoint export to measure section 3 on as well')
    ap.add_argument('--real-source', default='', help='where --real-waypoint comes from (written in its rows)')
    ap.add_argument('--seed', type=int, help='the simulator\'s seed for the RTK photo survey (default: the preset\'s)')
    ap.add_argument('--georeference', default='as_is',
                    help='as_is, proposed or both (comma-separated): proposed measures the change to '
                         'IncrementalAT._try_georeference this bench emulates (proposed_georeference)')
    a = ap.parse_args()
    commit = git('rev-parse', '--short', 'HEAD')
    clean = not git('status', '--porcelain', 'photogram_ros', 'bench/ppk_formats.py')
    out = Path(a.out or ROOT / 'bench' / 'results' / f'ppk_formats_{commit}.jsonl')
    head = {'commit': commit, 'clean_tree': clean, 'machine': machine_info(), 'cores': os.cpu_count(),
            'load_avg_before': [round(x, 2) for x in os.getloadavg()]}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for s in (() if a.skip_delay else (0.0, 1.0)):
            rows += delay_run(Path(tmp), s)
        if a.layouts:
            rows += layouts_run(Path(tmp), a.real_waypoint, a.real_source)
        if not a.skip_rtk:
            rows += rtk_runs(Path(tmp), a.preset, tuple(a.cases.split(',')), tuple(a.georeference.split(',')), a.seed)
    head['load_avg_after'] = [round(x, 2) for x in os.getloadavg()]
    with open(out, 'a') as f:
        for r in rows:
            f.write(json.dumps({**head, **r}) + '\n')
    sys.stderr.write(f'wrote {out}\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
