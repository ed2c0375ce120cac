"""Targets searched only where they can be (core/control.target_regions, detect_targets_in_regions).

A nadir camera 100 m above its targets: the markers painted into a 4000x3000 photo at the pixels their surveyed
coordinates project to; the region search on the photo's 1/4 decode and full-resolution windows finds what the
whole-image search finds, at the same centres; targets far from the footprint cost no decode at all.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_target_detection_fast import paint_markers  # noqa: E402

from photogram_ros.core.camera import PinholeCamera  # noqa: E402
from photogram_ros.core.control import (ControlSet, SurveyedTarget, TargetRegionOptions,  # noqa: E402
                                        detect_keyframe_targets_encoded, detect_targets_in_regions, target_regions)
from photogram_ros.core.geodesy import LocalFrame  # noqa: E402

W, H = 4000, 3000
CAM = PinholeCamera(W, H, 3000.0, 3000.0, (W - 1) / 2, (H - 1) / 2)
GROUND = LocalFrame(47.3977, 8.5456, 500.0)
HEIGHT_M = 100.0


def _photo(seed: int = 3):
    rng = np.random.default_rng(seed)
    noise = rng.normal(128, 40, (H // 8, W // 8)).clip(0, 255).astype(np.uint8)
    bg = cv2.cvtColor(cv2.resize(noise, (W, H), interpolation=cv2.INTER_CUBIC), cv2.COLOR_GRAY2BGR)
    img, truth = paint_markers(bg, (60, 90, 140), rng, per_side=2)
    ok, jpg = cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, 92])
    return jpg.tobytes(), truth


def _control(truth: dict, offset_m=(0.0, 0.0)) -> ControlSet:
    """The painted markers as surveyed targets on the ground under a nadir camera at GROUND + HEIGHT_M (image
    x east, y south), shifted by offset_m (east, north)."""
    out = []
    for k, uv in truth.items():
        e = (uv[0] - CAM.cx) * HEIGHT_M / CAM.fx + offset_m[0]
        n = -(uv[1] - CAM.cy) * HEIGHT_M / CAM.fy + offset_m[1]
        lat, lon, h = (float(v) for v in np.ravel(GROUND.enu_to_geodetic(np.array([e, n, 0.0]))))
        out.append(SurveyedTarget(f'GCP{k:02d}', k, lat, lon, h, 'gcp'))
    return ControlSet(out)


def _reduced(jpg: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(jpg, np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_4)


def test_region_search_finds_what_the_whole_image_search_finds():
    jpg, truth = _photo()
    control = _control(truth)
    regions = target_regions(CAM, control, GROUND.lat_deg, GROUND.lon_deg, GROUND.h_m + HEIGHT_M, 0.02)
    assert regions.status == 'rings' and len(regions.rings_px) == len(truth)
    found, stats = detect_targets_in_regions(jpg, _reduced(jpg), CAM, regions)
    whole = detect_keyframe_targets_encoded(jpg, CAM)
    assert len(whole) == len(truth) >= 5
    assert sorted(found['marker_id'].tolist()) == sorted(whole['marker_id'].tolist())
    by_id = {int(r['marker_id']): (r['u'], r['v']) for r in whole}
    diff = max(np.hypot(r['u'] - by_id[int(r['marker_id'])][0], r['v'] - by_id[int(r['marker_id'])][1])
               for r in found)
    assert diff < 0.05, diff
    # Full resolution searched in windows only (the six markers' and squares of the noise: 10 % measured).
    assert stats['full_decode'] == 1 and stats['windows'] >= 1 and stats['window_px'] < 0.15 * W * H, stats


def test_a_target_is_looked_for_only_in_its_ring():
    """One surveyed target: the other painted markers (not near its ring) are not searched for."""
    jpg, truth = _photo()
    far = max(truth, key=lambda k: np.hypot(*(truth[k] - [CAM.cx, CAM.cy])))
    near = min(truth, key=lambda k: np.hypot(*(truth[k] - [CAM.cx, CAM.cy])))
    control = _control({near: truth[near]})
    opt = TargetRegionOptions(gnss_margin_m=2.0, tilt_margin_deg=2.0)
    regions = target_regions(CAM, control, GROUND.lat_deg, GROUND.lon_deg, GROUND.h_m + HEIGHT_M, 0.02, opt)
    found, _ = detect_targets_in_regions(jpg, _reduced(jpg), CAM, regions)
    assert near in found['marker_id'].tolist() and far not in found['marker_id'].tolist()


def test_no_target_near_the_footprint_costs_no_decode():
    jpg, truth = _photo()
    control = _control(truth, offset_m=(800.0, -600.0))
    regions = target_regions(CAM, control, GROUND.lat_deg, GROUND.lon_deg, GROUND.h_m + HEIGHT_M, 0.02)
    assert regions.status == 'rings' and regions.rings_px == [] and regions.box(CAM) is None
    found, stats = detect_targets_in_regions(b'not a jpeg', np.zeros((H // 4, W // 4), np.uint8), CAM, regions)
    assert len(found) == 0 and stats == {'squares': 0, 'windows': 0, 'window_px': 0, 'full_decode': 0}
    assert target_regions(CAM, ControlSet([]), 47.0, 8.0, 600.0).box(CAM) is None


def test_heights_that_put_the_camera_under_a_target_search_everywhere():
    _, truth = _photo()
    regions = target_regions(CAM, _control(truth), GROUND.lat_deg, GROUND.lon_deg, GROUND.h_m - 30.0)
    assert regions.status == 'unknown' and 'above a target' in regions.why
    assert regions.box(CAM) == (0, 0, W, H)


@pytest.mark.parametrize('width', [999, 1001])
def test_a_reduced_image_of_another_size_is_refused(width):
    from photogram_ros.errors import DataError
    jpg, truth = _photo()
    regions = target_regions(CAM, _control(truth), GROUND.lat_deg, GROUND.lon_deg, GROUND.h_m + HEIGHT_M)
    with pytest.raises(DataError, match='no integer reduction'):
        detect_targets_in_regions(jpg, np.zeros((750, width + 100), np.uint8), CAM, regions)


def test_the_graph_gives_the_tracker_the_adjusters_control_file():
    from photogram_ros.nodes.graph import GraphSpec, role_values
    spec = GraphSpec(extra={'bundle': {'control_file': '/x/targets.txt', 'control_heights': 'orthometric'}})
    v = role_values(spec, 'tracker')
    assert v['control_file'] == '/x/targets.txt' and v['control_heights'] == 'orthometric'
    own = GraphSpec(extra={'bundle': {'control_file': '/x/targets.txt'}, 'tracker': {'control_file': '/y.txt'}})
    assert role_values(own, 'tracker')['control_file'] == '/y.txt'
    assert 'control_file' not in role_values(GraphSpec(), 'tracker')


def test_a_compressed_keyframe_hands_out_its_bytes_until_decoded():
    from photogram_ros.core.keyframe_image import EncodedImage, Keyframe
    ok, jpg = cv2.imencode('.jpg', np.full((64, 96, 3), 128, np.uint8))
    kf = Keyframe(0, 0, 1, EncodedImage(jpg.tobytes()), np.zeros(0), size=(96, 64))
    assert kf.encoded() is not None and kf.encoded().data.size == jpg.size
    assert kf.image.shape == (64, 96, 3) and kf.encoded() is None   # decoded: the raw image from now on
    assert Keyframe(1, 1, 2, np.zeros((4, 4, 3), np.uint8), np.zeros(0)).encoded() is None
