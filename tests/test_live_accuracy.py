"""bundle_node's live accuracy (map/control_points, /diagnostics) against check points intersected here.

The keyframes of test_gcp_flight.py (3D GNSS, five GCPs, four check points, the tracker's protocol)
go through a real bundle_node with the control file; at the end its live check-point RMSE must be the
one computed here (test_gcp_flight._check_rmse: every keyframe the simulator says saw the target, its
final adjusted pose, the truth's target centres rather than the control file's), its GCP residuals
apart, every keyframe counted as a 3D fix and the GNSS bias estimated from the GCPs.
"""

import numpy as np
import pytest

from helpers.control import targets_file
from helpers.keyframe_feed import run_bundle
from photogram_ros import msgs
from test_gcp_flight import _check_rmse, _values, flight_3d  # noqa: F401  (a fixture)

pytestmark = pytest.mark.ros


def test_live_check_points_are_those_of_the_published_poses(flight_3d, rclpy_context, tmp_path):  # noqa: F811
    sk, targets = flight_3d
    control = targets_file(tmp_path / 'targets.txt', sk.origin, targets)
    node, poses, georef = run_bundle(rclpy_context, sk, {t.name: t.marker_id for t in targets},
                                     {'control_file': str(control), 'quality_every': 3})
    try:
        q = node.quality()
        vals = _values(node)
    finally:
        node.destroy_node()
    assert set(poses) >= {node.at.kfs[k].stamp_ns for k in node.at.registered}
    # The final poses: the test's subscription may still hold window poses of some keyframes.
    final = {node.at.kfs[k].stamp_ns: msgs.pose_with_covariance_from_T(node.at.kfs[k].map_T_cam, 0)
             for k in node.at.registered}
    h, v, n = _check_rmse(sk, targets, final, georef)
    live = q['check_rmse']
    print(f'live check points: h {live["horizontal_m"] * 100:.2f} cm v {live["vertical_m"] * 100:.2f} cm; '
          f'intersected here: h {h * 100:.2f} cm v {v * 100:.2f} cm')
    assert live['count'] == n == 4
    assert live['horizontal_m'] == pytest.approx(h, abs=0.002) and live['vertical_m'] == pytest.approx(v, abs=0.002)
    assert float(vals['check_rmse_h_m']) == pytest.approx(live['horizontal_m'], rel=1e-4)
    assert vals['checks_measured'] == '4'
    assert {r['name'] for r in q['check_points']} == {t.name for t in targets if t.role == 'check'}
    assert all(r['images'] >= 2 and r['rms_px'] < 2.0 for r in q['check_points'])
    assert len(q['gcps']) == 5 and q['gcp_rmse']['horizontal_m'] < 0.05
    assert q['fix_share']['3d'] == pytest.approx(1.0) and q['keyframes'] == len(sk.records)
    assert q['gnss_bias_enu_m'] is not None and np.all(np.isfinite(q['gnss_bias_enu_m']))
