"""Stereo depth: Middlebury accuracy vs plain SGBM, rectification geometry, simulator pairs against the true DEM."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from conftest import shared_data
from figures import newest_figure
from photogram_ros.core import stereo
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.pairs import PairCriteria, choose_pairs, overlap_fraction
from photogram_ros.core.rotations import make_T, rot_x, rot_y, rot_z
from photogram_ros.core.stereo import CLOUD_DTYPE, StereoParams, stereo_pair

# The lengths these tests were written with (full resolution, no hole filling): the parameters'
# defaults now derive them from the GSD (core/gsd.py, tested in test_gsd.py).
FULL = dict(downscale=1.0, fill_holes_m=0.0, edge_step_m=1.0)
from photogram_ros.core.stereo_eval import load_scene, score
from photogram_ros.errors import ConfigError, DataError
from photogram_ros.params import from_dict

GSD_M = 40.0 / 520.0


# --- Middlebury ----------------------------------------------------------------------------------

# The module's bad-2 on the nonocc mask, as bench/stereo_middlebury.py measured it (method 'ours': the
# defaults): gated at 1.5x.
MIDDLEBURY = 'stereo_middlebury*.jsonl'   # the newest result file of the bench, as the table renders it


@pytest.mark.parametrize('name', ['tsukuba', 'venus'])
def test_middlebury_bad2_no_worse_than_plain_sgbm(name):
    sc = load_scene(shared_data('stereo', name))
    left, right = (cv2.cvtColor(i, cv2.COLOR_BGR2GRAY) for i in (sc.left, sc.right))
    num = 16 * ((sc.ndisp + 15) // 16)
    p = StereoParams()
    plain = stereo.disparity_from_sgbm(stereo.make_sgbm(p, 0, num, filtered=False).compute(left, right), 0)
    ours = stereo.match(left, right, p, 0, num).disparity_px
    mask = sc.masks['nonocc']
    s_plain, s_ours = score(plain, sc.gt_px, mask), score(ours, sc.gt_px, mask)
    assert s_ours['bad2'] <= s_plain['bad2']
    assert s_ours['bad1'] <= s_plain['bad1']
    middlebury, m = newest_figure(MIDDLEBURY, scene=name, method='ours')
    assert s_ours['bad2'] <= 1.5 * m['bad2'], f"bad-2 {s_ours['bad2']:.4f} > 1.5 x {m['bad2']} ({middlebury})"
    assert s_ours['density'] >= m['density'] / 1.5


def test_lr_check_rejects_occlusions_and_lowers_bad2():
    # Middlebury's occluded pixels (in 'gt' but not 'nonocc') have no true match in the right image:
    # a real left-right check rejects more of them (measured: 13 % kept vs 19 % without), and the
    # visible pixels it rejects are mostly wrong (bad-2 15 % among them vs 2.4 % among those kept).
    sc = load_scene(shared_data('stereo', 'teddy'))
    left, right = (cv2.cvtColor(i, cv2.COLOR_BGR2GRAY) for i in (sc.left, sc.right))
    num = 16 * ((sc.ndisp + 15) // 16)
    on = stereo.match(left, right, StereoParams(lr_check=True), 0, num).disparity_px
    off = stereo.match(left, right, StereoParams(lr_check=False), 0, num).disparity_px
    occ = sc.masks['gt'] & ~sc.masks['nonocc']
    kept_occ_on, kept_occ_off = np.isfinite(on[occ]).mean(), np.isfinite(off[occ]).mean()
    assert kept_occ_on < 0.8 * kept_occ_off
    vis = sc.masks['nonocc']
    wrong = ~(np.abs(np.nan_to_num(off, nan=-1e3) - sc.gt_px) <= 2.0)
    rejected, kept = np.isfinite(off) & ~np.isfinite(on) & vis, np.isfinite(on) & vis
    assert wrong[rejected].mean() > 4 * wrong[kept].mean()
    s_on, s_off = score(on, sc.gt_px, sc.masks['nonocc']), score(off, sc.gt_px, sc.masks['nonocc'])
    assert s_on['bad2'] < 0.8 * s_off['bad2']
    assert s_on['bad1'] < s_off['bad1']
    assert s_on['density'] > 0.85 * s_off['density']
    # The half-resolution right view (lr_scale 0.5, an eighth of the second SGBM) keeps most of the
    # gain (measured bad-2 0.0271 against 0.0259 full and 0.0343 off).
    half = stereo.match(left, right, StereoParams(lr_check=True, lr_scale=0.5), 0, num).disparity_px
    s_half = score(half, sc.gt_px, sc.masks['nonocc'])
    assert s_half['bad2'] < 0.85 * s_off['bad2']
    assert np.isfinite(half[occ]).mean() < 0.85 * kept_occ_off


def test_right_view_searches_the_found_range():
    # Left disparities between 10 and 30 px in a 0..192 search: the right view searches 10 - margin
    # to 30 + margin, a multiple of 16 wide, inside the searched range; ends of the search do not count.
    raw = np.full((50, 100), 20 * 16, np.int16)
    raw[:, :10] = np.int16(10 * 16)
    raw[:, 10:20] = np.int16(30 * 16)
    raw[:, 20:30] = -16               # invalid
    raw[0, :] = 0                     # the search's lower end: no measurement
    lo, num = stereo._found_range(raw, 0, 192, 1.0)
    assert lo <= 10 - 3 and lo + num >= 30 + 3 and num % 16 == 0 and num <= 48
    assert stereo._found_range(np.full((10, 10), -16, np.int16), 0, 192, 1.0) == (0, 192)


def test_lr_inconsistent_known_shift():
    # Left disparity 5 px everywhere, right disparity 5 px except a stripe at 8 px: left pixel x
    # matches right column x - 5, so left columns 5 + [20, 25) fail, and columns < 5 match outside.
    raw_l = np.full((4, 60), 5 * 16, np.int16)
    raw_r = raw_l.copy()
    raw_r[:, 20:25] = 8 * 16
    raw_l[0, 40] = 5 * 16 + 20          # 6.25 px -> right column round(33.75) = 34, |6.25 - 5| > 1
    raw_l[1, 40] = 5 * 16 + 12          # 5.75 px -> within 1 px
    raw_l[2, 41] = -16                  # invalid on the left
    bad = stereo.lr_inconsistent(raw_l, raw_r, 0, 1.0)
    expect = np.zeros_like(bad)
    expect[:, :5] = True
    expect[:, 25:30] = True
    expect[0, 40] = expect[2, 41] = True
    np.testing.assert_array_equal(bad, expect)
    assert stereo.lr_inconsistent(raw_l, raw_r, 0, 2.0)[:, 25:30].all()
    assert not stereo.lr_inconsistent(raw_l, raw_r, 0, 3.0)[:, 25:30].any()
    assert not stereo.lr_inconsistent(raw_l, raw_r, 0, 2.0)[0, 40]


def _textureless_pair():
    """Rectified pair with a known answer: textured ground at disparity 20 px holding an untextured
    flat strip (same disparity) and a plain raised block (a roof) at disparity 30 px."""
    rng = np.random.default_rng(7)
    H, W, d_ground, d_roof = 200, 320, 20, 30
    world = cv2.GaussianBlur(rng.uniform(0, 255, (H, W + d_roof)).astype(np.float32), (0, 0), 1.2)
    world = cv2.normalize(world, None, 20, 235, cv2.NORM_MINMAX)
    world[40:60, 60:220] = 128.0
    left, right = world[:, :W].copy(), world[:, d_ground:d_ground + W].copy()
    left[110:170, 180:260] = 200.0
    right[110:170, 180 - d_roof:260 - d_roof] = 200.0
    return left.astype(np.uint8), right.astype(np.uint8), d_ground, d_roof


def test_fill_holes_fills_a_plain_strip_and_not_a_plain_roof():
    left, right, d_ground, d_roof = _textureless_pair()
    strip, roof = (slice(42, 58), slice(70, 210)), (slice(110, 170), slice(180, 260))
    D = stereo.match(left, right, StereoParams(min_texture=2.0), 0, 48).disparity_px
    assert np.isfinite(D[strip]).mean() < 0.2          # nothing for SGBM to match on the strip
    holes = ~np.isfinite(D)
    holes[:, :d_roof + 8] = False                      # left of the overlap: no match possible there
    filled = stereo.fill_holes(D, holes, max_dist_px=12.0, max_rms_px=0.2, margin_px=3)
    # The strip (20 px wide, ground on both sides) gets the ground's disparity ...
    assert filled[strip].mean() > 0.8 and np.isfinite(D[strip]).mean() > 0.97
    assert np.mean(np.abs(D[strip] - d_ground) < 0.25) > 0.95
    # ... the roof (60 x 80 px, wider than the fill distance) nothing wrong: what it holds is its own
    # disparity, from the matched outline, never the ground's.
    on_roof = filled[roof]
    assert np.all(np.abs(D[roof][on_roof] - d_roof) < 1.0)
    assert on_roof.mean() < 0.3
    # A fill distance below the strip's half width leaves it unfilled.
    D2 = stereo.match(left, right, StereoParams(min_texture=2.0), 0, 48).disparity_px
    assert not stereo.fill_holes(D2, holes, max_dist_px=6.0, max_rms_px=0.2, margin_px=3)[strip].any()


def test_trusted_fills_drop_a_roof_filled_at_ground_height():
    # The plane of the ground around a plain roof puts the roof at ground height: in disparities a
    # track, in the images a roof edge landing on the ground.
    left, right, d_ground, d_roof = _textureless_pair()
    strip, roof = (slice(40, 60), slice(60, 220)), (slice(110, 170), slice(180, 260))
    d = np.full(left.shape, float(d_ground), np.float32)
    matched = np.ones(left.shape, bool)
    filled = np.zeros(left.shape, bool)
    filled[strip] = filled[roof] = True
    matched[filled] = False
    kept = stereo.trusted_fills(left, right, d, matched, filled)
    assert kept[strip].all()
    assert not kept[roof].any()
    # At its own disparity the roof agrees.
    d[roof] = d_roof
    assert stereo.trusted_fills(left, right, d, matched, filled)[roof].all()


def test_scene_folder_errors(tmp_path):
    with pytest.raises(DataError, match='missing'):
        load_scene(tmp_path)


# --- rectification -------------------------------------------------------------------------------

CAM = PinholeCamera(640, 480, 520.0, 520.26, 320.2, 238.2, (-0.12, 0.05, 0.0005, -0.0003, -0.01))
NADIR = np.column_stack([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])   # image top to north, looking down


def _pose(x, y, z, jitter=(0.0, 0.0, 0.0)):
    return make_T(NADIR @ rot_x(jitter[0]) @ rot_y(jitter[1]) @ rot_z(jitter[2]), [x, y, z])


@pytest.mark.parametrize('offset', [(0.0, 9.0), (12.0, 0.5), (-3.0, -8.0)])
def test_rectified_rows_agree_and_depth_is_recovered(offset):
    Ta = _pose(0.0, 0.0, 40.0, (0.01, -0.02, 0.03))
    Tb = _pose(offset[0], offset[1], 40.5, (-0.015, 0.01, -0.02))
    rect = stereo.rectify_pair(CAM, Ta, Tb, (25.0, 55.0))
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-8, 8, 300) + offset[0] / 2, rng.uniform(-8, 8, 300) + offset[1] / 2,
                           rng.uniform(-10, 8, 300)])
    uv = []
    for T in (Ta, Tb):
        p_cam = (pts - T[:3, 3]) @ T[:3, :3]
        uvi, front = CAM.project(p_cam)
        uv.append(uvi)
    keep = CAM.in_image(uv[0]) & CAM.in_image(uv[1])
    assert keep.sum() > 100
    rl = rect.rectified_pixels(CAM, uv[0][keep], 'left')
    rr = rect.rectified_pixels(CAM, uv[1][keep], 'right')
    assert np.max(np.abs(rl[:, 1] - rr[:, 1])) < 0.5
    # Depth along the rectified axis from the disparity.
    depth = rect.depth_from_disparity(rl[:, 0] - rr[:, 0])
    z_rect = (pts[keep] - Ta[:3, 3]) @ rect.map_R_rect[:, 2]
    np.testing.assert_allclose(depth, z_rect, rtol=1e-6)
    # The remap tables send each rectified pixel back to where the camera saw it (distortion included).
    for side, maps, uv_orig in (('left', rect.maps_left, uv[0][keep]), ('right', rect.maps_right, uv[1][keep])):
        fx, fy = cv2.convertMaps(*maps, cv2.CV_32FC1)
        r = rl if side == 'left' else rr
        inside = (r[:, 0] > 1) & (r[:, 0] < rect.width - 2) & (r[:, 1] > 1) & (r[:, 1] < rect.height - 2)
        u, v = r[inside, 0], r[inside, 1]
        mu = cv2.remap(fx, u.astype(np.float32)[None], v.astype(np.float32)[None], cv2.INTER_LINEAR)[0]
        mv = cv2.remap(fy, u.astype(np.float32)[None], v.astype(np.float32)[None], cv2.INTER_LINEAR)[0]
        err = np.hypot(mu - uv_orig[inside, 0], mv - uv_orig[inside, 1])
        assert np.median(err) < 0.1 and err.max() < 0.5


def test_rectify_rejects_degenerate_pairs():
    Ta = _pose(0, 0, 40)
    with pytest.raises(DataError, match='baseline'):
        stereo.rectify_pair(CAM, Ta, Ta.copy(), (20, 60))


def test_params_validated():
    with pytest.raises(ConfigError, match='odd'):
        from_dict(StereoParams, {'block_size': 4})
    with pytest.raises(ConfigError):
        from_dict(StereoParams, {'mode': 'bm'})


def test_pack_rgb():
    px = np.array([[1, 2, 3], [255, 0, 128]], np.uint8)   # BGR
    assert stereo.pack_rgb(px).tolist() == [0x030201, 0x8000FF]


# --- simulator frames with truth -----------------------------------------------------------------


@pytest.fixture(scope='module')
def sim_pair():
    from helpers.sim_world import rendered, world
    cfg, _, terrain, _, _ = world('tiny')
    frames = [(T, img) for _, T, img in rendered((2.0, 3.75))]   # 8.75 m apart along the first line, B/H 0.22
    return cfg.camera(), terrain, frames, cfg


def test_sim_pair_matches_true_dem(sim_pair):
    cam, terrain, ((Ta, ia), (Tb, ib)), cfg = sim_pair
    gsd = cfg.gsd_m
    assert abs(gsd - GSD_M) < 1e-9
    res = stereo_pair(cam, ia, Ta, ib, Tb, StereoParams(**FULL), depth_range_m=(20.0, 55.0))
    assert res.status == stereo.OK, res.message
    c = res.cloud
    assert c.dtype == CLOUD_DTYPE
    dz = np.abs(c['z'] - terrain.height_at(c['x'], c['y']))
    assert np.median(dz) <= gsd
    assert np.percentile(dz, 90) <= 3 * gsd
    assert c.size > 0.4 * cam.width * cam.height
    assert np.all((c['confidence'] >= 0) & (c['confidence'] <= 1))
    # Colour comes from the image: not all black, not constant.
    assert np.unique(c['rgb'][:1000]).size > 50


def test_sim_pair_reversed_and_downscaled(sim_pair):
    cam, terrain, ((Ta, ia), (Tb, ib)), cfg = sim_pair
    res = stereo_pair(cam, ib, Tb, ia, Ta, from_dict(StereoParams, {'downscale': 0.5}), depth_range_m=(20.0, 55.0))
    assert res.ok, res.message
    dz = np.abs(res.cloud['z'] - terrain.height_at(res.cloud['x'], res.cloud['y']))
    assert np.median(dz) <= 2 * cfg.gsd_m
    assert res.rect.width * res.rect.height < 0.3 * cam.width * cam.height


def test_poor_pairs_are_skipped_with_a_status(sim_pair):
    cam, _, ((Ta, ia), (Tb, ib)), _ = sim_pair
    p = StereoParams()
    assert stereo_pair(cam, ia, Ta, ib, Tb, p, (20, 55), reprojection_rms_px=(0.4, 3.5)).status == stereo.POOR_POSE
    near = Ta.copy()
    near[1, 3] += 0.5
    assert stereo_pair(cam, ia, Ta, ib, near, p, (20, 55)).status == stereo.BAD_BASELINE
    far = Ta.copy()
    far[1, 3] += 25.0   # ahead: B/H 0.67, a third of the 37 m footprint shared
    r = stereo_pair(cam, ia, Ta, ib, far, p, (20, 55))
    assert r.status == stereo.LOW_OVERLAP and r.cloud.size == 0


# --- pair choice ---------------------------------------------------------------------------------


def test_choose_pairs_along_and_across_lines():
    Ta = _pose(0.0, 20.0, 40.0)
    others = {1: _pose(0.0, 11.0, 40.0),     # along the line, B/H 0.23
              2: _pose(0.0, 18.0, 40.0),     # too short a baseline
              3: _pose(15.0, 20.5, 40.0),    # next line, beside
              4: _pose(0.0, -30.0, 40.0)}    # no overlap
    pairs = choose_pairs(CAM, Ta, others, 40.0, PairCriteria())
    keys = {(p.other, p.along) for p in pairs}
    assert keys == {(1, True), (3, False)}
    assert overlap_fraction(CAM, Ta, others[4], 40.0) == 0.0
    assert overlap_fraction(CAM, Ta, others[1], 40.0) == pytest.approx(1 - 9.0 / (480 * GSD_M), abs=0.05)



def test_plan_pairs_searches_the_tie_points_depths_else_the_ground_relief():
    # A nadir pair at 40 m over ground at 0 +- 2 m: with the tie points each pair searches what camera a
    # (the older keyframe) sees, 38-42 m widened by the 4 m margin; without, the ground height +- 20 m.
    from photogram_ros.core import pairs
    rng = np.random.default_rng(4)
    Ta = _pose(0.0, 20.0, 40.0)
    others = {1: _pose(0.0, 11.0, 40.0), 3: _pose(15.0, 20.5, 40.0), 4: _pose(0.0, -30.0, 40.0)}
    ties = np.column_stack([rng.uniform(-40, 60, (20000, 2)), rng.uniform(-2, 2, 20000)])
    crit, limits = PairCriteria(relief_m=20.0, depth_margin_m=4.0), (2.0, 500.0)
    plain = pairs.plan_pairs(CAM, Ta, others, 0.0, crit, limits)
    assert plain.status == pairs.OK and plain.height_m == 40.0
    assert [(q.other, q.along) for q in plain.pairs] == [(c.other, c.along) for c in choose_pairs(CAM, Ta, others,
                                                                                                  40.0, crit)]
    assert {q.other for q in plain.pairs} == {1, 3}
    assert all(q.depth_range_m == (20.0, 60.0) and not q.from_tie_points for q in plain.pairs)
    tied = pairs.plan_pairs(CAM, Ta, others, 0.0, crit, limits, ties)
    assert [q.other for q in tied.pairs] == [q.other for q in plain.pairs]
    for q in tied.pairs:
        lo, hi = q.depth_range_m
        assert q.from_tie_points and 33.8 < lo < 34.2 and 45.8 < hi < 46.2
    off = from_dict(PairCriteria, {'depth_from_sparse_cloud': False, 'relief_m': 20.0, 'depth_margin_m': 4.0})
    assert pairs.plan_pairs(CAM, Ta, others, 0.0, off, limits, ties).pairs == plain.pairs
    # The tie points' depths outside the ground search (a stray cloud 30 m lower): the ground search stays.
    narrow = from_dict(PairCriteria, {'relief_m': 1.0, 'depth_margin_m': 4.0})
    low = pairs.plan_pairs(CAM, Ta, others, 0.0, narrow, limits, ties - [0.0, 0.0, 30.0])
    assert all(q.depth_range_m == (39.0, 41.0) and not q.from_tie_points for q in low.pairs)
    assert all(q.depth_range_m == (20.0, 50.0) for q in pairs.plan_pairs(CAM, Ta, others, 0.0, crit, (2.0, 50.0)).pairs)
    below = pairs.plan_pairs(CAM, Ta, others, 45.0, crit, limits, ties)
    assert below.status == pairs.BELOW_GROUND and not below.pairs

def test_sim_pair_hole_filling_adds_points_on_the_track_and_no_wrong_ones():
    from helpers.sim_world import rendered, world
    cfg, _, terrain, _, _ = world('tiny')
    (_, Ta, ia), (_, Tb, ib) = rendered((10.5, 12.25))     # a plain 3 m track crosses this pair
    base = dict(downscale=0.5, min_texture=2.0, fill_holes_m=0.0, edge_step_m=1.0)
    plain = stereo_pair(cfg.camera(), ia, Ta, ib, Tb, from_dict(StereoParams, base), (20.0, 55.0))
    res = stereo_pair(cfg.camera(), ia, Ta, ib, Tb, from_dict(StereoParams, {**base, 'fill_holes_m': 2.0}),
                      (20.0, 55.0))
    assert plain.ok and res.ok
    dz = lambda c: np.abs(c['z'] - terrain.height_at(c['x'], c['y']))  # noqa: E731
    f = res.cloud['confidence'] == np.float32(StereoParams().fill_confidence)
    # Measured: 5,900 filled points, median |dz| 9.9 cm (the matched ones 15 cm: steep ground here).
    assert f.sum() > 3000
    assert res.cloud.size >= plain.cloud.size + 0.9 * f.sum()
    assert np.median(dz(res.cloud[f])) <= np.median(dz(res.cloud[~f]))
    assert np.percentile(dz(res.cloud[f]), 99) <= 0.5
    assert (dz(res.cloud) > 1.0).sum() <= (dz(plain.cloud) > 1.0).sum()


def test_points_whose_match_leaves_the_right_image_are_dropped(sim_pair):
    # A constant disparity (a plane at 40 m parallel to the rectified images): every point kept must
    # be seen inside image b by the camera model, and without the check some would not be.
    cam, _, ((Ta, ia), (Tb, ib)), _ = sim_pair
    p = StereoParams()
    rect = stereo.rectify_pair(cam, Ta, Tb, (20.0, 55.0))
    left, _ = rect.rectify(ia, ib)
    shape = (rect.height, rect.width)
    d = np.full(shape, float(rect.disparity_from_depth(40.0)), np.float32)
    disp = stereo.Disparity(d, np.zeros(shape, np.float32), np.ones(shape, np.float32), 1.0, 0.0, 0.0)

    def seen_in_b(cloud):
        xyz = np.column_stack([cloud['x'], cloud['y'], cloud['z']])
        uv, front = cam.project((xyz - Tb[:3, 3]) @ Tb[:3, :3])
        return front & cam.in_image(uv, margin_px=-1.0)

    checked = stereo.points_from_disparity(rect, disp, left, p, ib.shape[:2])
    unchecked = stereo.points_from_disparity(rect, disp, left, p, None)
    assert checked.size > 0.3 * cam.width * cam.height
    assert np.all(seen_in_b(checked))
    assert np.mean(seen_in_b(unchecked)) < 0.95
    # Colour is the rectified left pixel's: BGR packed as 0x00RRGGBB.
    assert np.unique(checked['rgb']).size > 100


def test_depth_range_from_the_pairs_tie_points():
    # Ground at 0 +- 2 m under a pair at 40 m, a few points beyond the pair's view: the range is what
    # both cameras see (about 38-42 m deep), widened by the margin, and None without enough points.
    from photogram_ros.core.pairs import depth_range_from_points
    rng = np.random.default_rng(3)
    Ta, Tb = _pose(0.0, 0.0, 40.0), _pose(0.0, 8.0, 40.0)
    xy = rng.uniform(-30, 30, (4000, 2))
    P = np.column_stack([xy, rng.uniform(-2, 2, 4000)])
    far = np.array([[200.0, 0.0, -30.0], [0.0, 300.0, 15.0]])     # outside both images: ignored
    lo, hi = depth_range_from_points(CAM, Ta, Tb, np.vstack([P, far]), margin_m=4.0)
    assert 33.5 < lo < 34.5 and 45.5 < hi < 46.5
    assert depth_range_from_points(CAM, Ta, Tb, P[:10], margin_m=4.0) is None
    assert depth_range_from_points(CAM, Ta, _pose(200.0, 0.0, 40.0), P, margin_m=4.0) is None


def test_a_wide_pair_is_taken_where_no_nearer_keyframe_overlaps():
    """A fixed-wing survey at 60 % forward overlap leaves some keyframes with only a partner two photos away:
    B/H 0.9 here (along the image's long side, 27 % shared), taken after the flight (final criteria) rather
    than leaving the keyframe unpaired; with a nearer partner there, that one is preferred."""
    Ta = _pose(0.0, 0.0, 40.0)
    crit = PairCriteria().for_final()
    wide = choose_pairs(CAM, Ta, {1: _pose(36.0, 0.0, 40.0)}, 40.0, crit)
    assert [p.other for p in wide] == [1] and wide[0].baseline_ratio == pytest.approx(0.9, abs=0.01)
    assert not choose_pairs(CAM, Ta, {1: _pose(36.0, 0.0, 40.0)}, 40.0,
                            dataclasses.replace(crit, max_baseline_ratio=0.8))
    both = choose_pairs(CAM, Ta, {1: _pose(36.0, 0.0, 40.0), 2: _pose(10.0, 0.0, 40.0)}, 40.0,
                        dataclasses.replace(crit, max_pairs_across=1))
    assert [p.other for p in both] == [2]
