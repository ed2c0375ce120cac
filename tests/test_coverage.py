"""Coverage in flight (core/coverage.py) against an independent oracle: ground cells projected into each camera.

A three-line survey over flat ground (the sample flight's geometry: 640x480, f = 520 px, 40 m, 65 %
side overlap, a keyframe every 5 m). The oracle counts, per 1 m ground cell, the cameras whose image
holds the cell's centre (PinholeCamera.project), which is not how the coverage rasterises footprints.
"""

import math

import numpy as np
import pytest

from photogram_ros.core.coverage import COVERAGE, FORWARD_OVERLAP, NOT_ORIENTED, Coverage, CoverageConfig
from photogram_ros.core.rotations import make_T
from photogram_ros.sim.scenario import preset

CAM = preset('sample').camera()
H_M, SPACING_M, STEP_M = 40.0, 17.2, 5.0
# The footprint across the line through its centre, m: the image's mid-side pixels cast on the ground
# (barrel distortion widens it beyond 640 px * 40 m / 520 px).
_RAYS = CAM.unproject(np.array([[-0.5, CAM.cy], [CAM.width - 0.5, CAM.cy], [CAM.cx, -0.5], [CAM.cx, CAM.height - 0.5]]))
WIDTH_M = float(H_M * (_RAYS[1, 0] / _RAYS[1, 2] - _RAYS[0, 0] / _RAYS[0, 2]))
LENGTH_M = float(H_M * (_RAYS[3, 1] / _RAYS[3, 2] - _RAYS[2, 1] / _RAYS[2, 2]))
R_NORTH = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])   # optical x east, y south, z down
R_SOUTH = np.array([[-1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]])


def survey(skip=lambda line, y: False):
    """[(stamp_ns, map_T_cam, line)] of a lawnmower: line 0 north, 1 south, 2 north, each 0..90 m."""
    out, t = [], 0
    for line in range(3):
        ys = np.arange(0.0, 90.01, STEP_M)
        for y in (ys if line % 2 == 0 else ys[::-1]):
            t += 1
            if not skip(line, y):
                R = R_NORTH if line % 2 == 0 else R_SOUTH
                out.append((t * 10**9, make_T(R, np.array([line * SPACING_M, y, H_M])), line))
        t += 10   # the turn
    return out


def oracle_views(kfs, xs, ys):
    X, Y = np.meshgrid(xs, ys)
    P = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    n = np.zeros(X.size, int)
    for _, T, _ in kfs:
        uv, front = CAM.project((P - T[:3, 3]) @ T[:3, :3])
        n += front & CAM.in_image(uv)
    return n.reshape(X.shape)


def feed(kfs, cfg=None, area=None, oriented=lambda stamp: True):
    cov = Coverage(CAM, cfg or CoverageConfig(), area)
    reports = []
    for stamp, T, _ in kfs:
        cov.set_keyframe(stamp, T, 0.0, oriented(stamp))
        reports.append(cov.update())
    return cov, reports


def test_plain_survey_has_no_gap_and_the_planned_overlaps():
    kfs = survey()
    _, reps = feed(kfs)
    r = reps[-1]
    assert r.lines == 3
    assert not [g for g in r.gaps if g.area_m2 >= 4.0]
    assert r.coverage_share == pytest.approx(1.0)
    # Forward overlap: 1 - step / footprint length; side: 1 - spacing / footprint width.
    assert r.forward_overlap_median == pytest.approx(1 - STEP_M / LENGTH_M, abs=0.02)
    assert r.side_overlap_min == pytest.approx(1 - SPACING_M / WIDTH_M, abs=0.03)
    # The survey area: three swaths 90 m long, 2 * 17.2 m + the footprint width - 2 m margin wide.
    assert r.survey_area_m2 == pytest.approx(90 * (2 * SPACING_M + WIDTH_M - 2.0), rel=0.03)


def test_camera_stop_on_the_outer_line_is_located_and_sized_like_the_oracle():
    gap = (15.0, 65.0)   # line 2 (the outer one, north) has no keyframe strictly between these y
    kfs = survey(lambda line, y: line == 2 and gap[0] < y < gap[1])
    cov, reps = feed(kfs)
    # Oracle: the cells of line 2's swath (its centres +- half width less the 1 m margin) seen < 2 times.
    xs, ys = np.arange(-30, 70) + 0.5, np.arange(-25, 115) + 0.5
    n = oracle_views(kfs, xs, ys)
    X, Y = np.meshgrid(xs, ys)
    half = WIDTH_M / 2 - 1.0
    swath = lambda cx: (np.abs(X - cx) <= half) & (Y >= 0) & (Y <= 90)  # noqa: E731
    missing = (swath(0) | swath(SPACING_M) | swath(2 * SPACING_M)) & (n < 2)
    assert missing.sum() > 200
    truth_c = np.array([X[missing].mean(), Y[missing].mean()])
    gaps = [g for g in reps[-1].gaps if g.kind == COVERAGE]
    assert len(gaps) == 1, reps[-1].gaps
    g = gaps[0]
    assert np.hypot(*(g.centroid_map_m - truth_c)) < 1.5
    assert g.area_m2 == pytest.approx(float(missing.sum()), rel=0.12)
    assert g.min_views == 0
    # Reported with the first keyframe after the stop, not at the end of the flight.
    first_after = next(i for i, (_, T, line) in enumerate(kfs) if line == 2 and T[1, 3] >= gap[1])
    assert any(x.kind == COVERAGE and x.area_m2 > 0.5 * g.area_m2 for x in reps[first_after].gaps)
    # The line's own hole: the ground between the two keyframes that neither sees, the whole swath wide.
    fwd = [x for x in reps[-1].gaps if x.kind == FORWARD_OVERLAP]
    assert len(fwd) == 1 and fwd[0].area_m2 > g.area_m2
    assert reps[-1].low_forward_pairs and reps[-1].low_forward_pairs[0][2] == 0.0
    assert reps[-1].coverage_share < 0.98


def test_cells_ahead_of_the_drone_are_never_gaps():
    kfs = survey()
    for k in range(3, len(kfs)):
        _, reps = feed(kfs[:k])
        assert not [g for g in reps[-1].gaps if g.area_m2 >= 4.0], k


def test_mission_polygon_beyond_the_flight_is_a_gap_once_finished():
    kfs = survey()
    area = [np.array([[-20.0, 0.0], [80.0, 0.0], [80.0, 90.0], [-20.0, 90.0]])]   # 20 m more to the east
    cov, reps = feed(kfs, area=area)
    cov.finish()
    r = cov.update()
    east = [g for g in r.gaps if g.kind == COVERAGE and g.centroid_map_m[0] > 60]
    assert len(east) == 1
    # What the survey did not see east of line 2's footprint edge up to 80 m.
    assert east[0].area_m2 == pytest.approx((80 - 2 * SPACING_M - WIDTH_M / 2) * 90, rel=0.1)
    assert r.survey_area_m2 == pytest.approx(100 * 90, rel=0.03)   # cv2 fills boundary cells too


def test_keyframes_the_adjustment_skipped_are_seen_but_not_mapped():
    kfs = survey()
    skipped = {s for s, T, line in kfs if line == 1 and 20 < T[1, 3] < 70}
    _, reps = feed(kfs, oriented=lambda s: s not in skipped)
    r = reps[-1]
    assert not [g for g in r.gaps if g.kind == COVERAGE and g.area_m2 >= 4.0]
    # Line 1 is the middle one: lines 0 and 2 see its swath, so nothing is unmapped ...
    assert not [g for g in r.gaps if g.kind == NOT_ORIENTED and g.area_m2 >= 4.0]
    # ... but on an outer line the strip only that line sees is.
    skipped = {s for s, T, line in kfs if line == 2 and 20 < T[1, 3] < 70}
    _, reps = feed(kfs, oriented=lambda s: s not in skipped)
    unmapped = [g for g in reps[-1].gaps if g.kind == NOT_ORIENTED]
    assert len(unmapped) == 1 and unmapped[0].area_m2 > 200
    # While the skipped keyframes are the newest, they wait for the adjuster: no gap yet.
    i = max(i for i, (s, _, _) in enumerate(kfs) if s in skipped)
    assert not [g for g in reps[i].gaps if g.kind == NOT_ORIENTED]


def test_grid_cell_size_does_not_move_the_gap():
    kfs = survey(lambda line, y: line == 2 and 15 < y < 65)
    got = []
    for c in (0.5, 1.0, 2.0):
        _, reps = feed(kfs, CoverageConfig(coverage_cell_m=c))
        got.append([g for g in reps[-1].gaps if g.kind == COVERAGE][0])
    for g in got[1:]:
        assert np.hypot(*(g.centroid_map_m - got[0].centroid_map_m)) < 1.0
        assert g.area_m2 == pytest.approx(got[0].area_m2, rel=0.1)
    assert math.isfinite(got[0].area_m2)
