"""Fixes, covariance, heights and time mapping: unit answers, the simulator's truth, real logs."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from conftest import shared_data
from photogram_ros.core import geoid
from photogram_ros.core import gnss_fix as gf
from photogram_ros.core.timesync import BootClock, lower_envelope
from photogram_ros.io.mavlink import FixEvent, Ingest, Trigger, Attitude, fixes_from_messages, read_tlog
from test_mavlink_parse import sample_dir  # noqa: F401  (fixture)

# --- fix conversion ------------------------------------------------------------------------------


def _raw(**kw):
    base = dict(receiver=0, time_usec=1_000_000, fix_type=3, lat_e7=491234567, lon_e7=-1231234567,
                alt_msl_mm=100_000)
    base.update(kw)
    return gf.RawGnss(**base)


def test_status_mapping_keeps_full_fix_type():
    want = {0: -1, 1: -1, 2: 0, 3: 0, 4: 1, 5: 2, 6: 2, 7: 0, 8: 1}
    assert {ft: gf.navsat_status(ft) for ft in range(9)} == want
    fl = gf.make_fix(_raw(fix_type=5, h_acc_mm=300, v_acc_mm=400), 1.0).fix
    fx = gf.make_fix(_raw(fix_type=6, h_acc_mm=14, v_acc_mm=30), 1.0).fix
    assert fl.status == fx.status == gf.STATUS_GBAS_FIX and (fl.fix_type, fx.fix_type) == (5, 6)


def test_covariance_sources():
    known = gf.make_fix(_raw(h_acc_mm=20, v_acc_mm=30, eph=80, epv=120), 0.0).fix
    assert known.cov_type == gf.COV_DIAGONAL_KNOWN
    assert known.var_enu_m2 == pytest.approx((0.0004, 0.0004, 0.0009))
    approx = gf.make_fix(_raw(eph=120, epv=200), 0.0, gf.ErrorModel()).fix
    assert approx.cov_type == gf.COV_APPROXIMATED
    assert approx.var_enu_m2 == pytest.approx(((1.2 * 2.5) ** 2, (1.2 * 2.5) ** 2, (2.0 * 2.5) ** 2))
    no_vdop = gf.make_fix(_raw(eph=100, epv=65535), 0.0).fix
    assert no_vdop.var_enu_m2[2] == pytest.approx((1.5 * 2.5) ** 2)
    unknown = gf.make_fix(_raw(eph=65535, epv=65535), 0.0).fix
    assert unknown.cov_type == gf.COV_UNKNOWN and math.isinf(unknown.sigma_h_m)


def test_heights_ellipsoidal():
    ell = gf.make_fix(_raw(alt_ellipsoid_mm=83_456), 0.0).fix
    assert ell.h_m == pytest.approx(83.456) and ell.height_source == 'alt_ellipsoid'
    msl = gf.make_fix(_raw(), 0.0).fix
    n = geoid.undulation_m(49.1234567, -123.1234567)
    assert -25 < n < -10                                # Vancouver: the geoid is ~17 m below the ellipsoid
    assert msl.h_m == pytest.approx(100.0 + n, abs=0.01) and msl.height_source == 'msl+EGM2008'


def test_bad_fixes_rejected_no_fix_has_no_position():
    assert gf.make_fix(_raw(lat_e7=950_000_000), 0.0).fix is None
    assert gf.make_fix(_raw(lat_e7=0, lon_e7=0), 0.0).fix is None
    assert gf.make_fix(_raw(), float('nan')).fix is None
    nofix = gf.make_fix(_raw(fix_type=1), 0.0).fix
    assert nofix.status == gf.STATUS_NO_FIX and not nofix.has_position and math.isnan(nofix.lat_deg)


def test_choose_best_receiver():
    f3 = gf.make_fix(_raw(receiver=0, eph=90, epv=120), 10.0).fix
    rtk = gf.make_fix(_raw(receiver=1, fix_type=6, h_acc_mm=15, v_acc_mm=25), 10.0).fix
    fl = gf.make_fix(_raw(receiver=1, fix_type=5, h_acc_mm=250, v_acc_mm=400), 10.0).fix
    assert gf.choose_best({0: f3, 1: rtk}, 10.1) == 1
    assert gf.choose_best({0: f3, 1: fl}, 10.1) == 1
    assert gf.choose_best({0: f3, 1: rtk}, 12.0, max_age_s=1.0) is None     # both stale
    old_rtk = gf.make_fix(_raw(receiver=1, fix_type=6, h_acc_mm=15, v_acc_mm=25), 8.0).fix
    assert gf.choose_best({0: f3, 1: old_rtk}, 10.0, max_age_s=1.0) == 0


# --- time sync -----------------------------------------------------------------------------------


def _drifting_clock(seed=0, n=600, drift_ppm=5.0, boot_unix=1_700_001_000.0):
    rng = np.random.default_rng(seed)
    t_unix = 1_700_002_000.0 + np.arange(n) + rng.uniform(0, 0.5, n)   # a plausible UNIX time (2023)
    boot = (t_unix - boot_unix) * (1 + drift_ppm * 1e-6)
    return t_unix, boot, rng


def test_system_time_fit_sub_millisecond_with_drift():
    t_unix, boot, _ = _drifting_clock()
    clk = BootClock()
    for tu, b in zip(t_unix, boot):
        assert clk.add_system_time(int(b * 1000), int(tu * 1e6)) == 'ok'
    err = [clk.to_time(b) - tu for tu, b in zip(t_unix[-200:], boot[-200:])]
    assert np.max(np.abs(err)) < 0.0006
    q = clk.quality()
    assert q['drift_ppm'] == pytest.approx(-5.0, abs=1.0) and q['source'] == 'system_time'


def test_arrival_lower_envelope_robust_to_latency():
    t_unix, boot, rng = _drifting_clock(seed=1, n=300)
    clk = BootClock()
    latency = 0.004 + rng.exponential(0.03, len(boot))
    latency[::17] += 0.5                                # bursts of a congested link
    for b, tu, lat in zip(boot, t_unix, latency):
        clk.add_arrival(b, tu + lat)
    err = np.array([clk.to_time(b, 'arrival') - tu for tu, b in zip(t_unix[-50:], boot[-50:])])
    # Maps to arrival time of the fastest packets: the 4 ms minimum latency, within a millisecond.
    assert np.all(np.abs(err - 0.004) < 0.0015), err
    # A mean fit would be biased by the mean latency (~65 ms): the envelope is not.
    assert abs(np.mean(latency) - 0.004) > 0.03


def test_lower_envelope_exact_line():
    x = np.linspace(0, 100, 50)
    y = 3.0 + 2e-6 * x + np.r_[0.0, np.abs(np.sin(x[1:-1])) * 0.1, 0.0]
    b, a = lower_envelope(x, y)
    assert b == pytest.approx(2e-6, abs=1e-9) and a == pytest.approx(3.0, abs=1e-9)


def test_clock_outlier_jump_and_reboot():
    T = 1_700_000_000.0
    clk = BootClock()
    for k in range(30):
        clk.add_system_time(10_000 + 1000 * k, int((T + 500.0 + k) * 1e6))
    assert clk.add_system_time(40_000, int((T + 530.0 + 7.0) * 1e6)) == 'outlier'     # one wild pair
    assert clk.to_time(40.0) == pytest.approx(T + 530.0 - 0.0005, abs=1e-3)
    events = [clk.add_system_time(41_000 + 1000 * k, int((T + 631.0 + k) * 1e6)) for k in range(3)]
    assert events == ['outlier', 'outlier', 'jump'] and clk.to_time(45.0) == pytest.approx(T + 635.0, abs=1e-3)
    # A reboot (boot time from 43 s back to 2 s) is believed when it repeats; the fit holds meanwhile.
    events = [clk.add_system_time(2_000 + 1000 * k, int((T + 700.0 + k) * 1e6)) for k in range(3)]
    assert events == ['outlier', 'outlier', 'reboot']
    assert clk.to_time(5.0) == pytest.approx(T + 703.0, abs=1e-3)


def test_clock_refuses_what_it_cannot_explain():
    """Poisoned time: a UNIX time outside 2000-2100, one wild pair, one wild boot time, and a fit after a
    reboot that would jump back in time are refused (and said: `detail`), the fit stays."""
    T = 1_780_000_000.0
    clk = BootClock()
    for k in range(10):
        assert clk.add_system_time(100_000 + 1000 * k, int((T + k) * 1e6)) == 'ok'
    assert clk.add_system_time(110_000, int(4_115_491_200 * 1e6)) == 'implausible'    # 2100
    assert '2000-2100' in clk.detail
    assert clk.add_system_time(110_000, int((T + 2.4e9) * 1e6)) == 'implausible'
    assert clk.add_system_time(110_000, int((T - 1.0e9) * 1e6)) == 'implausible'      # 1994
    assert clk.add_system_time(110_000, int((T + 86_400 * 300) * 1e6)) == 'outlier'   # plausible, but alone
    assert clk.add_system_time(0 + 1, int((T + 10) * 1e6)) == 'outlier'               # boot 1 ms: not a reboot
    assert clk.add_system_time(111_000, int((T + 11) * 1e6)) == 'ok'
    assert clk.to_time(112.0) == pytest.approx(T + 12.0, abs=1e-3)
    # After a reset (a reboot the data saw) the new fit must continue the UNIX time: not 1 h earlier.
    clk.reset()
    assert clk.add_system_time(5_000, int((T + 11 - 3600 + 5) * 1e6)) == 'outlier'
    assert 'does not continue' in clk.detail and clk.to_time(6.0) is None
    assert clk.add_system_time(6_000, int((T + 20 + 6) * 1e6)) == 'ok'                 # 20 s later: fine
    assert clk.to_time(7.0) == pytest.approx(T + 27.0, abs=1e-3)


# --- the simulator's flight: fixes against ground truth ------------------------------------------


def test_sample_flight_fixes_match_truth(sample_dir):  # noqa: F811
    from photogram_ros.sim.truth import GroundTruth
    msgs, _ = read_tlog(sample_dir / 'flight.tlog')
    events, ing = fixes_from_messages(msgs)
    gt = GroundTruth.load(sample_dir)
    sent = [f for f in gt.fixes]
    assert len(events) == len(sent)
    t_truth = np.array([f['t_fix_unix_s'] for f in sent])
    dt, d_sent, z = [], [], []
    for ev in events:
        f = ev.fix
        k = int(np.argmin(np.abs(t_truth - f.t_s)))
        tr = sent[k]
        dt.append(f.t_s - tr['t_fix_unix_s'])
        assert f.fix_type == tr['fix_type'] and ev.best
        enu = np.asarray(gt.origin.geodetic_to_enu(f.lat_deg, f.lon_deg, f.h_m), float).ravel()
        d_sent.append(enu - (np.array(tr['antenna_enu']) + np.array(tr['error_enu_m'])))
        z.append((enu - np.array(tr['antenna_enu'])) / np.sqrt(f.var_enu_m2))
    dt, d_sent, z = np.abs(dt), np.abs(d_sent), np.abs(z)
    assert dt.max() < 0.001                           # fix epoch, not arrival (+60 ms): to a millisecond
    assert d_sent[:, :2].max() < 0.007 and d_sent[:, 2].max() < 0.001   # 1e-7 deg and 1 mm quantisation
    assert z.max() < 5.0                              # errors within the reported 1-sigma accuracy
    assert ing.diagnostics()['time_sync_synced'] is True


def test_sample_flight_attitude_and_triggers(sample_dir):  # noqa: F811
    from photogram_ros.core.rotations import R_from_quat
    from photogram_ros.sim.truth import GroundTruth
    gt = GroundTruth.load(sample_dir)
    msgs, _ = read_tlog(sample_dir / 'flight.tlog')
    ing = Ingest()
    events = [e for m, t in msgs for e in ing.handle(m, t)]
    trig = [e for e in events if isinstance(e, Trigger)]
    att = [e for e in events if isinstance(e, Attitude)]
    assert len(trig) == len(gt.frames) and all(t.source == 'CAMERA_FEEDBACK' for t in trig)
    for tr, fr in zip(trig, gt.frames):
        assert abs(tr.t_s * 1e9 - fr.stamp_ns) < 2e3
        assert tr.fix.fix_type == gf.RTK_FIXED and tr.fix.quality == gf.Q_FIX and tr.fix.stamp_ns == round(tr.t_s * 1e9)
    # Euler ATTITUDE only until the first quaternion arrives.
    assert sum(a.source == 'ATTITUDE' for a in att) <= 1 and len(att) > 700
    # Body FLU in ENU: the body's x axis is the flight direction, so it follows the track.
    fr = gt.frames[len(gt.frames) // 2]
    a = min(att, key=lambda a: abs(a.t_s * 1e9 - fr.stamp_ns))
    R = R_from_quat(a.q_enu_flu_xyzw)
    assert abs(np.linalg.det(R) - 1) < 1e-9 and R[2, 2] > 0.95     # near level: body up ~ ENU up
    # The body x axis (FLU forward) follows the flight direction between neighbouring frames.
    k = len(gt.frames) // 2
    track = gt.frames[k + 1].map_T_cam[:3, 3] - gt.frames[k - 1].map_T_cam[:3, 3]
    fwd = R @ [1.0, 0.0, 0.0]
    assert np.dot(fwd[:2], track[:2]) / np.linalg.norm(track[:2]) / np.linalg.norm(fwd[:2]) > 0.9


def test_triggers_from_camera_trigger_only(sample_dir):  # noqa: F811
    """Without CAMERA_FEEDBACK, a trigger gets its position interpolated from the bracketing fixes."""
    from photogram_ros.sim.truth import GroundTruth
    gt = GroundTruth.load(sample_dir)
    msgs, _ = read_tlog(sample_dir / 'flight.tlog')
    ing = Ingest(trigger_source='trigger')
    trig = [e for m, t in msgs for e in ing.handle(m, t) if isinstance(e, Trigger)]
    assert len(trig) >= len(gt.frames) - 1 and all(t.source == 'CAMERA_TRIGGER' for t in trig)
    for tr in trig:
        fr = min(gt.frames, key=lambda f: abs(f.stamp_ns - tr.t_s * 1e9))
        enu = np.asarray(gt.origin.geodetic_to_enu(tr.fix.lat_deg, tr.fix.lon_deg, tr.fix.h_m), float).ravel()
        assert np.linalg.norm(enu - fr.antenna_enu) < 0.15        # 5 m/s * interpolation + RTK noise


# --- real logs -----------------------------------------------------------------------------------


def test_phoenix_fixes_against_plain_pymavlink():
    msgs, _ = read_tlog(shared_data('mavlink', 'phoenix_mission1_2018-09-17_16-44-06.tlog'))
    events, ing = fixes_from_messages(msgs)
    gps = [(m, t) for m, t in msgs if m.get_type() == 'GPS_RAW_INT']
    with_pos = [e for e in events if e.fix.has_position]
    # The autopilot reboots mid-log (boot time 224 s -> 26 s): the fix sent before the new
    # SYSTEM_TIME waits for it instead of being stamped with the old boot's clock.
    assert ing.counts['clock_reboot'] == 1
    assert len(with_pos) == 781 and Counter(e.fix.fix_type for e in with_pos) == {3: 781}
    assert len(events) == 786 and sum(not e.fix.has_position for e in events) == 5
    t = np.array([e.fix.t_s for e in with_pos])
    assert np.all(np.diff(t) > 0.1)                    # strictly increasing across the reboot
    good = [m for m, _ in gps if m.fix_type >= 2]
    by_time = {m.time_usec: m for m in good}
    t_log = np.array([t for _, t in msgs])
    for e in with_pos:
        f = e.fix
        assert t_log[0] - 5 < f.t_s < t_log[-1] + 5                  # mapped into the log's own UNIX time
        assert f.status == gf.STATUS_FIX and f.cov_type in (gf.COV_DIAGONAL_KNOWN, gf.COV_APPROXIMATED)
    lat = np.array([m.lat * 1e-7 for m in good])
    got = np.array([e.fix.lat_deg for e in with_pos])
    assert np.allclose(np.sort(got), np.sort(lat)[-len(got):]) or np.allclose(np.sort(got), np.sort(lat)[:len(got)])
    assert 49.0 < np.median(got) < 49.5 and len(by_time) >= 700


def test_sitl_vtol_is_rtk_fixed():
    msgs, _ = read_tlog(shared_data('mavlink', 'sitl_vtol.tlog'))
    events, _ = fixes_from_messages(msgs)
    pos = [e.fix for e in events if e.fix.has_position]
    assert len(pos) > 700 and {f.fix_type for f in pos} == {gf.RTK_FIXED}
    assert {f.status for f in pos} == {gf.STATUS_GBAS_FIX}


def test_ingest_survives_garbage_values():
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    ing = Ingest(clock_source='arrival')
    msgs = [mav.timesync_encode(0, 5_000_000_000), mav.system_time_encode(0, 5000)]
    out = []
    for m in msgs:
        m.pack(mav)
        out += ing.handle(m, 100.0)
    bad = mav.gps_raw_int_encode(5_100_000, 3, 2_000_000_000, 0, 0, 100, 100, 0, 0, 9)
    nanq = mav.attitude_quaternion_encode(5100, float('nan'), 0, 0, 0, 0, 0, 0)
    good = mav.gps_raw_int_encode(5_200_000, 3, 491234567, -1231234567, 100000, 100, 150, 0, 0, 9)
    back = mav.gps_raw_int_encode(5_150_000, 3, 491234567, -1231234567, 100000, 100, 150, 0, 0, 9)
    for m in (bad, nanq, good, back):
        m.pack(mav)
        m._header = mavlink2.MAVLink_header(m.id, 0, 0, 0, 0, 1, 1)
        out += ing.handle(m, 100.3)
    fixes = [e for e in out if isinstance(e, FixEvent)]
    assert len(fixes) == 1 and fixes[0].fix.t_s == pytest.approx(100.2, abs=1e-6)
    assert ing.counts['fix_rejected'] == 1 and ing.counts['attitude_rejected'] == 1
    assert ing.counts['fix_time_not_increasing'] == 1 and len(ing.problems) == 3


def _two_receiver_stream(gps2_types):
    """1 Hz SYSTEM_TIME and 5 Hz GPS_RAW_INT (3D) + GPS2_RAW (fix types from gps2_types)."""
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    out = []
    boot0 = 100.0
    for k in range(len(gps2_types)):
        boot = boot0 + 0.2 * k
        if k % 5 == 0:
            out.append(mav.system_time_encode(int((1_700_000_000 + boot) * 1e6), int(boot * 1000)))
        out.append(mav.gps_raw_int_encode(int(boot * 1e6), 3, 471000000 + k, 85000000, 500000, 90, 140, 0, 0, 12,
                                          547000, 1800, 2500))
        ft = gps2_types[k]
        out.append(mav.gps2_raw_encode(int(boot * 1e6), ft, 471000000 + k, 85000000, 500000, 60, 90, 0, 0, 20,
                                       3, 1, 0, 547000, 20 if ft == 6 else 300, 30 if ft == 6 else 450))
    pkts = b''.join(m.pack(mav) for m in out)
    from photogram_ros.io.mavlink import MavlinkStream
    return MavlinkStream().feed(pkts, final=True)


def test_two_receivers_best_chosen_and_switched():
    types = [6] * 10 + [1] * 10 + [5] * 10
    msgs = _two_receiver_stream(types)
    ing = Ingest()
    events = [e for m in msgs for e in ing.handle(m, None) if isinstance(e, FixEvent)]
    best = [(e.fix.receiver, e.fix.fix_type) for e in events if e.best]
    assert Counter(e.fix.receiver for e in events if e.per_receiver) == {0: 30, 1: 30}
    # One /gps/fix per epoch: GPS1 arrives first in epoch 0; then RTK fixed on GPS2 wins; while
    # GPS2 has no fix GPS1 (3D) is used, from the epoch GPS2 lost it; RTK float beats 3D again
    # from the epoch after GPS1 had already filled.
    assert best == [(0, 3)] + [(1, 6)] * 9 + [(0, 3)] * 11 + [(1, 5)] * 9
    t = [e.fix.t_s for e in events if e.best]
    assert np.all(np.diff(t) > 0.19)
    assert ing.diagnostics()['fix_type'] == 'RTK_FLOAT'


@pytest.mark.slow
def test_faulty_flight_outage_float_and_corruption(tmp_path):
    """Simulated outage (NO_FIX, no positions), a switch to RTK float, and a corrupted stretch of link."""
    from photogram_ros.sim.scenario import START_UNIX_S, preset, simulate
    out = tmp_path / 'faulty'
    gt = simulate(preset('tiny', gnss_outages=[(5, 10)], mavlink_corruption=[(12, 15)],
                         gnss_changes=[(20, 'rtk_float')]), out)
    msgs, stats = read_tlog(out / 'flight.tlog')
    assert stats.crc_errors > 0
    events, _ = fixes_from_messages(msgs)
    fixes = [e.fix for e in events if e.best]
    rel = np.array([f.t_s - START_UNIX_S for f in fixes])
    inside = [f for f, t in zip(fixes, rel) if 5.05 < t < 9.95]
    assert inside and all(f.status == gf.STATUS_NO_FIX and not f.has_position for f in inside)
    after = [f for f, t in zip(fixes, rel) if t > 20.5 and f.has_position]
    assert after and {f.fix_type for f in after} == {gf.RTK_FLOAT}
    assert min(f.var_enu_m2[0] for f in after) > 10 * max(f.var_enu_m2[0] for f, t in zip(fixes, rel)
                                                          if 16 < t < 19.5 and f.has_position)
    # Every fix sent outside the corrupted stretch is decoded and stamped at its epoch.
    sent = [f for f in gt.fixes if not 12 <= f['t_fix_unix_s'] + 0.06 - START_UNIX_S < 15.1]
    t_got = np.array([f.t_s for f in fixes])
    for f in sent:
        assert np.min(np.abs(t_got - f['t_fix_unix_s'])) < 0.001
    # Positions against truth, normalised by the reported sigma.
    for f in fixes:
        if not f.has_position:
            continue
        tr = min(gt.fixes, key=lambda x: abs(x['t_fix_unix_s'] - f.t_s))
        enu = np.asarray(gt.origin.geodetic_to_enu(f.lat_deg, f.lon_deg, f.h_m), float).ravel()
        assert np.all(np.abs(enu - np.array(tr['antenna_enu'])) / np.sqrt(f.var_enu_m2) < 5.0)
