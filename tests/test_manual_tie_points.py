"""Manual tie points (MTPs): points without coordinates marked by hand in several photos.

Files (io/control_file.py), the adjustment's per-observation loss scale (core/bundle), and a simulated
photo survey whose automatic tie points are cut between its two halves (tests/helpers/mtp_survey.py):
without MTPs the report says a part joined through its GNSS alone; with four MTPs across the band it
joins through them, the check points are within 1.5 GSD and each MTP's residual per photo is listed.
"""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from photogram_ros.core.bundle import BundleOptions, BundleProblem, bundle_adjust
from photogram_ros.core.bundle.solver import Solver
from photogram_ros.errors import DataError
from photogram_ros.io.control_file import read_gcp_list, read_tie_list
from tests.test_bundle_solver import CAM, block, perturb

GSD_LIMIT = 1.5


# --- files ------------------------------------------------------------------------------------

def test_gcp_list_mtp_rows_are_tie_points_not_gcps(tmp_path):
    p = tmp_path / 'gcp_list.txt'
    p.write_text('EPSG:32632\n'
                 '465698.5 5249464.8 499.4 97.40 163.65 IMG_0000.JPG GCP01\n'
                 '465698.5 5249464.8 499.4 98.77 350.68 IMG_0002.JPG GCP01\n'
                 '0 0 0 300.50 200.25 IMG_0000.JPG MTP01\n'       # an MTP row: its x y z are not read
                 '0 0 0 310.00 40.00 IMG_0002.JPG mtp01\n'
                 '120.5 80.25 IMG_0002.JPG A7\n')                  # a row without coordinates
    g = read_gcp_list(p)
    assert set(g.points) == {'GCP01'} and g.roles == {'GCP01': 'gcp'} and len(g.rows) == 2
    assert [(r.line, r.image, r.name) for r in g.tie_rows] == [(4, 'IMG_0000.JPG', 'MTP01'),
                                                              (5, 'IMG_0002.JPG', 'mtp01'),
                                                              (6, 'IMG_0002.JPG', 'A7')]
    assert g.tie_uv['IMG_0000.JPG']['MTP01'] == pytest.approx([300.5, 200.25])
    assert g.tie_uv['IMG_0002.JPG']['A7'] == pytest.approx([120.5, 80.25])


def test_tie_list_reads_rows_without_coordinates_and_names_a_bad_line(tmp_path):
    p = tmp_path / 'mtp.txt'
    p.write_text('EPSG:32632\n# px py image name\n10.5 20 IMG_1.JPG M1\n11 21 IMG_2.JPG M1   # second photo\n'
                 '1 2 3 30 40 IMG_3.JPG MTP9\n')
    rows = read_tie_list(p)
    assert [(r.line, r.image, r.name, *r.uv) for r in rows] == [(3, 'IMG_1.JPG', 'M1', 10.5, 20.0),
                                                                (4, 'IMG_2.JPG', 'M1', 11.0, 21.0),
                                                                (5, 'IMG_3.JPG', 'MTP9', 30.0, 40.0)]
    p.write_text('10.5 20 IMG_1.JPG M1\n10.5 IMG_2.JPG M1\n')
    with pytest.raises(DataError, match='line 2'):
        read_tie_list(p)
    p.write_text('10.5 x IMG_1.JPG M1\n')
    with pytest.raises(DataError, match="line 1: py 'x' is not a number"):
        read_tie_list(p)


# --- the adjustment: a robust-loss scale per observation --------------------------------------------

def _problem(scale=None):
    s = block(seed=2, n_lines=2, per_line=4, n_pts=60)
    T0, X0 = perturb(s, 0.3, 0.5, 0.3)
    return s, BundleProblem(CAM, T0, X0, s['obs_cam'], s['obs_pt'], s['uv'], fixed_cams=np.arange(8) < 2,
                            obs_loss_scale_px=scale)


def test_per_observation_loss_scale_is_the_cost_gradient_and_equals_a_common_scale():
    s, prob = _problem()
    n = len(s['obs_cam'])
    opts = BundleOptions(loss='huber', loss_scale_px=1.0)
    base = Solver(prob.resolved(), opts)
    d = base.d
    # The same scale for each observation: the same cost as the common scale.
    same = Solver(_problem(np.full(n, 1.0))[1].resolved(), opts)
    z = np.zeros(3)
    assert same.cost_parts(d['R'], d['t'], d['X'], d['intr'], z) == base.cost_parts(d['R'], d['t'], d['X'], d['intr'], z)
    # Scales of their own: J^T r of the weighted system is the gradient of the cost (finite differences).
    scale = np.where(np.arange(n) % 3 == 0, 20.0, 5.0)
    sol = Solver(_problem(scale)[1].resolved(), opts)
    d = sol.d
    r = sol._reproj(d['R'], d['t'], d['X'], d['intr'], False)[0]
    e = np.linalg.norm(r, axis=1)
    assert ((e > 5.0) & (e < 20.0)).sum() > 20     # residuals between the scales: the scales matter
    lin = sol.linearise(d['R'], d['t'], d['X'], d['intr'], z)
    grad = np.concatenate([lin['gc'], lin['gp'].ravel()])
    nc = sol.st.nc
    for k in list(range(0, nc, 5)) + list(nc + np.arange(0, len(grad) - nc, 17)):
        if k < nc and not sol.st.real[k]:
            continue
        step = np.zeros(len(grad))
        step[k] = 1e-6
        cost = [sum(sol.cost_parts(*sol.apply(d['R'], d['t'], d['X'], d['intr'], z, sg * step[:nc],
                                              sg * step[nc:].reshape(-1, 3))).values()) for sg in (1, -1)]
        assert (cost[0] - cost[1]) / 2e-6 == pytest.approx(grad[k], rel=2e-4, abs=1e-3)
    res = bundle_adjust(_problem(scale)[1], opts)
    assert res.status != 'failed'
    with pytest.raises(DataError, match='obs_loss_scale_px'):
        bundle_adjust(_problem(np.zeros(n))[1], opts)


# --- a photo survey cut in two halves ------------------------------------------------------------

LEVER = (0.0, -0.05, -0.2)     # the simulator's FRD lever arm in the nadir camera frame


def _survey(tmp_path_factory, gnss_mode):
    """A 4-line photo survey (no GCPs; 6 check points, two of them in the band), read and matched once
    with the camera's calibration (the simulator's camera.yaml: what the MTPs do is measured apart from
    the EXIF camera's model errors); the manual tie points file and the check points file."""
    from photogram_ros.io.photo_block import read_photo_block
    from photogram_ros.sim.scenario import preset, simulate
    from photogram_ros.sim.truth import GroundTruth
    from tests.helpers.mtp_survey import check_sides, control_rows, mtp_rows
    root = tmp_path_factory.mktemp(f'mtp_{gnss_mode}') / 'flight'
    simulate(preset('tiny', photos=True, fps=1.0, n_lines=4, line_length_m=60.0, n_gcp=9, n_check=6,
                    gnss_mode=gnss_mode), root)
    truth = GroundTruth.load(root)
    block = read_photo_block(root / 'photos', root / 'photos' / 'camera.yaml')
    names = [r.name for r in block.records]
    crs, rows = control_rows(root / 'photos', truth, names)
    checks = root / 'checks.txt'
    checks.write_text('\n'.join([crs] + [r for r in rows if r.split()[6].startswith('CHK')]) + '\n')
    mtp = root / 'mtp.txt'
    mtp.write_text('\n'.join(mtp_rows(truth, names)) + '\n')
    return dict(root=root, truth=truth, block=pickle.dumps(block), checks=checks, mtp=mtp,
                sides=check_sides(truth, names))


def _adjust(s, tmp_path, tag, with_mtp: bool):
    from photogram_ros.io.aerial_triangulation import TriangulateOptions, adjust_block
    from tests.helpers.mtp_survey import cut_block
    block = pickle.loads(s['block'])
    cut_block(block, s['truth'])
    opt = TriangulateOptions(lever_arm_cam_m=LEVER, gcp=str(s['checks']), mtp=str(s['mtp']) if with_mtp else None)
    res = adjust_block(block, tmp_path / tag, opt)
    rep = json.loads((tmp_path / tag / 'report.json').read_text())
    md = (tmp_path / tag / 'report.md').read_text()
    R = {c['name']: np.array(c['residual_m']) for c in rep['check']['points']}
    west = np.mean([R[n] for n in R if s['sides'][n] == 'west'], axis=0)
    east = np.mean([R[n] for n in R if s['sides'][n] == 'east'], axis=0)
    gsd = s['truth'].gsd_m
    worst = max(max(np.hypot(*r[:2]), abs(r[2])) for r in R.values()) / gsd
    offset = float(np.hypot(*(east - west)[:2]))
    ck = rep['check']['rmse']
    print(f"{tag}: {res.registered}/{res.inputs} oriented; check points H {ck['horizontal_m'] / gsd:.2f} "
          f"V {ck['vertical_m'] / gsd:.2f} GSD RMSE, worst {worst:.2f} GSD; east - west "
          f"{offset * 100:.1f} cm H; MTPs {[(p['name'], p['images'], p['rms_px']) for p in rep['mtp']['points']]}")
    return res, rep, md, worst, offset


@pytest.fixture(scope='module')
def rtk_survey(tmp_path_factory):
    return _survey(tmp_path_factory, 'rtk_fixed')


@pytest.fixture(scope='module')
def dgps_survey(tmp_path_factory):
    return _survey(tmp_path_factory, 'dgps')


@pytest.mark.slow
def test_four_mtps_join_the_cut_halves_and_check_points_are_within_1_5_gsd(rtk_survey, tmp_path):
    """RTK-fixed geotags, no GCPs. Cut: the eastern half joins through its GNSS alone, and the report
    says so. With the MTPs it joins through them; check points within 1.5 GSD (measured worst 0.41 GSD);
    every MTP listed with its residual in each photo (measured RMS 0.26-0.93 px)."""
    res, rep, md, _, _ = _adjust(rtk_survey, tmp_path, 'cut', False)
    assert res.registered == res.inputs
    assert any('joined it through its GNSS alone' in a for a in rep['assumptions'])
    assert rep['mtp']['points'] == []
    res, rep, md, worst, _ = _adjust(rtk_survey, tmp_path, 'mtp', True)
    assert res.registered == res.inputs
    joined = [a for a in rep['assumptions'] if 'joined it' in a]
    assert joined and all('manual tie points' in a for a in joined)
    assert rep['check']['rmse']['n'] == 6 and worst <= GSD_LIMIT
    pts = {p['name']: p for p in rep['mtp']['points']}
    assert sorted(pts) == ['MTP01', 'MTP02', 'MTP03', 'MTP04']
    for p in pts.values():
        assert p['images'] >= 3 and p['rms_px'] <= 1.5 * 0.93 and p['max_px'] <= 1.5 * 1.53
        assert all(r['residual_px'] is not None and r['used'] for r in p['photos'])
    assert '## Manual tie points' in md and 'MTP04' in md.split('## Manual tie points')[1]


@pytest.mark.slow
def test_without_mtps_the_halves_drift_apart_on_dgps(dgps_survey, tmp_path):
    """DGPS geotags (decimetres, a wandering bias), no GCPs: cut, the eastern half sits where its own
    GNSS puts it (check points east minus west: 145 cm horizontally); the MTPs hold the halves together
    (16 cm, the same block uncut: 28 cm)."""
    _, _, _, _, apart = _adjust(dgps_survey, tmp_path, 'cut', False)
    _, rep, _, _, together = _adjust(dgps_survey, tmp_path, 'mtp', True)
    assert together <= 1.5 * 0.16
    assert apart >= 4 * together
    assert any('through 3 manual tie points' in a or 'through 4 manual tie points' in a for a in rep['assumptions'])


def test_markers_missing_from_the_control_file_are_manual_tie_points_in_flight():
    from photogram_ros.core.control import TARGET_DTYPE, ControlSet, SurveyedTarget
    from photogram_ros.core.incremental import IncrementalAT
    c = ControlSet([SurveyedTarget('GCP01', 3, 47.0, 8.0, 500.0, 'gcp')])
    det = np.zeros(4, TARGET_DTYPE)
    det['marker_id'] = [3, 7, 9, 9]
    det['u'], det['v'] = [10.0, 20.0, 30.0, 40.0], [1.0, 2.0, 3.0, 4.0]
    ties = c.marker_ties(det)
    assert list(ties) == ['MTP_aruco7'] and ties['MTP_aruco7'] == pytest.approx([20.0, 2.0])
    at = IncrementalAT(CAM)
    at.add_ties(ties)
    tid = at.block.new_target_track('MTP_aruco7')
    assert at.is_tie(tid) and not at.is_check(tid)
    assert at.is_check(at.block.new_target_track('CHK01'))
