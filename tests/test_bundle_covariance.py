"""Marginal covariance of self-calibrated intrinsics: known answers on a simulated block."""

from __future__ import annotations

import numpy as np
import pytest

from photogram_ros.core.bundle import BundleOptions, BundleProblem, bundle_adjust
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.rotations import R_from_rotvec
from test_bundle_solver import block, centre_rmse, gnss, perturb

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


def _monte_carlo_f_and_height(tilt_deg, sigma_m, runs=30):
    """f and the block's height (mean camera height - mean point height) over noise draws on one geometry,
    and the covariance's figures at the last draw."""
    cam = PinholeCamera(1000, 800, 900.0, 900.0, 500.0, 400.0)
    s = block(seed=6, n_lines=3, per_line=6, n_pts=250, tilt_deg=tilt_deg, camera=cam, noise_px=0.5)
    g0 = gnss(s, sigma_m)
    antenna = np.einsum('cij,j->ci', s['T'][:, :3, :3], g0['lever_arm_cam_m']) + s['T'][:, :3, 3]
    rng = np.random.default_rng(1)
    f, h, res = [], [], None
    for _ in range(runs):
        uv = s['uv_true'] + rng.normal(0, 0.5, s['uv_true'].shape)
        g = dict(g0, gnss_pos_map=antenna + rng.normal(0, 1, antenna.shape) * np.array([1, 1, 1.5]) * sigma_m)
        res = bundle_adjust(BundleProblem(cam, s['T'], s['X'], s['obs_cam'], s['obs_pt'], uv, **g),
                            BundleOptions(refine_intrinsics=('f',), max_iterations=50, compute_covariance=True))
        f.append(res.camera.fx)
        h.append(np.mean(res.map_T_cams[:, 2, 3]) - np.mean(res.points_map[:, 2]))
    return np.corrcoef(f, h)[0, 1], res.intrinsics_height_correlation()['f']


def test_focal_height_correlation_flags_the_flat_nadir_block():
    near = _monte_carlo_f_and_height(0.2, 3.0, runs=1)[1]
    tilted = _monte_carlo_f_and_height(8.0, 3.0, runs=1)[1]
    assert near > 0.9 and abs(tilted) < 0.4, (near, tilted)


@pytest.mark.slow
def test_focal_height_correlation_matches_monte_carlo():
    """The correlation of f with the block's height from the covariance (Schur complement, points
    marginalised) against the sample correlation over 30 noise draws: near 1 for a flat-flown nadir
    block with 3 m GNSS (f and the ground's depth trade off), near 0 with 8 degree tilts."""
    for tilt, sigma, lo, hi in ((0.2, 3.0, 0.9, 1.0), (8.0, 3.0, -0.4, 0.4)):
        mc, cov = _monte_carlo_f_and_height(tilt, sigma)
        print(f'tilt {tilt} deg, GNSS {sigma} m: correlation Monte Carlo {mc:+.3f}, covariance {cov:+.3f}')
        assert lo <= cov <= hi and abs(mc - cov) < 0.15


def _joint_information(s, cam, T, X, g, gcp_idx, gcp_sigma_m, with_bias):
    """J^T J of the problem by central differences in its own unknowns: per camera a small rotation and its
    centre, the points, f (fx = fy) and, with_bias, the GNSS bias added to every fix's residual. Unit weights
    for the pixels, the fixes whitened by their sigmas, the GCPs by theirs: the solver's weights with loss
    'linear'."""
    C, P = len(T), len(X)
    L = np.linalg.inv(np.linalg.cholesky(g['gnss_cov_map']))

    def residuals(x):
        k = 0
        Ts = T.copy()
        for c in range(C):
            Ts[c, :3, :3] = R_from_rotvec(x[k:k + 3]) @ T[c, :3, :3]
            Ts[c, :3, 3] = T[c, :3, 3] + x[k + 3:k + 6]
            k += 6
        Xs = X + x[k:k + 3 * P].reshape(P, 3)
        k += 3 * P
        f = cam.fx + x[k]
        c2 = PinholeCamera(cam.width, cam.height, f, f, cam.cx, cam.cy, cam.dist)
        b = x[k + 1:k + 4] if with_bias else np.zeros(3)
        R = Ts[s['obs_cam'], :3, :3]
        pc = np.einsum('nji,nj->ni', R, Xs[s['obs_pt']] - Ts[s['obs_cam'], :3, 3])
        r = [(c2.project(pc)[0] - s['uv']).ravel()]
        ant = np.einsum('cij,j->ci', Ts[:, :3, :3], g['lever_arm_cam_m']) + Ts[:, :3, 3]
        r.append(np.einsum('cij,cj->ci', L, ant - g['gnss_pos_map'] + b).ravel())
        r.append(((Xs[gcp_idx] - X[gcp_idx]) / gcp_sigma_m).ravel())
        return np.concatenate(r)

    n = 6 * C + 3 * P + 1 + (3 if with_bias else 0)
    J = np.empty((len(residuals(np.zeros(n))), n))
    for j in range(n):
        d = np.zeros(n)
        d[j] = 1e-6
        J[:, j] = (residuals(d) - residuals(-d)) / 2e-6
    return J.T @ J, 6 * C + 3 * P


def test_focal_variance_with_the_gnss_bias_free_matches_the_joint_adjustment():
    """The covariance as if the GNSS bias were one more unknown (a Woodbury update of the reduced system's
    inverse) against the inverse of the whole problem's information with the bias as explicit columns, by
    finite differences. On a block whose heights the GCPs hold only through their relief, the freed bias
    loosens the focal length several times over."""
    cam = PinholeCamera(1000, 800, 900.0, 900.0, 500.0, 400.0)
    s = block(seed=4, n_lines=2, per_line=4, n_pts=60, tilt_deg=1.0, camera=cam, noise_px=0.5)
    g = gnss(s, 0.03)
    gcp_idx = np.arange(5)
    gcp_sigma = 0.02
    prob = BundleProblem(cam, s['T'], s['X'], s['obs_cam'], s['obs_pt'], s['uv'], **g,
                         point_priors_idx=gcp_idx, point_priors_map=s['X'][gcp_idx],
                         point_priors_sigma_m=np.full((5, 3), gcp_sigma))
    held = bundle_adjust(prob, BundleOptions(loss='linear', refine_intrinsics=('f',), max_iterations=0,
                                             compute_covariance=True))
    free = bundle_adjust(prob, BundleOptions(loss='linear', refine_intrinsics=('f',), max_iterations=0,
                                             compute_covariance=True, gnss_bias_free=True))
    q_held = held.intrinsics_cov[0][0, 0] / held.variance_factor
    q_free = free.intrinsics_cov[0][0, 0] / free.variance_factor
    for with_bias, q in ((False, q_held), (True, q_free)):
        N, k_f = _joint_information(s, cam, s['T'], s['X'], g, gcp_idx, gcp_sigma, with_bias)
        Ninv = np.linalg.inv(N)
        assert q == pytest.approx(Ninv[k_f, k_f], rel=0.02), (with_bias, q, Ninv[k_f, k_f])
        if with_bias:   # the bias's own covariance, all of it
            qb = free.gnss_bias_cov / free.variance_factor
            assert np.allclose(qb, Ninv[k_f + 1:, k_f + 1:], rtol=0.02, atol=1e-3 * np.abs(qb).max()), qb
    assert held.gnss_bias_cov is None
    assert q_free > 4.0 * q_held, (q_free, q_held)
    # Without GCPs nothing holds the block once the fixes may move together: no covariance.
    alone = bundle_adjust(BundleProblem(cam, s['T'], s['X'], s['obs_cam'], s['obs_pt'], s['uv'], **g),
                          BundleOptions(loss='linear', refine_intrinsics=('f',), max_iterations=0,
                                        compute_covariance=True, gnss_bias_free=True))
    assert alone.intrinsics_cov is None


def test_the_gnss_bias_estimated_as_unknowns_is_recovered_with_the_covariance_of_the_bias_freed():
    """Fixes all off by one offset (a GNSS receiver's bias), 5 GCPs: the solver estimates the offset as 3 unknowns
    beside the poses and points. It recovers the offset to within its sigma (a few cm against metres), puts the
    cameras back on the truth, and its covariance is the one the Woodbury update (`gnss_bias_free`) gives with the
    bias held at the estimate: two independent computations of the same inverse."""
    cam = PinholeCamera(1000, 800, 900.0, 900.0, 500.0, 400.0)
    s = block(seed=1, n_lines=3, per_line=6, n_pts=150, tilt_deg=3.0, camera=cam, noise_px=0.5)
    g = gnss(s, 0.03)
    bias_enu_m = np.array([1.7, -2.4, 3.1])
    g['gnss_pos_map'] = g['gnss_pos_map'] + bias_enu_m
    gcp_idx = np.arange(0, 150, 30)
    gcps = dict(point_priors_idx=gcp_idx, point_priors_map=s['X'][gcp_idx], point_priors_sigma_m=np.full((5, 3), 0.02))
    T0, X0 = perturb(s, 0.3, 0.5, 0.3)
    T0[:, :3, 3] += bias_enu_m           # the block starts where its fixes put it
    X0 = X0 + bias_enu_m
    est = bundle_adjust(BundleProblem(cam, T0, X0, s['obs_cam'], s['obs_pt'], s['uv'], **g, **gcps),
                        BundleOptions(loss='linear', max_iterations=100, estimate_gnss_bias=True,
                                      compute_covariance=True))
    assert est.status == 'converged', est.reason
    sd = np.sqrt(np.diag(est.gnss_bias_cov))
    err = est.gnss_bias_enu_m - bias_enu_m
    assert np.all(np.abs(err) < 3.0 * sd), (err, sd)
    assert np.all(sd < 1.5 * 0.0273), sd                          # measured 2.3 / 2.7 / 2.4 cm
    assert np.abs(err).max() < 1.5 * 0.0253, err                 # measured 1.9 / -2.5 / -1.5 cm
    assert centre_rmse(est.map_T_cams, s['T']) < 1.5 * 0.0602   # the fixes' 3 cm noise and the GCPs' 2 cm
    # The same optimum from the truth (the bias from zero): the solve did not stop short.
    from_truth = bundle_adjust(BundleProblem(cam, s['T'], s['X'], s['obs_cam'], s['obs_pt'], s['uv'], **g, **gcps),
                               BundleOptions(loss='linear', max_iterations=100, estimate_gnss_bias=True))
    assert np.abs(from_truth.gnss_bias_enu_m - est.gnss_bias_enu_m).max() < 1e-4
    # Held at its estimate, the bias freed by the Woodbury update: the same covariance.
    g_held = dict(g, gnss_pos_map=g['gnss_pos_map'] - est.gnss_bias_enu_m)
    held = bundle_adjust(BundleProblem(cam, est.map_T_cams, est.points_map, s['obs_cam'], s['obs_pt'], s['uv'],
                                       **g_held, **gcps),
                         BundleOptions(loss='linear', max_iterations=0, compute_covariance=True, gnss_bias_free=True))
    assert held.gnss_bias_enu_m is None
    # (the bias's covariance comes scaled by the variance factor, whose redundancy counts the bias's 3 unknowns
    # only where they are unknowns: compared unscaled)
    q_est, q_held = est.gnss_bias_cov / est.variance_factor, held.gnss_bias_cov / held.variance_factor
    assert np.allclose(q_est, q_held, rtol=1e-6, atol=1e-9 * np.abs(q_est).max()), (q_est, q_held)
    assert np.allclose(est.cam_centre_cov, held.cam_centre_cov, rtol=1e-6, atol=1e-9 * np.abs(est.cam_centre_cov).max())
    # Without the bias as unknowns the GCPs and the offset fixes pull against each other: the block lands between.
    plain = bundle_adjust(BundleProblem(cam, T0, X0, s['obs_cam'], s['obs_pt'], s['uv'], **g, **gcps),
                          BundleOptions(loss='linear', max_iterations=100))
    assert centre_rmse(plain.map_T_cams, s['T']) > 0.5          # measured 4.14 m
