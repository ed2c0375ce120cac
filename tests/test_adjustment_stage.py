"""The adjustment stage (stages/adjustment.py) in flight, without rclpy: simulated keyframes (features, target
rows, fixes) in through its plain methods, one at a time as the tracker sends them; poses, quality and
diagnostics out. GCP vetting (a placeholder height), a segment after every track was lost, and health.
"""

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT
from helpers.control import targets_file

from photogram_ros.core.control import TARGET_DTYPE
from photogram_ros.core.gnss_fix import COV_DIAGONAL_KNOWN, COV_UNKNOWN, STATUS_FIX, STATUS_GBAS_FIX
from photogram_ros.params import from_dict
from photogram_ros.sim.observations import simulate_keyframes
from photogram_ros.sim.scenario import build_world, preset
from photogram_ros.stages.adjustment import (ERROR, WARN, AdjustmentParams, AdjustmentStage, DiagnosticsLog,
                                             RecordedOutputs)


@pytest.fixture(scope='module')
def flight_3d():
    cfg = preset('tiny', n_gcp=5, n_check=4)
    world = build_world(cfg, np.random.default_rng(cfg.seed))
    return simulate_keyframes(cfg, gnss_mode='3d', world=world, attitude_sigma_deg=None), world[2]


@pytest.fixture(scope='module')
def flight_rtk():
    return simulate_keyframes(preset('tiny'), keyframe_interval_s=1.0, attitude_sigma_deg=None)


def _stage(sk, camera=None, out=None, **overrides):
    p = from_dict(AdjustmentParams, {'lever_arm_cam_m': [float(v) for v in sk.lever_arm_cam_m], **overrides})
    stage = AdjustmentStage(p, DiagnosticsLog(), out or RecordedOutputs())
    assert stage.set_camera(camera or sk.camera)
    return stage


def _fly(stage, records, marker_of: dict | None = None, status: int = STATUS_GBAS_FIX, fixes: bool = True):
    """Each record's fix (unless `fixes` is False), then its features and target rows; the stage adjusts what is
    ready after each."""
    for r in records:
        f = r.fix
        if fixes:
            stage.add_fix(r.stamp_ns, f.lat_deg, f.lon_deg, f.h_m, np.diag(np.diag(f.cov_enu_m2)), status,
                          COV_DIAGONAL_KNOWN)
        rows = np.zeros(len(r.target_uv), TARGET_DTYPE)
        for i, (name, uv) in enumerate(r.target_uv.items()):
            rows[i]['marker_id'], rows[i]['u'], rows[i]['v'] = (marker_of or {}).get(name, 999), uv[0], uv[1]
        stage.add_keyframe(r.stamp_ns, r.track_ids, r.uv, rows)
        assert stage.drain() == 1
    return stage.finish()


def test_gcp_with_a_placeholder_height_is_used_horizontally_only(flight_3d, tmp_path):
    """Every GCP's height written as 400 m (the ground is at 488 m), GCP02 30 m east of where it is: the stage
    uses four GCPs horizontally, leaves GCP02 out, says so with WARNs; the four check points' horizontal RMSE
    (measured 2.73 cm = 0.36 GSD) is gated at 1.5 times that."""
    sk, targets = flight_3d
    control = targets_file(tmp_path / 'targets.txt', sk.origin, targets, gcp_height_m=400.0,
                           moved_enu_m={'GCP02': (30.0, 0.0, 0.0)})
    stage = _stage(sk, control_file=str(control))
    outcome = _fly(stage, sk.records, {t.name: t.marker_id for t in targets}, STATUS_FIX)
    d, q = stage.diag, stage.quality()
    assert outcome.status == 'done' and not outcome.failed
    assert d.values['gcps_horizontal_only'] == 4 and d.values['gcps_rejected'] == 1
    assert d.values['gcps_rejected_names'] == 'GCP02' and d.values['gcps_full'] == 0
    assert d.values['gcps_horizontal_only_names'] == 'GCP01,GCP03,GCP04,GCP05'
    warns = [t for lv, t in d.problems if lv == WARN]
    assert any(t.startswith('control: GCP GCP02 not used') for t in warns)
    assert any(t.startswith('control: GCP GCP01') and 'placeholder' in t for t in warns)
    assert q['control']['use']['GCP02'] == 'unused' and q['gcp_rmse']['vertical_m'] is None
    assert sorted(r['name'] for r in q['gcps']) == ['GCP01', 'GCP03', 'GCP04', 'GCP05']
    out = stage.out
    assert len(out.pose_by_stamp) == len(sk.records) and len(out.georeferences) == 1
    h = q['check_rmse']['horizontal_m']
    print(f'stage, 3D GNSS, 400 m GCP heights, GCP02 30 m off: check RMSE h {h * 100:.2f} cm '
          f'({h / sk.gsd_m:.2f} GSD) over {q["check_rmse"]["count"]}')
    assert q['check_rmse']['count'] == 4 and h <= 1.5 * 0.36 * sk.gsd_m
    assert out.qualities and out.qualities[-1]['georeference'] == 'final'
    # The figures published in flight come from the in-flight block, the last from the final adjustment.
    assert out.qualities[-1]['block'] == 'adjusted' and q['block'] == 'adjusted'
    assert any(d['block'] == 'in_flight' for d in out.qualities[:-1])
    # The report, from the detections the map folder keeps: GCP02, left out, with its 30 m; the others without
    # their placeholder heights; the check points as the stage measured them.
    doc = json.loads(json.dumps(out.qualities[-1], default=lambda v: v.tolist()))
    fig = _report_from_the_map_folder(stage, doc, tmp_path, {'/bundle_node': {'values': dict(d.values)}})
    use = {r['name']: r for r in fig['gcp_residuals']['points']}
    assert use['GCP02']['use'] == 'not used' and abs(use['GCP02']['dx_m'] + 30.0) < 1.0
    assert all(use[n]['use'] == 'horizontal only' and use[n]['dz_m'] is None for n in ('GCP01', 'GCP03', 'GCP04'))
    assert abs(fig['check_points']['rmse']['horizontal_m'] - h) < 1e-4


def test_a_flight_without_any_fix_is_placed_by_its_gcps_at_the_end(flight_3d, tmp_path):
    """No fix in the whole flight, 5 GCPs in the control file: at the end the map's origin is the GCPs' centre
    (a WARN says so), the GCPs are taken as given and place the block; the check points against the truth."""
    sk, targets = flight_3d
    control = targets_file(tmp_path / 'targets.txt', sk.origin, targets)
    stage = _stage(sk, control_file=str(control), fix_wait_s=0.0)
    outcome = _fly(stage, sk.records, {t.name: t.marker_id for t in targets}, fixes=False)
    q = stage.quality()
    warns = [t for lv, t in stage.diag.problems if lv == WARN]
    h, v = q['check_rmse']['horizontal_m'], q['check_rmse']['vertical_m']
    print(f'stage, no fix, 5 GCPs: {outcome.status}, check RMSE h {h * 100:.2f} cm v {v * 100:.2f} cm '
          f'({h / sk.gsd_m:.2f} / {v / sk.gsd_m:.2f} GSD) over {q["check_rmse"]["count"]}')
    assert outcome.status == 'done' and not outcome.failed and stage.at.georeferenced
    assert stage.diag.values['georeferenced'] == 'True'   # what the ground station shows
    assert any(t.startswith('no GNSS fix came in this flight') for t in warns)
    assert q['check_rmse']['count'] == 4
    assert h <= 1.5 * 0.0098 and v <= max(1.5 * 0.0053, 0.01)   # measured 0.98 / 0.53 cm (0.13 / 0.07 GSD)
    assert len(stage.out.pose_by_stamp) == len(sk.records) and len(stage.out.georeferences) == 1
    assert abs(stage.out.georeferences[0][0] - np.median([t.lat_deg for t in stage.control.targets
                                                           if t.role == 'gcp'])) < 1e-9


def test_the_flight_after_every_track_was_lost_is_a_segment_joined_through_its_gnss(flight_rtk):
    sk = flight_rtk
    kb = len(sk.records) // 2
    recs = [r if i < kb else dataclasses.replace(r, track_ids=np.asarray(r.track_ids) + 10**6, target_uv={})
            for i, r in enumerate(sk.records)]
    stage = _stage(sk)
    outcome = _fly(stage, recs)
    counts = stage.diag.counts()
    print(f'segment: {counts.get("keyframes_joined_from_a_segment")} joined, '
          f'{counts.get("keyframes_oriented")} of {len(recs)} oriented')
    assert outcome.status == 'done'
    assert counts.get('keyframes_joined_from_a_segment', 0) >= 3   # a segment joins once it has a few
    assert any(lv == WARN and t.startswith('every track was lost') for lv, t in stage.diag.problems)
    after = [r.stamp_ns for r in recs[kb:] if r.stamp_ns in stage.out.pose_by_stamp]
    assert len(after) >= len(recs) - kb - 1                       # handed out, not only adjusted
    # The segment sits where its RTK fixes put it: camera centres within 6.6 cm of the truth (measured), gated at 1.5x.
    T = {r.stamp_ns: t for r, t in zip(recs, sk.true_map_T_cam)}
    o = stage.at.origin
    err = [np.linalg.norm(sk.origin.ecef_to_enu(o.enu_to_ecef(pose[:3, 3])) - T[s][:3, 3])
           for s, (pose, _) in stage.out.pose_by_stamp.items() if s in after]
    print(f'segment: camera centres after the break within {max(err) * 100:.1f} cm of the truth')
    assert max(err) < 1.5 * 0.066


def test_health_tells_a_good_block_from_one_that_does_not_orient(flight_rtk):
    """A good flight: block-check verdict ok, every keyframe oriented, no WARN. Keyframes that share no
    track: ERROR with the reason, no georeference, nothing to adjust at the end."""
    sk = flight_rtk
    good = _stage(sk)
    assert _fly(good, sk.records).status == 'done'
    v = good.diag.values
    assert v['verdict'] == 'ok' and v['keyframes_registered_share'] == 1.0
    assert good.diag.level() < WARN, good.diag.problems
    bad = _stage(sk, georef_warn_keyframes=5)
    recs = [dataclasses.replace(r, track_ids=np.asarray(r.track_ids) + 10**6 * (k + 1))
            for k, r in enumerate(sk.records[:12])]
    outcome = _fly(bad, recs)
    texts = [t for _, t in bad.diag.problems]
    assert bad.diag.counts()['keyframes_not_oriented'] == len(recs)
    assert any('of the last' in t and 'waiting_for_initialisation' in t for t in texts)
    assert any(lv == ERROR and t.startswith('no georeference after') for lv, t in bad.diag.problems)
    assert bad.diag.level() == ERROR and bad.diag.values['keyframes_registered_share'] == 0.0
    assert outcome.status == 'none' and not bad.out.pose_by_stamp


class OrderedOutputs(RecordedOutputs):
    """RecordedOutputs that also keep the order of the camera and pose publications."""

    def __init__(self):
        super().__init__()
        self.order = []

    def camera(self, camera, stamp_ns):
        super().camera(camera, stamp_ns)
        self.order.append('camera')

    def poses(self, poses):
        super().poses(poses)
        self.order.append('poses')


def test_the_final_adjustments_camera_goes_out_before_its_poses(flight_rtk):
    """The stage starts from a camera whose k1 is 0.03 off the images' (-0.09 for -0.12) and refines k1, k2 in the
    final adjustment (final_self_calibration): the camera it sends after the final adjustment is the refined one
    (k1 -0.1192: 0.0008 off, gated at 1.5x), sent before the final poses adjusted with it. Without the
    self-calibration the input camera goes out."""
    sk = flight_rtk
    wrong = dataclasses.replace(sk.camera, dist=np.add(sk.camera.dist, [0.03, 0.0, 0.0, 0.0, 0.0]))
    stage = _stage(sk, camera=wrong, out=OrderedOutputs(), final_self_calibration='k1,k2')
    assert _fly(stage, sk.records).status == 'done'
    out = stage.out
    cam, stamp = out.cameras[-1]
    print(f'final camera k1 {cam.dist[0]:.5f} k2 {cam.dist[1]:.5f}, the images\' {sk.camera.dist[0]:.5f} '
          f'{sk.camera.dist[1]:.5f}, the input\'s {wrong.dist[0]:.5f}')
    assert abs(cam.dist[0] - sk.camera.dist[0]) < 1.5 * 0.0008 and cam == stage.at.camera
    assert stamp == max(r.stamp_ns for r in sk.records if r.stamp_ns in out.pose_by_stamp)
    assert out.order[-2:] == ['camera', 'poses']
    plain = _stage(sk, out=OrderedOutputs())
    assert _fly(plain, sk.records[:12]).status == 'done'
    assert plain.out.cameras and plain.out.cameras[-1][0] == sk.camera


def test_the_pass_sends_its_refined_camera_before_the_poses_it_moved(flight_rtk):
    """In flight, a full adjustment of the pass (growth_ratio) that refines the lens (pass_self_calibration) sends
    the refined camera, then every keyframe's pose, before the final adjustment: the stereo node pairs the
    keyframes with the intrinsics their poses were adjusted with. The input camera's k1 is 0.03 off the images'."""
    sk = flight_rtk
    wrong = dataclasses.replace(sk.camera, dist=np.add(sk.camera.dist, [0.03, 0.0, 0.0, 0.0, 0.0]))
    stage = _stage(sk, camera=wrong, out=OrderedOutputs(), pass_self_calibration='k1,k2', growth_ratio=1.5,
                   pass_min_keyframes=10)
    n = len(sk.records)
    for r in sk.records[:-1]:
        f = r.fix
        stage.add_fix(r.stamp_ns, f.lat_deg, f.lon_deg, f.h_m, np.diag(np.diag(f.cov_enu_m2)), STATUS_GBAS_FIX,
                      COV_DIAGONAL_KNOWN)
        stage.add_keyframe(r.stamp_ns, r.track_ids, r.uv, np.zeros(0, TARGET_DTYPE))
        assert stage.drain() == 1
    out = stage.out
    assert out.cameras, 'no refined camera was sent during the pass'
    cam, stamp = out.cameras[0]
    print(f'{n - 1} keyframes, {len(out.cameras)} cameras sent in flight; the first k1 {cam.dist[0]:+.4f} at '
          f'keyframe {[r.stamp_ns for r in sk.records].index(stamp)}; input {wrong.dist[0]:+.4f}, '
          f'images {sk.camera.dist[0]:+.4f}')
    assert abs(cam.dist[0] - sk.camera.dist[0]) < 0.5 * abs(wrong.dist[0] - sk.camera.dist[0])
    i = out.order.index('camera')
    assert out.order[i + 1] == 'poses'
    assert all(stage.at.kfs[k].stamp_ns in out.pose_by_stamp for k in stage.at.registered)
    # Without the pass's self-calibration no camera goes out before the final adjustment.
    plain = _stage(sk, camera=wrong, out=OrderedOutputs())
    for r in sk.records[:20]:
        f = r.fix
        plain.add_fix(r.stamp_ns, f.lat_deg, f.lon_deg, f.h_m, np.diag(np.diag(f.cov_enu_m2)), STATUS_GBAS_FIX,
                      COV_DIAGONAL_KNOWN)
        plain.add_keyframe(r.stamp_ns, r.track_ids, r.uv, np.zeros(0, TARGET_DTYPE))
        assert plain.drain() == 1
    assert not plain.out.cameras


def _report_from_the_map_folder(stage, doc: dict, tmp_path, diagnostics=None) -> dict:
    """The flight report's figures from a map folder as the map node keeps it: the published poses, the final
    camera, the last live accuracy document (`doc`, as JSON) with its detections."""
    from photogram_ros.io.flight_report import build_report
    from photogram_ros.io.map_store import CAMERA_FINAL, MapStore
    store = MapStore(tmp_path / 'map', 0.1, 256)
    store.set_origin(stage.at.origin)
    store.save_camera(stage.at.camera, CAMERA_FINAL)
    for stamp, (T, _) in stage.out.pose_by_stamp.items():
        store.save_keyframe_pose(stamp, T)
        store.save_keyframe_image(stamp, b'')     # the figures read the stored detections, not the images
    store.save_control_points(doc)
    (tmp_path / 'report').mkdir()
    return build_report(tmp_path / 'report', store, 'EPSG:32632', {}, control=stage.control, diagnostics=diagnostics)


def test_the_report_intersects_the_stages_detections_into_the_same_figures(flight_3d, tmp_path):
    """The map folder as the map node keeps it (the published poses, the final camera, the last live accuracy
    document with its detections, as JSON): the flight report's check-point and GCP figures equal the stage's
    (map/control_points, what the ground station shows) to 0.1 mm: one method over one set of detections.
    The GCP residuals come from the adjusted cameras, not from the adjusted target point its prior holds."""
    sk, targets = flight_3d
    control = targets_file(tmp_path / 'targets.txt', sk.origin, targets)
    stage = _stage(sk, control_file=str(control))
    assert _fly(stage, sk.records, {t.name: t.marker_id for t in targets}, STATUS_FIX).status == 'done'
    doc = json.loads(json.dumps(stage.out.qualities[-1], default=lambda v: v.tolist()))
    assert doc['check_rmse']['count'] == 4 and doc['gcp_rmse']['count'] == 5
    assert all(len(doc['detections'][r['name']]) >= r['images'] >= 2 for r in doc['check_points'] + doc['gcps'])
    fig = _report_from_the_map_folder(stage, doc, tmp_path)
    chk, gcp = fig['check_points']['rmse'], fig['gcp_residuals']['rmse']
    print(f"report check points {chk['horizontal_m'] * 100:.2f} / {chk['z_m'] * 100:.2f} cm, page "
          f"{doc['check_rmse']['horizontal_m'] * 100:.2f} / {doc['check_rmse']['vertical_m'] * 100:.2f} cm; GCPs "
          f"{gcp['horizontal_m'] * 100:.2f} / {gcp['z_m'] * 100:.2f} cm, page {doc['gcp_rmse']['horizontal_m'] * 100:.2f}"
          f" / {doc['gcp_rmse']['vertical_m'] * 100:.2f} cm")
    assert fig['check_points']['detections'].startswith('found by the tracker in flight')
    assert chk['count'] == 4 and gcp['count'] == 5
    for a, b in ((chk['horizontal_m'], doc['check_rmse']['horizontal_m']), (chk['z_m'], doc['check_rmse']['vertical_m']),
                 (gcp['horizontal_m'], doc['gcp_rmse']['horizontal_m']), (gcp['z_m'], doc['gcp_rmse']['vertical_m'])):
        assert abs(a - b) < 1e-4
    # GCPs from the adjusted cameras: their residuals are not the prior's (σ 1 / 1 / 2 cm holds the point).
    assert gcp['horizontal_m'] > 0.0


def test_fix_policy():
    """No covariance: the GNSS mode's; RTK status with a 2 m sigma: not used (lost corrections); no position:
    not used. A keyframe waits for its fix; a later fix ends the wait."""
    stage = AdjustmentStage(AdjustmentParams(), DiagnosticsLog())
    assert stage.add_fix(1, 45.0, 7.0, 500.0, np.zeros((3, 3)), STATUS_GBAS_FIX, COV_UNKNOWN)
    assert stage._fixes[1].cov_enu_m2[0, 0] == pytest.approx(0.25)
    assert not stage.add_fix(2, 45.0, 7.0, 500.0, np.eye(3) * 4.0, STATUS_GBAS_FIX, COV_DIAGONAL_KNOWN)
    assert stage.add_fix(3, 45.0, 7.0, 500.0, np.eye(3) * 4.0, STATUS_FIX, COV_DIAGONAL_KNOWN)
    assert not stage.add_fix(4, float('nan'), 7.0, 500.0, np.eye(3), STATUS_FIX, COV_DIAGONAL_KNOWN)
    c = stage.diag.counts()
    assert (c['fixes'], c['fixes_without_covariance'], c['fixes_too_inaccurate'], c['fixes_without_position']) \
        == (2, 1, 1, 1)


ROS_BLOCKED_FLIGHT = """
import importlib.abc, sys
ROS = ('rclpy', 'rosidl_runtime_py', 'rcl_interfaces', 'builtin_interfaces', 'sensor_msgs', 'std_msgs',
       'geometry_msgs', 'diagnostic_msgs', 'nav_msgs')
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ROS:
            raise ImportError(f'ROS package {name} imported')
sys.meta_path.insert(0, Block())
sys.path.insert(0, 'tests')
import photogram_ros.stages.map
import test_adjustment_stage as t
sk = t.simulate_keyframes(t.preset('tiny'), keyframe_interval_s=1.0, attitude_sigma_deg=None)
stage = t._stage(sk)
outcome = t._fly(stage, sk.records[:12])
assert not [m for m in sys.modules if m.split('.')[0] in ROS]
print(outcome.status, stage.diag.counts().get('keyframes_oriented', 0), len(stage.out.pose_by_stamp))
"""


def test_the_stages_run_with_ros_unimportable():
    """Both stages import, and the adjustment stage flies 12 keyframes, with every ROS package blocked."""
    r = subprocess.run([sys.executable, '-c', ROS_BLOCKED_FLIGHT], cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    status, oriented, poses = r.stdout.split()[-3:]
    assert status == 'done' and int(oriented) >= 10 and int(poses) >= 10


def test_a_gimballed_cameras_first_keyframes_wait_for_the_attitude_stream_to_start(flight_rtk):
    """Attitudes reach the stage by another path than keyframes and often start later: the first keyframe
    waits for the first attitude instead of taking no antenna offset; with no attitude at all it waits
    fix_wait_s from the first keyframe, then goes on and says why."""
    import time
    gimbal = {'lever_arm_cam_m': [0.0, 0.0, 0.0], 'lever_arm_body_frd_m': [0.05, 0.0, -0.20]}
    r = flight_rtk.records[0]

    def keyframe(stage, r, arrival_s=None):
        f = r.fix
        stage.add_fix(r.stamp_ns, f.lat_deg, f.lon_deg, f.h_m, np.diag(np.diag(f.cov_enu_m2)), STATUS_GBAS_FIX,
                      COV_DIAGONAL_KNOWN)
        stage.add_keyframe(r.stamp_ns, r.track_ids, r.uv, arrival_s=arrival_s)

    stage = _stage(flight_rtk, **gimbal)
    keyframe(stage, r)
    assert stage.drain() == 0                                 # no attitude yet: it waits
    for dt_ns in (-50_000_000, 50_000_000):                  # the autopilot's attitudes around the keyframe
        stage.add_attitude(r.stamp_ns + dt_ns, [0.0, 0.0, 0.0, 1.0])
    assert stage.drain() == 1
    assert stage.diag.counts().get('keyframes_without_attitude', 0) == 0
    # Attitudes from a busy link arrive in bursts seconds apart: the next keyframe waits for the next burst.
    time.sleep(1.2)
    keyframe(stage, flight_rtk.records[1])
    assert stage.drain() == 0

    silent = _stage(flight_rtk, **gimbal)
    keyframe(silent, r, arrival_s=time.monotonic() - 60.0)       # a minute without any attitude
    assert silent.drain() == 1
    assert silent.diag.counts()['keyframes_without_attitude'] == 1
