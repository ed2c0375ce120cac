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


def test_from_receiver_fix_keeps_position_variances_and_epoch():
    fix = _receiver_fix()
    g = gf.GnssFix.from_fix(fix)
    assert (g.lat_deg, g.lon_deg, g.h_m) == (fix.lat_deg, fix.lon_deg, fix.h_m)
    assert g.cov_enu_m2.shape == (3, 3) and tuple(np.diag(g.cov_enu_m2)) == fix.var_enu_m2
    assert np.count_nonzero(g.cov_enu_m2 - np.diag(np.diag(g.cov_enu_m2))) == 0
    assert g.stamp_ns == int(round(fix.t_s * 1e9)) and abs(g.stamp_ns - 1_700_000_000_123_456_789) < 1000
    assert g.status == gf.STATUS_GBAS_FIX and g.cov_type == gf.COV_DIAGONAL_KNOWN and not g.interpolated
    assert g.horizontal_sigma_m == pytest.approx(0.014)


def test_no_fix_stays_no_fix():
    g = gf.GnssFix.from_fix(_receiver_fix(fix_type=gf.NO_FIX))
    assert g.status == gf.STATUS_NO_FIX and math.isnan(g.lat_deg) and g.cov_type == gf.COV_UNKNOWN


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
