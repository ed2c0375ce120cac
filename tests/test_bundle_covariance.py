"""Marginal covariance of self-calibrated intrinsics: known answers on a simulated block."""

from __future__ import annotations

import numpy as np

from photogram_ros.core.bundle import BundleOptions, BundleProblem, bundle_adjust
from photogram_ros.core.camera import PinholeCamera
from test_bundle_solver import block, gnss, perturb

TRUTH = PinholeCamera(1000, 800, 900.0, 900.0, 500.0, 400.0, (-0.08, 0.0, 0.0, 0.0, 0.0))
FREE = ('f', 'cx', 'cy', 'k1', 'k2')


def _self_calibrate(noise_px):
    # Same seed: same geometry, GNSS and start; the image noise is the same draw scaled.
    s = block(seed=6, n_lines=5, per_line=9, n_pts=700, tilt_deg=15.0, camera=TRUTH, noise_px=noise_px)
    wrong = PinholeCamera(1000, 800, 900.0 * 1.02, 900.0 * 1.02, 500.0, 400.0)
    T0, X0 = perturb(s, 0.3, 0.5, 0.3)
    return bundle_adjust(BundleProblem(wrong, T0, X0, s['obs_cam'], s['obs_pt'], s['uv'], **gnss(s, 0.02)),
                         BundleOptions(loss='huber', loss_scale_px=3.0, refine_intrinsics=FREE,
                                       max_iterations=100, compute_covariance=True))


def test_intrinsics_sigma_covers_the_error_and_scales_with_image_noise():
    r1, r2 = _self_calibrate(0.5), _self_calibrate(1.0)
    for res, noise in ((r1, 0.5), (r2, 1.0)):
        assert res.status == 'converged', res.reason
        assert res.intrinsics_cov.shape == (1, len(FREE), len(FREE))
        assert np.allclose(res.intrinsics_cov[0], res.intrinsics_cov[0].T)
        assert np.all(np.linalg.eigvalsh(res.intrinsics_cov[0]) > 0)
        # s0 follows the pixel noise the residuals actually have (GNSS residuals at unit weight).
        assert 0.6 * noise < np.sqrt(res.variance_factor) < 1.4 * noise, res.variance_factor
        sig = res.intrinsics_sigma()
        assert set(sig) == set(FREE)
        f_err = res.camera.fx - TRUTH.fx
        assert abs(f_err) < 3.0 * sig['f'], (f_err, sig['f'])
        assert abs(res.camera.dist[0] - TRUTH.dist[0]) < 3.0 * sig['k1'] + 1e-4
        assert 0.005 < sig['f'] < 2.0          # a fraction of a pixel for 45 photos, not 0 or huge
    ratio = r2.intrinsics_sigma()['f'] / r1.intrinsics_sigma()['f']
    assert 1.7 < ratio < 2.3, ratio


def test_no_intrinsics_covariance_without_self_calibration():
    s = block(seed=2, n_lines=2, per_line=5, n_pts=200)
    T0, X0 = perturb(s, 0.2, 0.3, 0.2)
    res = bundle_adjust(BundleProblem(TRUTH, T0, X0, s['obs_cam'], s['obs_pt'], s['uv'], **gnss(s)),
                        BundleOptions(compute_covariance=True))
    assert res.intrinsics_cov is None and res.intrinsics_sigma() == {}
    assert res.cam_centre_cov is not None and res.variance_factor > 0
