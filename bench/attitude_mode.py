"""The tilt of a few-strip RTK block about its strips: how far the least-squares optimum turns the block, what
turns it, and where that puts the ground, the check points and the GNSS bias estimate.

The simulator's sample flight (3 strips 30 m apart, 40 m high, lens k1 -0.12, RTK fixed fixes whose error
wanders, a first-order Gauss-Markov process with a 60 s time constant) through the adjustment stage as in
flight, then:
- without control: the cameras' mean rotation against the truth (mrad, about E, N, U), the camera centres'
  mean offset, the final adjustment's cost at its estimate, at the truth (the same problem: every
  observation and fix, the true cameras and points) and after adjusting from the truth; once with the
  simulated 0.3 px image noise and once with none (`pixel_sigma` 0), which tells what turns the block;
- with 5 GCPs and 4 check points: the check points' RMSE at the last poll in flight and after the final
  adjustment, the GNSS bias estimated against the fixes' true mean error and the sigma the covariance gives
  it at the final state (fixes taken as independent), the cameras' mean offset and rotation.
Prints one JSON line.

    .venv/bin/python bench/attitude_mode.py [--preset sample]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'tests'))

from helpers.control import targets_file  # noqa: E402
from helpers.stage_flight import fly_stage  # noqa: E402

from photogram_ros.core.bundle import bundle_adjust  # noqa: E402
from photogram_ros.core.bundle.problem import BundleOptions  # noqa: E402
from photogram_ros.sim.observations import simulate_keyframes  # noqa: E402
from photogram_ros.sim.scenario import build_world, preset  # noqa: E402


def fly(sk, targets, control: str = '', **overrides):
    """The stage fed keyframe by keyframe (RTK fixes, target rows), then finished: (stage, last in-flight
    quality); overrides: AdjustmentParams by name."""
    stage, live = fly_stage(sk, targets, control, **overrides)
    return stage, (live[-1][1] if live else None)


def truth_in_at(sk, at):
    """sk's true camera poses (K, 4, 4) and a function map ENU (sim origin) -> the adjuster's map ENU."""
    def to_at(x):
        lat, lon, h = sk.origin.enu_to_geodetic(np.asarray(x, float))
        return np.ravel(at.origin.geodetic_to_enu(lat, lon, h))
    Ts = []
    for T in sk.true_map_T_cam:
        T = np.array(T, float)
        T[:3, 3] = to_at(T[:3, 3])
        Ts.append(T)
    return np.array(Ts), to_at


def block_against_truth(sk, at) -> dict:
    kids = list(at.registered)
    Tt, to_at = truth_in_at(sk, at)
    Te = np.array([at.kfs[k].map_T_cam for k in kids])
    rot = np.array([Rotation.from_matrix(a[:3, :3] @ b[:3, :3].T).as_rotvec() for a, b in zip(Te, Tt[kids])])
    return {'rotation_mrad_enu': (rot.mean(axis=0) * 1e3).round(3).tolist(),
            'rotation_spread_mrad': (rot.std(axis=0) * 1e3).round(3).tolist(),
            'centre_offset_m_enu': (Te[:, :3, 3] - Tt[kids, :3, 3]).mean(axis=0).round(4).tolist()}


def cost_at_truth(sk, at) -> dict:
    """The final adjustment's problem (every registered keyframe free, every point) evaluated at the
    estimate, at the truth, and adjusted from the truth."""
    kids = list(at.registered)
    ids, _ = at.points.arrays()
    tracks = np.asarray(ids, np.int64)
    prob = at.problem(kids, [], tracks)
    Tt, to_at = truth_in_at(sk, at)
    truth_pts = np.array([to_at(sk.points_map[t]) for t in tracks if t < len(sk.points_map)])
    if len(truth_pts) != len(prob.points_map):
        return {'error': 'targets among the points: run without control'}
    opt = BundleOptions(loss=at.opt.loss, loss_scale_px=at.opt.loss_scale_px, max_iterations=0)
    at_truth = dataclasses.replace(prob, map_T_cams=Tt[kids], points_map=truth_pts)
    back = bundle_adjust(at_truth, dataclasses.replace(opt, max_iterations=100))
    rot = np.array([Rotation.from_matrix(a[:3, :3] @ b[:3, :3].T).as_rotvec()
                    for a, b in zip(back.map_T_cams, Tt[kids])])
    return {'cost_estimate': round(bundle_adjust(prob, opt).initial_cost, 1),
            'cost_truth': round(bundle_adjust(at_truth, opt).initial_cost, 1),
            'cost_from_truth': round(back.final_cost, 1), 'from_truth_status': back.status,
            'from_truth_rotation_mrad_enu': (rot.mean(axis=0) * 1e3).round(3).tolist()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--preset', default='sample')
    a = ap.parse_args()
    cfg = preset(a.preset, n_gcp=5, n_check=4)
    world = build_world(cfg, np.random.default_rng(cfg.seed))
    sk = simulate_keyframes(cfg, world=world, attitude_sigma_deg=None)
    targets = world[2]
    fix_err = np.mean([np.ravel(sk.origin.geodetic_to_enu(r.fix.lat_deg, r.fix.lon_deg, r.fix.h_m))
                       - (T[:3, :3] @ sk.lever_arm_cam_m + T[:3, 3]) for r, T in zip(sk.records, sk.true_map_T_cam)],
                      axis=0)
    out = {'preset': a.preset, 'altitude_m': cfg.altitude_m, 'lines': cfg.n_lines,
           'fixes_true_mean_error_m_enu': fix_err.round(4).tolist()}
    plain, _ = fly(sk, targets)
    out['rtk_only'] = {**block_against_truth(sk, plain.at), **cost_at_truth(sk, plain.at)}
    quiet = simulate_keyframes(cfg, world=world, attitude_sigma_deg=None, pixel_sigma=0.0)
    plain, _ = fly(quiet, targets)
    out['rtk_only_no_image_noise'] = {**block_against_truth(quiet, plain.at), **cost_at_truth(quiet, plain.at)}
    with tempfile.TemporaryDirectory() as tmp:
        control = str(targets_file(Path(tmp) / 'targets.txt', sk.origin, targets))
        gcp, last = fly(sk, targets, control)
    q = gcp.quality()
    at = gcp.at
    ids, _ = at.points.arrays()
    cov = bundle_adjust(at.problem(list(at.registered), [], np.asarray(ids, np.int64)),
                        BundleOptions(loss=at.opt.loss, loss_scale_px=at.opt.loss_scale_px, max_iterations=0,
                                      compute_covariance=True, estimate_gnss_bias=True))
    sigma = np.sqrt(np.diag(cov.gnss_bias_cov) * (cov.variance_factor or 1.0))
    out['with_5_gcps'] = {
        'check_in_flight_m': [round(last['check_rmse'][k], 4) for k in ('horizontal_m', 'vertical_m')],
        'check_final_m': [round(q['check_rmse'][k], 4) for k in ('horizontal_m', 'vertical_m')],
        'gcps_used': gcp.diag.values.get('gcps_used'),
        'gnss_bias_enu_m': np.asarray(gcp.at.gnss_bias_enu).round(4).tolist(),
        'gnss_bias_sigma_m': sigma.round(4).tolist(),
        **block_against_truth(sk, gcp.at)}
    print(json.dumps(out))
    return 0


if __name__ == '__main__':
    sys.exit(main())
