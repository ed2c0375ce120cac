"""A resumed run feeds again the keyframes its map holds without a pose (issue 48): camera_node
`resume_keyframes_of` plays the map's stored keyframe images, with their stamps and the fixes the map kept
(io/image_source.StoredKeyframes), before its own source's frames, so that the tracker and the adjuster take them
like any keyframe. The flight through the whole graph is tests/test_faults_resume.py's (slow)."""

from __future__ import annotations

import json
import shutil

import numpy as np

from test_camera_node import _listener, _spin_until, survey  # noqa: F401  (the module's fixture)


def _stored_map(root, photos: list, posed: list[int], fixes: dict):
    """A map folder holding `photos` ((path, stamp_ns)) as keyframe images; poses for the stamps in `posed`;
    keyframe_fixes.jsonl rows for `fixes` (stamp -> (lat, lon, h, sigma_h or None))."""
    from photogram_ros.io.flight_inputs import append_keyframe_fix
    from photogram_ros.io.map_store import MapStore
    store = MapStore(root, cell_m=0.5, tile_cells=64)
    for path, stamp in photos:
        store.save_keyframe_image(stamp, path.read_bytes())
    for stamp in posed:
        store.save_keyframe_pose(stamp, np.eye(4))
    for stamp, (lat, lon, h, sigma) in fixes.items():
        append_keyframe_fix(root, stamp, lat, lon, h, 0, sigma, None if sigma is None else 2 * sigma)
    return store


def test_stored_keyframes_without_a_pose_are_played_first_with_their_fixes(survey, rclpy_context, tmp_path):  # noqa: F811
    from rclpy.executors import SingleThreadedExecutor

    from photogram_ros import msgs
    from photogram_ros.io.image_source import FolderSource
    from photogram_ros.nodes.camera_node import CameraNode
    photos, truth, calib, geo = survey
    entries = FolderSource(photos).entries   # (path, stamp_ns) in time order
    assert len(entries) >= 6
    # Before the crash: keyframes 0..3 saved, 1 oriented; the restart's camera starts at photo 3 (taken again).
    src = tmp_path / 'src'
    src.mkdir()
    for path, _ in entries[3:]:
        shutil.copy(path, src / path.name)
    s = [stamp for _, stamp in entries]
    fix0 = (47.1, 8.2, 500.5, 0.03)     # an RTK keyframe: its sigma kept
    fix2 = (47.2, 8.3, 501.5, None)     # kept without one: exif_sigma_m, exif_sigma_v_m
    _stored_map(tmp_path / 'map', entries[:4], posed=[s[1]], fixes={s[0]: fix0, s[2]: fix2, s[1]: fix0})
    cam = CameraNode({'source': str(src), 'calibration_file': str(calib), 'rate': 0.0, 'autostart': False,
                      'publish_exif_fix': False, 'exif_sigma_m': 3.0, 'exif_sigma_v_m': 6.0,
                      'resume_keyframes_of': str(tmp_path / 'map')},
                     context=rclpy_context)
    listener, got = _listener(rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(cam)
    ex.add_node(listener)
    n = 2 + len(entries) - 3
    try:
        assert _spin_until(ex, lambda: cam.pub_image.get_subscription_count() > 0)
        while cam.publish_next():
            ex.spin_once(timeout_sec=0.01)
        assert _spin_until(ex, lambda: len(got['image']) == n and len(got['fix']) == 2)
    finally:
        ex.shutdown()
        listener.destroy_node()
        cam.destroy_node()
    stamps = [msgs.ns_from_time(m.header.stamp) for m in got['image']]
    # The unposed 0 and 2 first (1 has its pose; 3 is the source's own first photo), then the source.
    assert stamps == [s[0], s[2]] + s[3:], (stamps, s)
    first = msgs.image_from_msg(got['image'][0])
    assert first.shape == (truth.camera.height, truth.camera.width, 3)
    fixes = [msgs.fix_from_navsatfix(m) for m in got['fix']]   # only the stored ones: publish_exif_fix false
    assert [f['stamp_ns'] for f in fixes] == [s[0], s[2]]
    assert abs(fixes[0]['lat_deg'] - 47.1) < 1e-9 and abs(fixes[0]['h_m'] - 500.5) < 1e-6
    assert np.allclose(np.diag(fixes[0]['covariance_enu_m2']), [0.03 ** 2, 0.03 ** 2, 0.06 ** 2])
    assert abs(fixes[1]['lon_deg'] - 8.3) < 1e-9 and np.allclose(np.diag(fixes[1]['covariance_enu_m2']),
                                                                   [9.0, 9.0, 36.0])
    c = cam.diag.counts()
    assert c['resumed_keyframes'] == 2 and c['frames'] == n, c


def test_keyframe_fixes_keep_their_sigmas_when_given(tmp_path):
    from photogram_ros.io.flight_inputs import append_keyframe_fix, keyframe_fixes
    append_keyframe_fix(tmp_path, 5, 1.0, 2.0, 3.0, 2, 0.02, 0.04)
    append_keyframe_fix(tmp_path, 6, 1.0, 2.0, 3.0, 0)
    with open(tmp_path / 'keyframe_fixes.jsonl', 'a') as f:
        f.write(json.dumps({'stamp_ns': 7, 'lat_deg': 1.0})[:-3])   # cut by a kill
    assert keyframe_fixes(tmp_path) == {
        5: {'lat_deg': 1.0, 'lon_deg': 2.0, 'h_m': 3.0, 'status': 2, 'sigma_h_m': 0.02, 'sigma_v_m': 0.04},
        6: {'lat_deg': 1.0, 'lon_deg': 2.0, 'h_m': 3.0, 'status': 0}}
