"""Incremental aerial triangulation on simulator flights with ground truth.

Keyframe observations come straight from the truth (sim/observations.py: 0.3 px noise, the GNSS
receiver error model of the mode); the figures are printed and gated at 1.5x their measured values
(docs/measurements.md).
"""

import dataclasses
import json

import numpy as np
import pytest

from photogram_ros.core.at_report import build_report
from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions, KeyframeRecord
from photogram_ros.errors import DataError
from photogram_ros.io.at_report import markdown, write_report
from photogram_ros.sim.observations import simulate_keyframes
from photogram_ros.sim.scenario import build_world, preset


@pytest.fixture(scope='module')
def world():
    cfg = preset('tiny', n_gcp=5, n_check=4)
    return cfg, build_world(cfg, np.random.default_rng(cfg.seed))


def _run(cfg, world, gnss_mode, use_gcps, outliers=0.0, seed=None):
    c = dataclasses.replace(cfg, seed=seed) if seed is not None else cfg
    sk = simulate_keyframes(c, gnss_mode=gnss_mode, outlier_fraction=outliers, world=world)
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m), use_gcps=use_gcps),
                       origin=sk.origin, control=sk.control)
    for r in sk.records:
        at.add_keyframe(r)
    at.full_adjustment()
    cam_err = np.array([at.kfs[k].map_T_cam[:3, 3] - sk.true_map_T_cam[k][:3, 3] for k in at.registered])
    rep = build_report(at, gsd_m=sk.gsd_m)
    chk = np.array([p['residual_m'] for p in rep['check']['points'] if p['name'].startswith('CHK')])
    return sk, at, rep, cam_err, chk


def _rmse_hv(chk):
    return np.sqrt(np.mean(np.sum(chk[:, :2] ** 2, axis=1))), np.sqrt(np.mean(chk[:, 2] ** 2))


def test_rtk_fixed_without_gcps(world):
    """Camera centres <= 3 cm (or the GNSS's own mean error), pooled check points within 1.5x their
    measured 0.26 GSD horizontal and 0.46 GSD vertical.

    The RTK model's bias wanders with a 60 s time constant, so on a 27 s flight it is nearly constant
    and cannot be averaged away without GCPs: the camera error of one flight sits at the mean GNSS
    error of that flight (printed as the floor). Four GNSS realizations are pooled.
    """
    cfg, w = world
    errs, chks = [], []
    for seed in (7, 8, 9, 10):
        sk, at, rep, cam_err, chk = _run(cfg, w, 'rtk_fixed', use_gcps=False, seed=seed)
        assert len(at.registered) == len(sk.records) and at.georeferenced
        gnss_err = np.array([sk.origin.geodetic_to_enu(r.fix.lat_deg, r.fix.lon_deg, r.fix.h_m)
                             - (T[:3, 3] + r.antenna_offset_map_m) for r, T in zip(sk.records, sk.true_map_T_cam)])
        floor = np.linalg.norm(gnss_err.mean(axis=0))
        rmse = np.sqrt(np.mean(np.sum(cam_err ** 2, axis=1)))
        h, v = _rmse_hv(chk)
        print(f'RTK seed {seed}: camera-centre RMSE {rmse * 100:.2f} cm (GNSS mean-error floor {floor * 100:.2f} cm), '
              f'check RMSE h {h / sk.gsd_m:.2f} GSD v {v / sk.gsd_m:.2f} GSD, reprojection '
              f"{rep['reprojection_rms_px']:.3f} px")
        # The adjustment adds little to the receiver's own unobservable mean error.
        assert rmse <= max(0.03, floor + 0.01)
        errs.append(cam_err)
        chks.append(chk)
    cam = np.sqrt(np.mean(np.sum(np.concatenate(errs) ** 2, axis=1)))
    h, v = _rmse_hv(np.concatenate(chks))
    print(f'RTK pooled: camera-centre RMSE {cam * 100:.2f} cm; check RMSE h {h / sk.gsd_m:.2f} GSD, '
          f'v {v / sk.gsd_m:.2f} GSD (GSD {sk.gsd_m * 100:.1f} cm)')
    assert h <= 1.5 * 0.26 * sk.gsd_m and v <= 1.5 * 0.46 * sk.gsd_m      # docs/measurements.md


def test_3d_gnss_with_five_gcps(world):
    cfg, w = world
    sk, at, rep, cam_err, chk = _run(cfg, w, '3d', use_gcps=True)
    h, v = _rmse_hv(chk)
    print(f"3D GNSS + {len(rep['gcp']['points'])} GCPs: check RMSE h {h / sk.gsd_m:.2f} GSD, v {v / sk.gsd_m:.2f} GSD "
          f"({len(chk)} check points); camera RMSE {np.sqrt(np.mean(np.sum(cam_err ** 2, 1))) * 100:.1f} cm; "
          f"estimated GNSS bias {np.round(at.gnss_bias_enu, 2)} m")
    assert len(rep['gcp']['points']) == 5 and len(chk) == 4
    assert h <= 1.5 * 0.18 * sk.gsd_m and v <= 1.5 * 0.17 * sk.gsd_m     # measured 0.18 / 0.17 GSD
    # Without the GCPs the same flight is off by the receiver's metre-level bias: they matter.
    sk2, at2, rep2, _, chk2 = _run(cfg, w, '3d', use_gcps=False)
    h2, v2 = _rmse_hv(chk2)
    print(f'3D GNSS without GCPs: check RMSE h {h2:.2f} m, v {v2:.2f} m')
    assert h2 > 5 * h


@pytest.mark.parametrize('mode,gcps', [('rtk_fixed', False), ('3d', True)])
def test_five_percent_gross_outliers(world, mode, gcps):
    cfg, w = world
    sk, at, rep, cam_err, chk = _run(cfg, w, mode, use_gcps=gcps, outliers=0.05)
    h, v = _rmse_hv(chk)
    cam = np.sqrt(np.mean(np.sum(cam_err ** 2, 1)))
    # How many corrupted observations survived in the adjusted block?
    bad = set(sk.outlier_tracks.tolist())
    kept_bad = 0
    for k in at.registered:
        kf = at.kfs[k]
        for t, a in zip(kf.track_ids, kf.active):
            kept_bad += bool(a and int(t) in bad and int(t) in at.points
                             and at.reprojection_px(kf.map_T_cam, at.points[int(t)][None], kf.uv[kf.index_of[int(t)]][None])[0] > 3)
    print(f'{mode} gcps={gcps} with 5 % outlier tracks ({len(bad)}): camera RMSE {cam * 100:.2f} cm, '
          f'check h {h / sk.gsd_m:.2f} v {v / sk.gsd_m:.2f} GSD, reprojection {rep["reprojection_rms_px"]:.3f} px, '
          f'large-residual outlier observations left {kept_bad}')
    assert rep['reprojection_rms_px'] < 0.5 and kept_bad == 0
    # Same flight and receiver without the outliers: the figures must not move.
    _, _, _, cam_err0, chk0 = _run(cfg, w, mode, use_gcps=gcps)
    cam0 = np.sqrt(np.mean(np.sum(cam_err0 ** 2, 1)))
    h0, v0 = _rmse_hv(chk0)
    print(f'  clean run: camera RMSE {cam0 * 100:.2f} cm, check h {h0 / sk.gsd_m:.2f} v {v0 / sk.gsd_m:.2f} GSD')
    if not gcps:   # with 3D GNSS the camera centres are not a must-show figure (the GCPs set the datum)
        assert abs(cam - cam0) < 0.005
    # With the outliers: RTK 0.31 / 0.76 GSD (clean 0.25 / 0.67), 3D GNSS + GCPs 0.15 / 0.16 (clean 0.18 / 0.17).
    h_gsd, v_gsd = (0.18, 0.17) if gcps else (0.31, 0.76)
    assert h <= 1.5 * h_gsd * sk.gsd_m and v <= 1.5 * v_gsd * sk.gsd_m


def test_georeference_waits_for_a_turn_and_report_files(world, tmp_path):
    cfg, w = world
    sk = simulate_keyframes(cfg, world=w)
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m)),
                       origin=sk.origin, control=sk.control)
    provisional_at = final_at = None
    for i, r in enumerate(sk.records):
        at.add_keyframe(r)
        if at.georeferenced and provisional_at is None:
            provisional_at = i
            err_prov = np.linalg.norm(at.kfs[i].map_T_cam[:3, 3] - sk.true_map_T_cam[i][:3, 3])
        if at.georeferenced and not at.georef_provisional and final_at is None:
            final_at = i
    sv = lambda C: np.linalg.svd(C - C.mean(0), compute_uv=False) / np.sqrt(len(C))  # noqa: E731
    print(f'provisional georeference (straight line, nadir roll) at keyframe {provisional_at}, camera error '
          f'{err_prov:.3f} m; final at keyframe {final_at}, centre spread then {sv(sk.true_map_T_cam[:final_at + 1, :3, 3]).round(2)} m')
    # Provisional on the straight first line, final once the turn makes the roll observable.
    assert sv(sk.true_map_T_cam[:provisional_at + 1, :3, 3])[1] < 0.2
    assert final_at is not None and sv(sk.true_map_T_cam[:final_at + 1, :3, 3])[1] > 1.0
    assert err_prov < 0.5
    # Bounded work: the window adjusts at most window_size keyframes.
    assert max(h.window_size for h in at.history if h.status != 'initialised') <= 10
    rep = build_report(at, assumptions=['test'], gsd_m=sk.gsd_m)
    md, js = write_report(rep, tmp_path)
    doc = json.loads(js.read_text())
    assert doc['check']['rmse']['n'] == 4 and len(doc['per_image']) == len(sk.records)
    assert 'Check points' in md.read_text() and 'CHK01' in markdown(rep)


def test_a_photo_that_missed_its_turn_registers_in_flight(world):
    """A keyframe that comes before the pair that starts the block is not registered in sequence; it is resected
    as soon as a later keyframe shares its tracks (IncrementalAT._orient_waiting), nothing is left for the
    end-of-flight retry, and it lands where the truth has it."""
    cfg, w = world
    sk = simulate_keyframes(cfg, world=w)
    late = 12
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m)),
                       origin=sk.origin, control=sk.control)
    for r in [sk.records[late]] + sk.records[:late] + sk.records[late + 1:]:
        at.add_keyframe(r)
    assert at.kfs[0].map_T_cam is not None and len(at.registered) == len(sk.records)
    assert 0 not in at.two_view_oriented    # resected: it shares points the block knows
    assert at.retry_unregistered() == 0
    at.full_adjustment()
    err = np.linalg.norm(at.kfs[0].map_T_cam[:3, 3] - sk.true_map_T_cam[late][:3, 3])
    others = np.array([np.linalg.norm(at.kfs[k].map_T_cam[:3, 3] - sk.true_map_T_cam[k - 1 if k <= late else k][:3, 3])
                       for k in at.registered if k != 0])
    print(f'retried keyframe centre error {err * 100:.1f} cm, others RMS {np.sqrt(np.mean(others ** 2)) * 100:.1f} cm')
    assert err < max(3 * np.sqrt(np.mean(others ** 2)), 0.05)


def test_bad_keyframe_raises(world):
    cfg, w = world
    at = IncrementalAT(cfg.camera())
    with pytest.raises(DataError):
        at.add_keyframe(KeyframeRecord(0, np.arange(5), np.zeros((4, 2))))


def _as_tracker_ids(records, max_length: int = 6):
    """Ids as a tracker gives them: a ground point seen again after a gap is a new track, and a
    track is lost after `max_length` keyframes (the tiny world keeps points in view for long)."""
    label, run, prev, nxt, out = {}, {}, set(), 0, []
    for r in records:
        ids = np.asarray(r.track_ids)
        for g in ids.tolist():
            run[g] = run.get(g, 0) + 1 if g in prev else 1
            if run[g] % max_length == 1 or max_length == 1:
                label[g], nxt = nxt, nxt + 1
        prev = set(ids.tolist())
        out.append(dataclasses.replace(r, track_ids=np.array([label[g] for g in ids.tolist()]), target_uv={}))
    return out


@pytest.mark.parametrize('ids', ['tracker', 'ground_points'])
def test_spilling_frozen_keyframes_changes_nothing(world, tmp_path, ids):
    """Long-flight memory: frozen keyframes go to disk and frozen points to compact arrays; the result
    must be the same, bit for bit. With tracker-like ids (a track ends for good) keyframes freeze
    along the flight. With the simulator's ground-point ids, seen again on the next line, a tiny
    window with no margin freezes tracks that come back (the thaw path); GCP and check targets
    are seen throughout, and the keyframes observing them stay in memory."""
    cfg, w = world
    sk = simulate_keyframes(dataclasses.replace(cfg, seed=7), gnss_mode='3d', outlier_fraction=0.05, world=w)
    if ids == 'tracker':
        sk.records = _as_tracker_ids(sk.records)
    ats = []
    for spill in (False, True):
        opt = IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m), window_size=4, max_fixed_keyframes=8,
                                 spill_frozen=spill, spill_dir=str(tmp_path / 'spill') if spill else '',
                                 freeze_margin_keyframes=0, freeze_every=1)
        at = IncrementalAT(sk.camera, opt, origin=sk.origin, control=sk.control)
        frozen_seen = 0
        for r in sk.records:
            at.add_keyframe(r)
            frozen_seen = max(frozen_seen, sum(kf.frozen for kf in at.kfs))
        at.full_adjustment()
        ats.append((at, frozen_seen, build_report(at, gsd_m=sk.gsd_m)))
    (a, _, rep_a), (b, frozen_b, rep_b) = ats
    print(f'{len(b.kfs)} keyframes, at most {frozen_b} frozen at once; after the end: {b.memory_stats()}')
    # Tracker ids never come back; ground-point ids do, so freezing stops after a few thaws.
    assert bool(b.freezing_stopped) == (ids == 'ground_points')
    if ids == 'ground_points':
        assert b.points.frozen_bytes > 0
    else:
        assert frozen_b >= len(b.kfs) // 4 and any((tmp_path / 'spill').iterdir())
    assert a.registered == b.registered
    for k in a.registered:
        assert np.array_equal(a.kfs[k].map_T_cam, b.kfs[k].map_T_cam)
    ia, pa = a.points.arrays()
    ib, pb = b.points.arrays()
    assert np.array_equal(ia, ib) and np.array_equal(pa, pb)
    assert [h.cost for h in a.history] == [h.cost for h in b.history]
    assert rep_a['check'] == rep_b['check'] and rep_a['reprojection_rms_px'] == rep_b['reprojection_rms_px']


def _two_view_tracks_only(records):
    """The same keyframes with every track cut into pieces of two consecutive sightings: no point is
    seen by three keyframes (photo-rate matching at its worst), so resection never has known points."""
    seen, out = {}, []
    for r in records:
        ids = np.empty(len(r.track_ids), np.int64)
        for j, t in enumerate(np.asarray(r.track_ids).tolist()):
            n = seen.get(t, 0)
            seen[t] = n + 1
            ids[j] = t * 1000 + n // 2 if t >= 0 else t
        out.append(dataclasses.replace(r, track_ids=ids))
    return out


def test_keyframes_without_three_view_points_orient_from_relative_pose_and_gnss(world):
    """Resection needs points seen before; with two-view tracks only it never has one. The relative pose
    to the registered keyframe sharing most tracks, scaled by GNSS (or by the known points it sees),
    orients every keyframe instead of stalling; without that fallback only the first pair orients."""
    cfg, w = world
    sk = simulate_keyframes(cfg, gnss_mode='3d', world=w)
    recs = _two_view_tracks_only(sk.records)
    shown = {}
    for fallback in (False, True):
        at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m),
                                                         relative_fallback=fallback), origin=sk.origin)
        for r in recs:
            at.add_keyframe(r)
        shown[fallback] = at
    off, on = shown[False], shown[True]
    on.full_adjustment()
    err = np.array([on.kfs[k].map_T_cam[:3, 3] - sk.true_map_T_cam[k][:3, 3] for k in on.registered])
    rms = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
    fix_err = np.array([on.kfs[k].fix_enu - sk.true_map_T_cam[k][:3, 3] for k in on.registered])
    fix_rms = float(np.sqrt(np.mean(np.sum(fix_err ** 2, axis=1))))
    print(f'{len(recs)} keyframes: {len(off.registered)} oriented by resection alone, {len(on.registered)} with the '
          f'relative fallback; camera centres {rms:.2f} m RMS, the fixes themselves {fix_rms:.2f} m (3D GNSS)')
    assert len(off.registered) <= 3
    assert len(on.registered) >= 0.9 * len(recs) and on.georeferenced
    # Two-view tracks hold the block together only weakly: it sits about where its fixes put it (with
    # three-view tracks this flight's cameras are 3.4 m off, the fixes' own bias).
    assert rms < 1.6 * fix_rms


def _lost_every_track(records, k_break: int):
    """The same keyframes with every track id changed from keyframe k_break on: the tracker lost them all
    (a long gap in the frames), so nothing links the flight after the break to the block before it."""
    return [r if i < k_break else dataclasses.replace(r, track_ids=np.asarray(r.track_ids) + 10**6, target_uv={})
            for i, r in enumerate(records)]


@pytest.mark.parametrize('gnss_mode', ['rtk_fixed', '3d'])
def test_the_flight_after_every_track_was_lost_joins_as_a_segment(world, gnss_mode):
    """Half the flight shares no tie point with the first half. Without segments none of it orients; with
    them it is a block of its own that joins through its GNSS, as accurate as the GNSS places it."""
    cfg, w = world
    sk = simulate_keyframes(cfg, gnss_mode=gnss_mode, world=w, attitude_sigma_deg=None)
    kb = len(sk.records) // 2
    recs = _lost_every_track(sk.records, kb)
    out = {}
    for segments in (False, True):
        at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m), segments=segments),
                           origin=sk.origin)
        reps = [at.add_keyframe(r) for r in recs]
        at.full_adjustment()
        out[segments] = (at, reps)
    off, (on, reps) = out[False][0], out[True]
    err = lambda at, ks: float(np.sqrt(np.mean([np.sum((at.kfs[k].map_T_cam[:3, 3] - sk.true_map_T_cam[k][:3, 3]) ** 2)
                                                 for k in ks])))
    after = [k for k in on.registered if k >= kb]
    before = [k for k in on.registered if k < kb]
    fix = float(np.sqrt(np.mean([np.sum((on.kfs[k].fix_enu - sk.true_map_T_cam[k][:3, 3]) ** 2) for k in after])))
    print(f'{gnss_mode}: after the break {len(after)} of {len(recs) - kb} oriented with segments, '
          f'{sum(k >= kb for k in off.registered)} without; centres {err(on, before):.3f} m before it, '
          f'{err(on, after):.3f} m after (the fixes there {fix:.3f} m)')
    assert not any(k >= kb for k in off.registered)
    assert len(after) >= len(recs) - kb - 1 and on.segments_joined == 1
    if gnss_mode == 'rtk_fixed':   # joined in flight, once its GNSS placed it (3D: at the end)
        assert any(r.joined for r in reps)
    assert err(on, after) <= max(1.5 * err(on, before), 0.1)
