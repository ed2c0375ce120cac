"""The GNSS bias estimate with GCPs: RTK fixes a few centimetres off (the simulator's wandering bias) are
estimated to the centimetre, against the true mean error of the flight's fixes."""

from __future__ import annotations

import numpy as np

from test_incremental import _rmse_hv, _run, world  # noqa: F401  (a fixture)


def test_rtk_bias_of_a_few_centimetres_is_estimated_with_five_gcps(world):  # noqa: F811
    cfg, w = world
    sk, at, rep, _, chk = _run(cfg, w, 'rtk_fixed', use_gcps=True, seed=7)
    gnss_err = np.array([sk.origin.geodetic_to_enu(r.fix.lat_deg, r.fix.lon_deg, r.fix.h_m)
                         - (T[:3, 3] + r.antenna_offset_map_m) for r, T in zip(sk.records, sk.true_map_T_cam)])
    true_bias = gnss_err.mean(axis=0)
    off = np.linalg.norm(at.gnss_bias_enu - true_bias)
    h, v = _rmse_hv(chk)
    print(f'RTK + 5 GCPs: true mean GNSS error {np.round(true_bias * 100, 1)} cm, estimated bias '
          f'{np.round(at.gnss_bias_enu * 100, 1)} cm ({off * 100:.2f} cm apart); check RMSE h {h * 100:.2f} cm, '
          f'v {v * 100:.2f} cm')
    assert at.gnss_bias_estimated
    assert abs(true_bias[2]) > 0.03                        # this flight's fixes are 4 cm low: a bias to find
    assert off <= 1.5 * 0.0193                             # measured 1.93 cm (3.93 cm with the bias left at 0.2 cm)
    assert v <= 1.5 * 0.0117                               # measured 1.17 cm (3.75 cm with the bias left at 0.2 cm)
