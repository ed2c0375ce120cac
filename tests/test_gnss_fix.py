"""gnss_fix.GnssFix, the fix the tracker and the adjustment consume: conversions from a receiver fix and
through a NavSatFix keep every value; a covariance has one shape."""

import math

import numpy as np
import pytest

from photogram_ros.core import gnss_fix as gf
from photogram_ros.errors import DataError


def _receiver_fix(**kw):
    raw = dict(receiver=0, time_usec=0, fix_type=gf.RTK_FIXED, lat_e7=473_977_420, lon_e7=85_455_940,
               alt_msl_mm=488_000, h_acc_mm=14, v_acc_mm=30)
    raw.update(kw)
    return gf.make_fix(gf.RawGnss(**raw), 1_700_000_000.123456789).fix


def test_a_receiver_fix_is_the_consumed_fix_with_its_epoch_quality_and_source():
    fix = _receiver_fix()
    assert isinstance(fix, gf.GnssFix) and gf.GnssFix.from_fix(fix) is fix
    assert fix.cov_enu_m2.shape == (3, 3) and fix.var_enu_m2 == pytest.approx((0.014 ** 2, 0.014 ** 2, 0.03 ** 2))
    assert np.count_nonzero(fix.cov_enu_m2 - np.diag(np.diag(fix.cov_enu_m2))) == 0
    assert abs(fix.stamp_ns - 1_700_000_000_123_456_789) < 1000 and fix.stamp_ns == gf.stamp_ns_of(fix.t_s)
    assert fix.t_s == 1_700_000_000.123456789         # the receiver's time, to the bit
    assert fix.status == gf.STATUS_GBAS_FIX and fix.cov_type == gf.COV_DIAGONAL_KNOWN and not fix.interpolated
    assert fix.quality == gf.Q_FIX and fix.fix_type == gf.RTK_FIXED and fix.native_scale == 'GPS_FIX_TYPE'
    assert fix.source == 'GPS_RAW_INT' and fix.height_datum == 'ellipsoid' and fix.height_source == 'msl+EGM2008'
    assert fix.horizontal_sigma_m == pytest.approx(0.014)
    assert fix.sigma_enu_m == pytest.approx([0.014, 0.014, 0.03])


def test_no_fix_stays_no_fix():
    g = _receiver_fix(fix_type=gf.NO_FIX)
    assert g.status == gf.STATUS_NO_FIX and g.quality == gf.Q_NONE and math.isnan(g.lat_deg)
    assert g.cov_type == gf.COV_UNKNOWN and not g.has_position


@pytest.mark.parametrize('fix_type, q', [(gf.FIX_2D, gf.Q_SINGLE), (gf.FIX_3D, gf.Q_SINGLE), (gf.DGPS, gf.Q_DGPS),
                                         (gf.RTK_FLOAT, gf.Q_FLOAT), (gf.RTK_FIXED, gf.Q_FIX), (gf.PPP, gf.Q_PPP)])
def test_one_quality_scale_keeps_the_receivers_own_number(fix_type, q):
    g = _receiver_fix(fix_type=fix_type)
    assert g.quality == q and g.fix_type == fix_type and g.status == gf.navsat_status(fix_type)


@pytest.mark.parametrize('status', [gf.STATUS_NO_FIX, gf.STATUS_FIX, gf.STATUS_SBAS_FIX, gf.STATUS_GBAS_FIX])
def test_a_navsatstatus_goes_to_the_quality_scale_and_back_unchanged(status):
    g = gf.GnssFix(47.0, 8.0, 500.0, np.eye(3), 1, status)
    assert g.status == status and g.quality == gf.quality_of_status(status)


def test_an_exif_height_becomes_ellipsoidal_with_the_reading_given_and_unknown_sigmas_take_the_defaults():
    g = gf.GnssFix(47.0, 8.0, 100.0, np.zeros((3, 3)), quality=gf.Q_SINGLE, height_datum='exif', source='EXIF')
    e = g.at(5, 3.0, 6.0, 'ellipsoidal')
    assert (e.stamp_ns, e.h_m, e.height_datum, e.cov_type) == (5, 100.0, 'ellipsoid', gf.COV_APPROXIMATED)
    assert e.sigma_enu_m == pytest.approx([3.0, 3.0, 6.0]) and e.source == 'EXIF'
    r = g.at(5, 3.0, 6.0, 'relative', 20.0, 'ellipsoidal')
    assert r.h_m == 120.0
    m = g.at(5, 3.0, 6.0, 'msl')
    assert m.h_m == pytest.approx(100.0 + gf.undulation_m(47.0, 8.0), abs=0.05)
    known = gf.GnssFix(47.0, 8.0, 100.0, np.diag([0.01, 0.01, 0.04]), cov_type=gf.COV_DIAGONAL_KNOWN)
    assert known.at(7, 3.0, 6.0).sigma_enu_m == pytest.approx([0.1, 0.1, 0.2])


def test_a_quality_off_the_scale_or_an_unknown_datum_is_refused():
    with pytest.raises(DataError, match='quality'):
        gf.GnssFix(47.0, 8.0, 500.0, np.eye(3), quality=7)
    with pytest.raises(DataError, match='datum'):
        gf.GnssFix(47.0, 8.0, 500.0, np.eye(3), height_datum='geoid')


def test_dict_and_navsatfix_round_trips():
    from photogram_ros import msgs
    g = gf.GnssFix(47.1, 8.5, 510.25, np.array([[4.0, 0.5, 0.0], [0.5, 9.0, 0.1], [0.0, 0.1, 16.0]]), 123_456_789_012,
                   gf.STATUS_SBAS_FIX, gf.COV_APPROXIMATED)
    d = msgs.fix_from_navsatfix(msgs.navsatfix_from_gnss_fix(g, 'gps'))
    assert d['frame_id'] == 'gps' and set(g.as_dict()) == set(d) - {'frame_id'}
    for back in (gf.GnssFix.from_dict(g.as_dict()), gf.GnssFix.from_dict(d)):
        for k in ('stamp_ns', 'lat_deg', 'lon_deg', 'h_m', 'status', 'cov_type', 'interpolated'):
            assert getattr(back, k) == getattr(g, k), k
        assert np.array_equal(back.cov_enu_m2, g.cov_enu_m2)


def test_positional_form_of_the_adjustment_still_reads():
    # core.incremental builds GnssFix(lat, lon, h, cov): the same call works here, stamp 0.
    g = gf.GnssFix(47.0, 8.0, 500.0, np.eye(3) * 0.01)
    assert g.stamp_ns == 0 and g.status == gf.STATUS_FIX and g.cov_type == gf.COV_UNKNOWN


def test_three_variances_are_not_a_covariance():
    with pytest.raises(DataError, match='3x3'):
        gf.GnssFix(47.0, 8.0, 500.0, (1.0, 1.0, 4.0))
