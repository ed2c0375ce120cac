"""Bundle adjustment on synthetic aerial blocks with known truth; triangulation and DLT resection."""

from __future__ import annotations

import numpy as np
import pytest

from photogram_ros.core.bundle import BALModel, BrownModel, BundleOptions, BundleProblem, bundle_adjust
from photogram_ros.core.bundle.solver import Solver
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.resection import resect_dlt
from photogram_ros.core.rotations import R_from_rotvec, make_T, rot_x, rot_y, rot_z
from photogram_ros.core.triangulation import triangulate_points
from photogram_ros.errors import ConfigError, DataError

CAM = PinholeCamera(1000, 800, 900.0, 900.0, 500.0, 400.0, (-0.05, 0.01, 0.0005, -0.0003, 0.0))
NADIR = np.diag([1.0, -1.0, -1.0])   # optical camera looking down, x east, y south


def block(seed=0, n_lines=4, per_line=8, alt=60.0, n_pts=400, tilt_deg=8.0, camera=CAM, noise_px=0.5):
    """A survey block: cameras on lines with varied tilts and heights over hilly ground."""
    rng = np.random.default_rng(seed)
    T = []
    for i in range(n_lines):
        for j in range(per_line):
            c = np.array([j * 14.0, i * 22.0, alt + rng.uniform(-8, 8)])
            R = rot_z(rng.uniform(-0.1, 0.1) + (np.pi if i % 2 else 0.0)) @ rot_x(np.radians(
                rng.uniform(-tilt_deg, tilt_deg))) @ rot_y(np.radians(rng.uniform(-tilt_deg, tilt_deg))) @ NADIR
            T.append(make_T(R, c))
    T = np.array(T)
    lo, hi = np.array([-20, -20]), np.array([(per_line - 1) * 14 + 20, (n_lines - 1) * 22 + 20])
    xy = rng.uniform(lo, hi, size=(n_pts, 2))
    z = 6 * np.sin(xy[:, 0] / 15) + 4 * np.cos(xy[:, 1] / 11) + rng.uniform(-3, 12, n_pts)
    X = np.c_[xy, z]
    oc, op, uv = [], [], []
    for c in range(len(T)):
        R, t = T[c, :3, :3].T, -T[c, :3, :3].T @ T[c, :3, 3]
        Pc = X @ R.T + t
        pix, front = camera.project(Pc)
        ok = front & camera.in_image(pix, 5)
        oc += [np.full(ok.sum(), c)]
        op += [np.nonzero(ok)[0]]
        uv += [pix[ok]]
    oc, op, uv = np.concatenate(oc), np.concatenate(op), np.concatenate(uv)
    keep = np.bincount(op, minlength=n_pts) >= 2
    sel = keep[op]
    remap = np.cumsum(keep) - 1
    X = X[keep]
    uv_obs = uv[sel] + rng.normal(0, noise_px, (sel.sum(), 2))
    return dict(T=T, X=X, obs_cam=oc[sel], obs_pt=remap[op[sel]], uv_true=uv[sel], uv=uv_obs, rng=rng)


def perturb(s, pos_m=0.5, ang_deg=1.0, pt_m=0.5):
    rng = s['rng']
    T0 = s['T'].copy()
    for c in range(len(T0)):
        T0[c, :3, :3] = R_from_rotvec(rng.normal(0, np.radians(ang_deg), 3)) @ T0[c, :3, :3]
        T0[c, :3, 3] += rng.normal(0, pos_m, 3)
    return T0, s['X'] + rng.normal(0, pt_m, s['X'].shape)


def centre_rmse(T, T_true):
    return float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))


def gnss(s, sigma=0.02, lever=np.array([0.05, -0.1, -0.15])):
    rng = s['rng']
    ant = np.einsum('cij,j->ci', s['T'][:, :3, :3], lever) + s['T'][:, :3, 3]
    C = len(ant)
    cov = np.tile(np.diag([sigma ** 2, sigma ** 2, (1.5 * sigma) ** 2]), (C, 1, 1))
    meas = ant + rng.normal(0, 1, (C, 3)) * np.array([sigma, sigma, 1.5 * sigma])
    return dict(gnss_cam=np.arange(C), gnss_pos_map=meas, gnss_cov_map=cov, lever_arm_cam_m=lever)


def test_models_jacobians_match_finite_differences():
    rng = np.random.default_rng(3)
    for model, prm, zsign in [(BrownModel(), BrownModel.params_of(CAM), 1.0),
                              (BALModel(), np.array([500.0, 0.1, -0.05]), -1.0)]:
        P = rng.normal(size=(20, 3))
        P[:, 2] = zsign * rng.uniform(2, 4, 20)
        prm_n = np.tile(prm, (20, 1))
        _, Jp, Jk = model.project(P, prm_n)
        for k in range(3):
            d = np.zeros(3)
            d[k] = 1e-6
            fd = (model.project(P + d, prm_n)[0] - model.project(P - d, prm_n)[0]) / 2e-6
            assert np.allclose(fd, Jp[:, :, k], rtol=1e-5, atol=1e-4)
        for k in range(len(prm)):
            d = np.zeros(len(prm))
            d[k] = 1e-6 * max(1.0, abs(prm[k]))
            fd = (model.project(P, prm_n + d)[0] - model.project(P, prm_n - d)[0]) / (2 * d[k])
            assert np.allclose(fd, Jk[:, :, k], rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize('gnss_bias', [False, True])
def test_full_gradient_with_priors_matches_finite_differences(gnss_bias):
    """J^T r of every residual type (reprojection, GNSS with lever arm, GCP, attitude) vs FD of the cost;
    with the GNSS bias as unknowns, at a bias away from zero, their gradient too."""
    s = block(seed=1, n_lines=2, per_line=4, n_pts=60)
    T0, X0 = perturb(s, 0.3, 0.5, 0.3)
    g = gnss(s, sigma=0.05)
    prob = BundleProblem(CAM, T0, X0, s['obs_cam'], s['obs_pt'], s['uv'], **g,
                         point_priors_idx=np.array([0, 3, 5]), point_priors_map=s['X'][[0, 3, 5]],
                         point_priors_sigma_m=np.array([0.02, 0.02, 0.04]),
                         attitude_cam=np.array([1, 2]), attitude_map_R_cam=s['T'][[1, 2], :3, :3],
                         attitude_sigma_rad=np.array([0.01, 0.01, 0.03]))
    opts = BundleOptions(loss='cauchy', loss_scale_px=2.0, refine_intrinsics=('f', 'cx', 'k1', 'p2'),
                         estimate_gnss_bias=gnss_bias)
    sol = Solver(prob.resolved(), opts)
    d = sol.d
    b = np.array([0.3, -0.2, 0.5]) if gnss_bias else np.zeros(3)
    lin = sol.linearise(d['R'], d['t'], d['X'], d['intr'], b)
    # With a robust loss, J^T r of the IRLS-weighted system is exactly the cost gradient.
    grad = np.concatenate([lin['gc'], lin['gp'].ravel()])
    n = sol.st.nc
    rng = np.random.default_rng(0)
    bias = list(sol.st.bias_col + np.arange(3)) if gnss_bias else []
    assert (sol.st.bias_col >= 0) == gnss_bias
    for k in list(rng.choice(n, 25, replace=False)) + bias + list(n + rng.choice(len(grad) - n, 15, replace=False)):
        if k < n and not sol.st.real[k]:
            continue
        e = np.zeros(len(grad))
        e[k] = 1e-6
        cost = []
        for sgn in (1, -1):
            st = sol.apply(d['R'], d['t'], d['X'], d['intr'], b, sgn * e[:n], sgn * e[n:].reshape(-1, 3))
            cost.append(sum(sol.cost_parts(*st).values()))
        fd = (cost[0] - cost[1]) / 2e-6
        assert fd == pytest.approx(grad[k], rel=2e-4, abs=1e-3 * max(1.0, np.abs(grad).max() * 1e-4))
    if gnss_bias:
        assert np.abs(grad[bias]).max() > 1.0     # the bias away from its optimum: a gradient that could be wrong


def test_rtk_gnss_recovers_camera_centres_within_few_cm():
    s = block(seed=2)
    T0, X0 = perturb(s)
    g = gnss(s, 0.02)
    prob = BundleProblem(CAM, T0, X0, s['obs_cam'], s['obs_pt'], s['uv'], **g)
    res = bundle_adjust(prob, BundleOptions(loss='huber', compute_covariance=True, point_covariance=True))
    assert res.status == 'converged', res.reason
    assert res.final_cost < 0.01 * res.initial_cost
    err = centre_rmse(res.map_T_cams, s['T'])
    # 2 cm horizontal / 3 cm vertical fixes, GSD 6.7 cm: the adjustment beats the raw fixes.
    ant = np.einsum('cij,j->ci', s['T'][:, :3, :3], g['lever_arm_cam_m']) + s['T'][:, :3, 3]
    raw = float(np.sqrt(np.mean(np.sum((g['gnss_pos_map'] - ant) ** 2, axis=1))))
    assert err < 0.04 and err < raw, (err, raw)
    assert res.rms['reprojection_px'] < 0.8
    assert 0.01 < res.rms['gnss_m'] < 0.05
    # Marginal covariance: positive definite, a few mm to 2 cm per axis, consistent with the error.
    sd = np.sqrt(np.diagonal(res.cam_centre_cov, axis1=1, axis2=2))
    assert np.all(sd > 1e-3) and np.all(sd < 0.03)
    assert np.all(np.linalg.eigvalsh(res.point_cov) > 0)
    pt_err = np.linalg.norm(res.points_map - s['X'], axis=1)
    pt_sd = np.sqrt(np.trace(res.point_cov, axis1=1, axis2=2))
    assert 0.3 < np.sqrt(np.mean(pt_err ** 2)) / np.sqrt(np.mean(pt_sd ** 2)) < 3.0


def test_point_covariance_only_when_asked_and_the_rest_unchanged():
    s = block(seed=2)
    T0, X0 = perturb(s)
    prob = BundleProblem(CAM, T0, X0, s['obs_cam'], s['obs_pt'], s['uv'], **gnss(s, 0.02))
    opt = dict(loss='huber', compute_covariance=True, refine_intrinsics=('f', 'k1'))
    both = bundle_adjust(prob, BundleOptions(**opt, point_covariance=True))
    cams = bundle_adjust(prob, BundleOptions(**opt))
    assert both.point_cov is not None and both.point_cov.shape == (len(X0), 3, 3)
    assert cams.point_cov is None
    np.testing.assert_array_equal(cams.cam_centre_cov, both.cam_centre_cov)
    np.testing.assert_array_equal(cams.intrinsics_cov, both.intrinsics_cov)
    np.testing.assert_array_equal(cams.intrinsics_height_corr, both.intrinsics_height_corr)


def test_gcp_priors_fix_the_gauge_without_gnss():
    s = block(seed=4)
    # Start from a shifted, rotated and scaled copy: only the GCPs can pull it back.
    S = 1.03 * rot_z(0.05)
    shift = np.array([3.0, -2.0, 1.5])
    T0, X0 = perturb(s, 0.1, 0.3, 0.1)
    T0[:, :3, 3] = T0[:, :3, 3] @ S.T + shift
    T0[:, :3, :3] = rot_z(0.05) @ T0[:, :3, :3]
    X0 = X0 @ S.T + shift
    rng = s['rng']
    gcp = rng.choice(len(s['X']), 6, replace=False)
    res = bundle_adjust(BundleProblem(CAM, T0, X0, s['obs_cam'], s['obs_pt'], s['uv'],
                                      point_priors_idx=gcp, point_priors_map=s['X'][gcp] + rng.normal(0, 0.01, (6, 3)),
                                      point_priors_sigma_m=np.full((6, 3), 0.01)),
                        BundleOptions(loss='huber', max_iterations=100))
    assert res.status == 'converged', res.reason
    assert centre_rmse(res.map_T_cams, s['T']) < 0.10
    others = np.setdiff1d(np.arange(len(s['X'])), gcp)
    assert np.sqrt(np.mean(np.sum((res.points_map[others] - s['X'][others]) ** 2, 1))) < 0.10
    assert res.rms['gcp_m'] < 0.03


@pytest.mark.parametrize('loss', ['huber', 'cauchy'])
def test_robust_loss_keeps_accuracy_with_5_percent_outliers(loss):
    s = block(seed=5)
    rng = s['rng']
    uv = s['uv'].copy()
    bad = rng.choice(len(uv), int(0.05 * len(uv)), replace=False)
    uv[bad] += rng.uniform(15, 60, (len(bad), 2)) * rng.choice([-1, 1], (len(bad), 2))
    T0, X0 = perturb(s)
    g = gnss(s, 0.02)
    robust = bundle_adjust(BundleProblem(CAM, T0, X0, s['obs_cam'], s['obs_pt'], uv, **g),
                           BundleOptions(loss=loss, loss_scale_px=1.0))
    plain = bundle_adjust(BundleProblem(CAM, T0, X0, s['obs_cam'], s['obs_pt'], uv, **g),
                          BundleOptions(loss='linear'))
    e_rob, e_plain = centre_rmse(robust.map_T_cams, s['T']), centre_rmse(plain.map_T_cams, s['T'])
    assert e_rob < 0.035, e_rob
    assert e_rob < e_plain
    # A two-view point with one gross outlier cannot be saved by any loss: judge the typical point.
    pt = np.median(np.linalg.norm(robust.points_map - s['X'], axis=1))
    assert pt < 0.05, pt


def test_self_calibration_recovers_focal_within_0_3_percent():
    truth = PinholeCamera(1000, 800, 900.0, 900.0, 500.0, 400.0, (-0.08, 0.0, 0.0, 0.0, 0.0))
    s = block(seed=6, n_lines=5, per_line=9, n_pts=700, tilt_deg=15.0, camera=truth)
    wrong = PinholeCamera(1000, 800, 900.0 * 1.03, 900.0 * 1.03, 500.0, 400.0)
    T0, X0 = perturb(s, 0.3, 0.5, 0.3)
    res = bundle_adjust(BundleProblem(wrong, T0, X0, s['obs_cam'], s['obs_pt'], s['uv'], **gnss(s, 0.02)),
                        BundleOptions(loss='huber', refine_intrinsics=('f', 'cx', 'cy', 'k1', 'k2'),
                                      max_iterations=100))
    assert res.status == 'converged', res.reason
    f_err = abs(res.camera.fx / truth.fx - 1.0)
    assert f_err < 0.003, f_err
    assert res.camera.dist[0] == pytest.approx(-0.08, abs=0.01)
    assert centre_rmse(res.map_T_cams, s['T']) < 0.05
    assert res.rms['reprojection_px'] < 0.8


def test_fixed_blocks_do_not_move_and_bad_input_raises():
    s = block(seed=7, n_lines=2, per_line=5, n_pts=150)
    T0, X0 = perturb(s, 0.2, 0.3, 0.2)
    fixed_c = np.zeros(len(T0), bool)
    fixed_c[:3] = True
    T0[:3] = s['T'][:3]
    fixed_p = np.zeros(len(X0), bool)
    fixed_p[:10] = True
    res = bundle_adjust(BundleProblem(CAM, T0, X0, s['obs_cam'], s['obs_pt'], s['uv'],
                                      fixed_cams=fixed_c, fixed_points=fixed_p), BundleOptions())
    assert np.allclose(res.map_T_cams[:3], T0[:3], atol=1e-12)
    assert np.array_equal(res.points_map[:10], X0[:10])
    assert not np.allclose(res.map_T_cams[3:], T0[3:])
    assert res.final_cost < res.initial_cost
    with pytest.raises(DataError):
        BundleProblem(CAM, T0, X0, s['obs_cam'][:-1], s['obs_pt'], s['uv']).resolved()
    with pytest.raises(ConfigError):
        bundle_adjust(BundleProblem(CAM, T0, X0, s['obs_cam'], s['obs_pt'], s['uv']), BundleOptions(loss='l1'))
    with pytest.raises(ConfigError):
        bundle_adjust(BundleProblem(CAM, T0, X0, s['obs_cam'], s['obs_pt'], s['uv']),
                      BundleOptions(refine_intrinsics=('focal',)))


def test_max_iterations_status():
    s = block(seed=8, n_lines=2, per_line=4, n_pts=100)
    T0, X0 = perturb(s)
    res = bundle_adjust(BundleProblem(CAM, T0, X0, s['obs_cam'], s['obs_pt'], s['uv']),
                        BundleOptions(max_iterations=1))
    assert res.status == 'max_iterations' and res.iterations == 1


def test_triangulation_recovers_points_with_angles_and_errors():
    s = block(seed=9, n_lines=2, per_line=5, n_pts=200, noise_px=0.3)
    tri = triangulate_points(CAM, s['T'], s['obs_cam'], s['obs_pt'], s['uv'])
    assert tri.valid.all()
    err = np.linalg.norm(tri.points_map - s['X'], axis=1)
    assert np.median(err) < 0.05 and err.max() < 0.5
    assert np.all(tri.reproj_rms_px < 1.5) and np.median(tri.reproj_rms_px) < 0.5
    # Angle against a direct computation for one point.
    p = 0
    cams = s['obs_cam'][s['obs_pt'] == p]
    rays = s['X'][p] - s['T'][cams, :3, 3]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(rays @ rays.T, -1, 1))).max()
    assert tri.angle_deg[p] == pytest.approx(ang, abs=0.2)
    # A point seen once is not valid.
    one = triangulate_points(CAM, s['T'], s['obs_cam'][:1], s['obs_pt'][:1] * 0, s['uv'][:1])
    assert not one.valid[0]


def test_dlt_resection_recovers_k_r_t():
    rng = np.random.default_rng(11)
    K = np.array([[1200.0, 0.5, 640.0], [0.0, 1180.0, 470.0], [0.0, 0.0, 1.0]])
    R = rot_z(0.3) @ rot_x(2.8) @ rot_y(0.1)
    C = np.array([10.0, -5.0, 80.0])
    t = -R @ C
    X = np.c_[rng.uniform(-40, 40, (30, 2)), rng.uniform(-10, 15, 30)]
    p = (X @ R.T + t) @ K.T
    uv = p[:, :2] / p[:, 2:3]
    res = resect_dlt(X, uv)
    assert np.allclose(res.K, K, rtol=1e-6, atol=1e-6)
    assert np.allclose(res.cam_R_map, R, atol=1e-8)
    assert np.allclose(res.map_T_cam[:3, 3], C, atol=1e-6)
    noisy = resect_dlt(X, uv + rng.normal(0, 0.5, uv.shape))
    assert abs(noisy.K[0, 0] / K[0, 0] - 1) < 0.02
    assert np.linalg.norm(noisy.map_T_cam[:3, 3] - C) < 1.0
    assert noisy.rms_px < 1.0
    with pytest.raises(DataError):
        resect_dlt(X[:5], uv[:5])


def test_check_points_are_triangulated_from_adjusted_cameras_only():
    from photogram_ros.core.bundle import check_points
    s = block(seed=12)
    chk = np.array([1, 7, 20, 33, 50])
    is_chk = np.isin(s['obs_pt'], chk)
    # The adjustment never sees the check points' observations.
    keep_pts = np.setdiff1d(np.arange(len(s['X'])), chk)
    remap = np.full(len(s['X']), -1)
    remap[keep_pts] = np.arange(len(keep_pts))
    T0, X0 = perturb(s)
    res = bundle_adjust(BundleProblem(CAM, T0, X0[keep_pts], s['obs_cam'][~is_chk], remap[s['obs_pt'][~is_chk]],
                                      s['uv'][~is_chk], **gnss(s, 0.02)), BundleOptions())
    lookup = {p: k for k, p in enumerate(chk)}
    cp = check_points(res.camera, res.map_T_cams, s['obs_cam'][is_chk],
                      np.array([lookup[p] for p in s['obs_pt'][is_chk]]), s['uv'][is_chk], s['X'][chk])
    assert cp['valid'].all()
    assert cp['rmse_xy_m'] < 0.06 and cp['rmse_z_m'] < 0.10, cp
    # From the unadjusted start they are far worse: the residuals measure the adjustment.
    raw = check_points(CAM, T0, s['obs_cam'][is_chk], np.array([lookup[p] for p in s['obs_pt'][is_chk]]),
                       s['uv'][is_chk], s['X'][chk])
    assert raw['rmse_xy_m'] > 3 * cp['rmse_xy_m']
