"""Dense stereo depth from posed keyframe pairs (no ROS here).

A pair of keyframes with poses `map_T_cam` is rectified with its x axis along the baseline (so a
survey pair displaced along the image y axis is rectified "sideways": the rectified images are the
originals turned by about 90 degrees), matched with OpenCV's StereoSGBM, filtered (left-right
check, uniqueness, speckles, local consistency, texture) and turned into coloured points in `map`.
"""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from photogram_ros.core import gsd
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.pairs import PairLimits, overlap_fraction
from photogram_ros.errors import ConfigError, DataError
from photogram_ros.params import param

# The one cloud layout exchanged between stereo and map: positions in map ENU metres,
# colour packed 0x00RRGGBB as PCL/RViz expect, and a per-point confidence in [0, 1].
CLOUD_DTYPE = np.dtype([
    ("x", np.float64),
    ("y", np.float64),
    ("z", np.float64),
    ("rgb", np.uint32),
    ("confidence", np.float32),
])

SGBM_MODES = {'sgbm': cv2.STEREO_SGBM_MODE_SGBM, 'sgbm_3way': cv2.STEREO_SGBM_MODE_SGBM_3WAY,
              'hh': cv2.STEREO_SGBM_MODE_HH, 'hh4': cv2.STEREO_SGBM_MODE_HH4}

# Result statuses: 'ok' carries a cloud; the others say why the pair was skipped.
OK, POOR_POSE, LOW_OVERLAP, BAD_BASELINE, NO_POINTS = 'ok', 'poor_pose', 'low_overlap', 'bad_baseline', 'no_points'


@dataclass
class StereoParams(PairLimits):
    """The matcher's parameters; the pair limits it checks (overlap, baseline ratio) come from PairLimits."""
    mode: str = param('sgbm_3way', 'StereoSGBM mode; sgbm_3way is about 2x faster than sgbm at equal quality',
                      choices=tuple(SGBM_MODES))
    block_size: int = param(5, 'SGBM matching block size, pixels (odd)', min=1, max=15)
    p1_per_px: int = param(8, 'SGBM smoothness P1 = p1_per_px * block_size^2 (small disparity changes)', min=0, max=64)
    p2_per_px: int = param(32, 'SGBM smoothness P2 = p2_per_px * block_size^2 (disparity jumps); > p1_per_px',
                           min=1, max=256)
    max_num_disparities: int = param(192, 'largest disparity search range, pixels (the depth range is clipped '
                                          'to it)', min=16, max=512)
    uniqueness_ratio: int = param(15, 'SGBM uniqueness: best cost must beat the second best by this percent',
                                  min=0, max=50)
    speckle_window_px: int = param(200, 'largest connected blob of disparities removed as a speckle, pixels',
                                   min=0, max=10000)
    speckle_range_px: float = param(1.0, 'disparity variation allowed within one connected blob, pixels',
                                    min=0.0, max=16.0)
    lr_check: bool = param(True, 'left-right consistency check: a second SGBM on the flipped, swapped pair '
                                 'gives the right view\'s disparity; left pixels whose match disagrees are '
                                 'dropped (occlusions, mismatches). About doubles the SGBM time')
    lr_scale: float = param(1.0, 'resolution of the right view\'s SGBM for the left-right check (0.5: half, '
                                 'an eighth of the work; tolerance widened by a pixel)', min=0.25, max=1.0)
    lr_max_diff_px: float = param(1.0, 'left-right consistency tolerance |dL(x) - dR(x - dL)|, pixels '
                                       '(sub-pixel; used when lr_check is on)', min=0.0, max=16.0)
    pre_filter_cap: int = param(31, 'SGBM prefilter clipping of the x-derivative', min=1, max=63)
    max_local_dev_px: float = param(0.5, 'drop disparities differing from their 3x3 median by more, pixels',
                                    min=0.0, max=100.0)
    min_texture: float = param(0.0, 'drop pixels whose mean absolute gradient in the block is below this, '
                                    'grey levels per pixel', min=0.0, max=100.0)
    fill_holes_m: float = param(gsd.AUTO, 'posed pairs: pixels left without a match (a plain track, a mismatch) up to '
                                     'this far from matched ones, m on the ground, get a disparity interpolated '
                                     'from them where the matched surface around is continuous (no depth step '
                                     'over edge_step_m, so never across a roof edge); 0: off; -1: from the GSD '
                                     '(core/gsd.py: 2 m for the simulator\'s 640x480 at 40 m)', min=gsd.AUTO, max=100.0)
    fill_confidence: float = param(0.35, 'confidence of interpolated (filled) points; the map fuses points from '
                                         'its min_confidence (0.3) up, so a lower value keeps them out of the map',
                                   min=0.0, max=1.0)
    min_confidence: float = param(0.0, 'drop points with a lower confidence (0..1)', min=0.0, max=1.0)
    edge_step_m: float = param(gsd.AUTO, 'depth step (wall, roof edge) around which disparities are dropped, m; '
                                         '0 keeps them; -1: from the GSD (core/gsd.py: 1 m for the simulator\'s)',
                               min=gsd.AUTO, max=1e3)
    edge_margin_px: int = param(3, 'pixels dropped on both sides of such a step (SGBM misplaces the step by '
                                   'up to its block radius)', min=0, max=32)
    min_depth_m: float = param(2.0, 'nearest valid depth, m', min=0.01, max=1e5)
    max_depth_m: float = param(500.0, 'farthest valid depth, m', min=0.1, max=1e6)
    max_grazing_deg: float = param(75.0, 'drop points whose surface is seen at more than this angle from its '
                                         'normal, degrees', min=10.0, max=90.0)
    downscale: float = param(gsd.AUTO, 'scale of the rectified images (0.5 = half resolution, 4x faster); -1: '
                                       'from the image size (core/gsd.py: about 77,000 pixels matched, 0.5 for '
                                       '640x480, 0.25 for 1080p)', min=gsd.AUTO, max=1.0)
    point_stride: int = param(1, 'keep one point in stride x stride pixels', min=1, max=16)
    max_reprojection_rms_px: float = param(2.0, 'skip pairs whose keyframe poses have a larger reprojection RMS, '
                                                'pixels', min=0.0, max=1e3)

    def check(self) -> None:
        if self.block_size % 2 == 0:
            raise ConfigError(f'block_size must be odd (got {self.block_size})')
        if self.p2_per_px <= self.p1_per_px:
            raise ConfigError(f'p2_per_px ({self.p2_per_px}) must be larger than p1_per_px ({self.p1_per_px})')
        if self.max_num_disparities % 16:
            raise ConfigError(f'max_num_disparities must be a multiple of 16 (got {self.max_num_disparities})')
        if self.min_depth_m >= self.max_depth_m:
            raise ConfigError('min_depth_m must be smaller than max_depth_m')
        gsd.check_auto_or_at_least(self, {'downscale': 0.1, 'fill_holes_m': 0.0, 'edge_step_m': 0.0})
        super().check()


# --- matching ------------------------------------------------------------------------------------


def make_sgbm(params: StereoParams, min_disparity: int, num_disparities: int, channels: int = 1,
              filtered: bool = True):
    """StereoSGBM from the parameters; filtered=False gives the bare matcher (no uniqueness, speckle, LR)."""
    bs = params.block_size
    return cv2.StereoSGBM_create(
        minDisparity=int(min_disparity), numDisparities=int(num_disparities), blockSize=bs,
        P1=params.p1_per_px * channels * bs * bs, P2=params.p2_per_px * channels * bs * bs,
        # Off: with OpenCV 5.0.0, disp12MaxDiff -1, 0 and 1 give bit-identical output (teddy, tsukuba,
        # sim pair; SGBM and SGBM_3WAY) and 5 invalidates fewer pixels than -1, so it is no usable
        # left-right check; match() does a real one (lr_check) with a second SGBM on the flipped pair.
        disp12MaxDiff=-1,
        preFilterCap=params.pre_filter_cap,
        uniquenessRatio=params.uniqueness_ratio if filtered else 0,
        speckleWindowSize=params.speckle_window_px if filtered else 0,
        # SGBM's speckle range is in disparity units *16 internally; it takes whole pixels.
        speckleRange=max(1, int(round(params.speckle_range_px))) if filtered else 0,
        mode=SGBM_MODES[params.mode])


def disparity_from_sgbm(raw: np.ndarray, min_disparity: int) -> np.ndarray:
    """SGBM's fixed-point output (1/16 px) -> float32 pixels with NaN where there is no match."""
    d = raw.astype(np.float32) * (1.0 / 16.0)
    d[raw < (min_disparity * 16)] = np.nan
    return d


@dataclass
class Disparity:
    disparity_px: np.ndarray      # float32 (H, W), NaN where rejected
    local_dev_px: np.ndarray      # float32 (H, W): |d - median3x3(d)|
    texture: np.ndarray           # float32 (H, W): mean absolute image gradient over the block
    texture_ref: float            # texture at which the texture cue reaches 1/2
    sgbm_ms: float
    filter_ms: float
    lr_ms: float = 0.0            # the right view's SGBM for the left-right check (not in sgbm_ms)
    filled: np.ndarray | None = None   # bool (H, W): disparities interpolated, not matched (fill_textureless)
    fill_confidence: float = 0.0

    def confidence_at(self, flat_idx: np.ndarray) -> np.ndarray:
        """Confidence in [0, 1] at flat pixel indices (see _filter for the cues)."""
        dev = self.local_dev_px.ravel()[flat_idx]
        tex = self.texture.ravel()[flat_idx]
        c = (np.exp(dev * np.float32(-2.0)) * (tex / (tex + np.float32(self.texture_ref)))).astype(np.float32)
        if self.filled is not None:
            c[self.filled.ravel()[flat_idx]] = np.float32(self.fill_confidence)
        return c

    @property
    def confidence(self) -> np.ndarray:
        """Per-pixel confidence (H, W), 0 where there is no disparity."""
        c = self.confidence_at(np.arange(self.disparity_px.size)).reshape(self.disparity_px.shape)
        c[~np.isfinite(self.disparity_px)] = 0.0
        return c


def match(left_grey: np.ndarray, right_grey: np.ndarray, params: StereoParams, min_disparity: int,
          num_disparities: int, matcher=None) -> Disparity:
    """Filtered sub-pixel disparity of a rectified pair (left pixel u matches right pixel u - d)."""
    if left_grey.shape != right_grey.shape or left_grey.ndim != 2:
        raise DataError(f'rectified images must be single-channel and equal in size, got {left_grey.shape} '
                        f'and {right_grey.shape}')
    if num_disparities % 16 or num_disparities <= 0:
        raise DataError(f'num_disparities must be a positive multiple of 16 (got {num_disparities})')
    sgbm = matcher or make_sgbm(params, min_disparity, num_disparities)
    t0 = time.perf_counter()
    raw = _left_view(sgbm, left_grey, right_grey, min_disparity + num_disparities)
    t_lr = time.perf_counter()
    raw_right = None
    if params.lr_check:
        lo, num = _found_range(raw, min_disparity, num_disparities, params.lr_max_diff_px)
        if params.lr_scale < 1.0:
            raw_right = _right_view_scaled(params, left_grey, right_grey, lo, num)
        else:
            right = sgbm if (lo, num) == (min_disparity, num_disparities) else make_sgbm(params, lo, num)
            raw_right = _right_view(right, left_grey, right_grey, lo + num)
    t1 = time.perf_counter()
    out = _filter(raw, min_disparity, left_grey, params, raw_right)
    out.sgbm_ms, out.lr_ms, out.filter_ms = (t_lr - t0) * 1e3, (t1 - t_lr) * 1e3, (time.perf_counter() - t1) * 1e3
    return out


def _found_range(raw: np.ndarray, min_disparity: int, num_disparities: int, tol_px: float) -> tuple[int, int]:
    """(min, num) disparities for the right view's search: the range the left view found, not the
    range it searched.

    A survey pair's search range covers every height the terrain and buildings could have (often
    192 px); the disparities found span a fraction of it. A right pixel's disparity is a left
    pixel's, so searching only the found range (0.5-99.5 percentiles, widened by the check's
    tolerance) costs that fraction of a second full SGBM; a left pixel outside it fails the check,
    as the outlier it almost always is.
    """
    # Disparities at the ends of the search are no measurement (the cost fell off the range: the
    # padding beside the image, mostly) and would stretch the found range to the searched one.
    valid = raw.ravel()[::4]
    valid = valid[(valid > min_disparity * 16) & (valid < (min_disparity + num_disparities - 1) * 16)]
    if valid.size < 100:
        return min_disparity, num_disparities
    lo_q, hi_q = np.percentile(valid, (0.5, 99.5)) / 16.0
    margin = int(np.ceil(tol_px)) + 2
    lo = max(int(np.floor(lo_q)) - margin, min_disparity)
    num = min(16 * int(np.ceil((np.ceil(hi_q) + margin - lo) / 16)), num_disparities)
    lo = min(lo, min_disparity + num_disparities - num)
    return lo, num


def _left_view(sgbm, left_grey: np.ndarray, right_grey: np.ndarray, max_disparity: int) -> np.ndarray:
    """SGBM fixed-point disparity of the left image over all its columns.

    SGBM computes no disparity for the first min_disparity + num_disparities columns (some of their
    candidate matches would lie left of the right image). With a search range as wide as a survey
    pair's (tall buildings, hilly ground) that band is most of the image, although most of its
    pixels do have their match inside the right image: padding both images on the left gives every
    column a value for the same cost per column. Matches that fall in the padding are rejected later
    (left-right check, and the right-image bounds in points_from_disparity).
    """
    pad = max(int(max_disparity), 0)
    if pad == 0:
        return sgbm.compute(left_grey, right_grey)
    lp, rp = (cv2.copyMakeBorder(im, 0, 0, pad, 0, cv2.BORDER_REPLICATE) for im in (left_grey, right_grey))
    return sgbm.compute(lp, rp)[:, pad:]


def _right_view(sgbm, left_grey: np.ndarray, right_grey: np.ndarray, max_disparity: int) -> np.ndarray:
    """SGBM fixed-point disparity of the right image (right pixel x matches left pixel x + d).

    Mirrored, the right image becomes a left image whose matches lie d columns to the left in the
    mirrored left image, so the same matcher and range apply. SGBM leaves its first max_disparity
    columns without a value; mirrored, those are the right image's last columns, whose left matches
    mostly exist (a survey pair's disparity range is much wider than its disparities): padding both
    mirrored images on that side gives them a value, for (W + max_disparity) / W of the time.
    """
    pad = max(int(max_disparity), 0)
    fr, fl = (cv2.copyMakeBorder(cv2.flip(im, 1), 0, 0, pad, 0, cv2.BORDER_REPLICATE)
              for im in (right_grey, left_grey))
    return cv2.flip(sgbm.compute(fr, fl)[:, pad:], 1)


def _right_view_scaled(params: StereoParams, left_grey: np.ndarray, right_grey: np.ndarray, lo: int,
                       num: int) -> np.ndarray:
    """The right view's disparity from images scaled by lr_scale, back at full size and scale.

    The check is after occlusions and gross mismatches, errors of many pixels, which a coarser
    right view sees as well at a fraction of the cost (a quarter of the pixels and half the
    disparities at half size); invalid pixels stay invalid (very negative).
    """
    H, W = left_grey.shape
    s = params.lr_scale
    size = (max(int(round(W * s)), 16), max(int(round(H * s)), 16))
    ls, rs = (cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in (left_grey, right_grey))
    lo_s = int(np.floor(lo * s))
    num_s = 16 * int(np.ceil((np.ceil((lo + num) * s) - lo_s + 1) / 16))
    raw_s = _right_view(make_sgbm(params, lo_s, num_s), ls, rs, lo_s + num_s).astype(np.int32)
    raw_s = np.where(raw_s >= lo_s * 16, np.round(raw_s / s), -(1 << 20)).astype(np.int32)
    return cv2.resize(raw_s.astype(np.float32), (W, H), interpolation=cv2.INTER_NEAREST).astype(np.int32)


def lr_inconsistent(raw_left: np.ndarray, raw_right: np.ndarray, min_disparity: int, max_diff_px: float) -> np.ndarray:
    """True where left pixel x with disparity d fails |dL(x) - dR(round(x - d))| <= max_diff_px.

    Both inputs are SGBM fixed point (1/16 px), dR indexed by right-image column; a match outside the
    right image or on an invalid right pixel fails.
    """
    H, W = raw_left.shape
    cols = np.arange(W, dtype=np.int32)
    # round(x - d) in 1/16 px: (16 x - raw + 8) >> 4 is floor((16 x - raw + 8) / 16).
    xr = ((cols * 16)[None, :] - raw_left.astype(np.int32) + 8) >> 4
    inside = (xr >= 0) & (xr < W)
    np.clip(xr, 0, W - 1, out=xr)
    dr = np.take_along_axis(raw_right, xr, axis=1).astype(np.int32)
    valid = inside & (dr >= min_disparity * 16) & (raw_left >= min_disparity * 16)
    return ~(valid & (np.abs(raw_left.astype(np.int32) - dr) <= int(round(max_diff_px * 16))))


def _filter(raw: np.ndarray, min_disparity: int, left_grey: np.ndarray, params: StereoParams,
            raw_right: np.ndarray | None = None) -> Disparity:
    """SGBM output -> float disparity with local-consistency (and optional texture/confidence) rejection.

    Two cues SGBM does not expose: agreement with the 3x3 median (isolated mismatches and flying
    pixels at depth edges disagree) and image texture in the block (flat areas are where SGBM
    guesses from the smoothness term alone). Their product is the points' confidence.
    """
    # Invalid pixels hold min_disparity - 1 here: a plausible neighbour value for the median.
    d = raw.astype(np.float32)
    d *= np.float32(1.0 / 16.0)
    dev = cv2.absdiff(d, cv2.medianBlur(d, 3))
    bad = (raw < min_disparity * 16) | (dev > np.float32(params.max_local_dev_px))
    if raw_right is not None:
        tol = params.lr_max_diff_px + (1.0 if params.lr_scale < 1.0 else 0.0)
        bad |= lr_inconsistent(raw, raw_right, min_disparity, tol)
    bs = params.block_size
    g = cv2.add(cv2.convertScaleAbs(cv2.Sobel(left_grey, cv2.CV_16S, 1, 0, ksize=3), alpha=0.125),
                cv2.convertScaleAbs(cv2.Sobel(left_grey, cv2.CV_16S, 0, 1, ksize=3), alpha=0.125))
    tex = cv2.boxFilter(g, cv2.CV_32F, (bs, bs))
    tex_ref = 4.0 * max(params.min_texture, 0.5)
    if params.min_texture > 0:
        bad |= tex < np.float32(params.min_texture)
    out = Disparity(d, dev, tex, tex_ref, 0.0, 0.0)
    if params.min_confidence > 0:
        bad |= out.confidence_at(np.arange(d.size)).reshape(d.shape) < np.float32(params.min_confidence)
    d[bad] = np.nan
    return out


def near_depth_steps(D: np.ndarray, f_baseline: float, step_m: float, margin_px: int) -> np.ndarray:
    """True where a pixel lies within `margin_px` of a depth step larger than `step_m`.

    `D` is the true disparity f * baseline / depth (NaN where none). Block matching places a depth
    step up to a block radius away from where it is (the side with more texture wins the block), so
    the pixels within that margin carry the depth of the other side: far ground drawn into the roof
    outline, or roof heights spilled onto the ground. Measured in depth, not disparity, so a fixed
    step is found whatever the baseline and steep-but-continuous slopes within the margin survive.
    """
    k = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)
    fin = np.isfinite(D)
    near_d = cv2.dilate(np.where(fin, D, np.float32(-np.inf)).astype(np.float32), k)
    far_d = cv2.erode(np.where(fin, D, np.float32(np.inf)).astype(np.float32), k)
    far_d = np.maximum(far_d, np.float32(1e-3))
    fb = np.float32(f_baseline)
    with np.errstate(invalid='ignore', divide='ignore'):
        return fin & (fb / far_d - fb / near_d > np.float32(step_m))


def fill_holes(D: np.ndarray, holes: np.ndarray, max_dist_px: float, max_rms_px: float, margin_px: int,
               min_plane_frac: float = 0.9) -> np.ndarray:
    """Where to interpolate: narrow holes among matched pixels that lie on one plane.

    SGBM has no data term on a plain surface (an untextured track, a plain roof), and its uniqueness
    and left-right tests rightly leave it unmatched. Interpolating such holes from the matched pixels
    around, as SGM pipelines do, is right for a patch of ground bounded by one continuous surface
    and wrong across a roof edge, a wall or an occlusion. `D` is the true disparity
    f * baseline / depth (NaN where unmatched), `holes` the unmatched pixels that could have a match
    (inside the overlap). A connected hole is filled only when it is narrow (every pixel within
    `max_dist_px` of a matched one: a plain roof, and a wall joined to the roof's unmatched
    interior, are wider) and at least `min_plane_frac` of it passes the plane test: a plane in the
    scene is a plane in (u, v, D), so each pixel takes the least-squares plane of the matched pixels
    in a window reaching `margin_px` beyond `max_dist_px` (wide enough to see both sides of a
    misplaced step), when their RMS about it is at most `max_rms_px` and they span both image
    directions. Fills `D` in place and returns the mask of filled pixels.
    """
    valid = np.isfinite(D)
    holes = holes & ~valid
    if max_dist_px < 1 or not holes.any() or not valid.any():
        return np.zeros_like(holes)
    dist = cv2.distanceTransform((~valid).astype(np.uint8), cv2.DIST_L2, 3)
    n, labels = cv2.connectedComponents(holes.astype(np.uint8), connectivity=8)
    # Narrow: no pixel of the hole farther than max_dist_px from a matched one.
    narrow = np.bincount(labels[holes & (dist > np.float32(max_dist_px))], minlength=n) == 0
    narrow[0] = False
    cand = narrow[labels]
    if not cand.any():
        return cand
    H, W = D.shape
    # Window sums of the plane-fit moments over q x q cells, each taken at its centre: the window
    # spans tens of pixels, so pooling loses nothing that matters and leaves a small grid for the
    # window sums (float64: sums of u^2 over a window lose digits in float32; coordinates about the
    # image centre keep them small).
    r_px = int(np.ceil(max_dist_px)) + margin_px + 2
    q = 4 if r_px >= 12 else 2
    rq = max(int(round(r_px / q)), 1)
    hq, wq = H // q, W // q     # the last rows/columns beyond whole cells add nothing to the moments

    def pool(a):
        return a[:hq * q, :wq * q].reshape(hq, q, wq, q).sum(axis=(1, 3), dtype=np.float64)

    d0 = np.where(valid, D, np.float32(0))
    n_c, sd_c, sdd_c = pool(valid.astype(np.float32)), pool(d0), pool(d0 * d0)
    uc = ((np.arange(wq) + 0.5) * q - 0.5 - W / 2)[None, :]
    vc = ((np.arange(hq) + 0.5) * q - 0.5 - H / 2)[:, None]

    def win(a):
        return cv2.boxFilter(np.ascontiguousarray(a, np.float64), cv2.CV_64F, (2 * rq + 1, 2 * rq + 1),
                             normalize=False, borderType=cv2.BORDER_CONSTANT)

    # The fit of every cell's window, on the small grid; candidates then read their cell's.
    cnt, su, sv, sd = win(n_c), win(uc * n_c), win(vc * n_c), win(sd_c)
    suu, suv, svv = win(uc * uc * n_c), win(uc * vc * n_c), win(vc * vc * n_c)
    sud, svd, sdd = win(uc * sd_c), win(vc * sd_c), win(sdd_c)
    with np.errstate(divide='ignore', invalid='ignore'):
        mu, mv, md = su / cnt, sv / cnt, sd / cnt
        cuu, cuv, cvv = suu - su * mu, suv - su * mv, svv - sv * mv
        cud, cvd, cdd = sud - su * md, svd - sv * md, sdd - sd * md
        det = cuu * cvv - cuv * cuv
        a = (cud * cvv - cvd * cuv) / det
        b = (cvd * cuu - cud * cuv) / det
        rms = np.sqrt(np.maximum(cdd - a * cud - b * cvd, 0.0) / cnt)
        # Spread in both directions: a matched line (a roof ridge alone) fixes no plane.
        spread = np.sqrt(np.maximum(np.minimum(cuu, cvv) / cnt, 0.0))
    r = q * rq + q // 2     # the window's half width in pixels
    good = ((cnt >= 0.1 * (2 * r + 1) ** 2) & (rms <= max_rms_px) & (spread >= 0.2 * r)
            & np.isfinite(a) & np.isfinite(b))   # (a + b would warn on inf - inf)
    jj, ii = np.nonzero(cand)
    cj, ci = np.minimum(jj // q, hq - 1), np.minimum(ii // q, wq - 1)
    ok = good[cj, ci]
    lab = labels[jj, ii]
    share = np.bincount(lab[ok], minlength=n) / np.maximum(np.bincount(lab, minlength=n), 1)
    ok &= share[lab] >= min_plane_frac
    jj, ii, cj, ci = jj[ok], ii[ok], cj[ok], ci[ok]
    D[jj, ii] = (md[cj, ci] + a[cj, ci] * (ii - W / 2 - mu[cj, ci])
                 + b[cj, ci] * (jj - H / 2 - mv[cj, ci])).astype(np.float32)
    out = np.zeros_like(cand)
    out[jj, ii] = True
    return out


def beside_wide_holes(valid: np.ndarray, holes: np.ndarray, max_dist_px: float, margin_px: int) -> np.ndarray:
    """Valid pixels within `margin_px` of a wide hole (one with a pixel farther than `max_dist_px`
    from every valid pixel).

    Around a plain roof SGBM has no roof disparity to set against the ground's, so no depth step is
    seen there, yet the block matcher draws the ground a block radius into the roof outline as it
    does at every step: the matched ring around an unexplained wide hole is as suspect as the
    margin of a step.
    """
    holes = holes & ~valid
    if not holes.any() or margin_px <= 0:
        return np.zeros_like(valid)
    dist = cv2.distanceTransform((~valid).astype(np.uint8), cv2.DIST_L2, 3)
    n, labels = cv2.connectedComponents(holes.astype(np.uint8), connectivity=8)
    wide = np.bincount(labels[holes & (dist > np.float32(max_dist_px))], minlength=n) > 0
    wide[0] = False
    near = cv2.dilate(wide[labels].astype(np.uint8), np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8))
    return valid & (near > 0)


def trusted_fills(left_grey: np.ndarray, right_grey: np.ndarray, d_px: np.ndarray, matched: np.ndarray,
                  filled: np.ndarray, max_fail_frac: float = 0.1) -> np.ndarray:
    """The filled pixels whose connected region the two images confirm (rectified grey pair, disparity
    `d_px` holding matched and filled values).

    A plain roof filled at ground height looks, in disparities, like a plain track (when the roof's
    rim matched nowhere, its hole can be as narrow as a track's). In the images it does not: at the
    wrong disparity the roof's edge lands on the ground in the right image, a band of pixels whose
    grey values disagree by the roof-to-ground contrast, while a correctly filled track agrees to
    the noise. A region fails when more than `max_fail_frac` of its pixels differ from their match
    by more than twice the 90th percentile of the matched pixels' differences.
    """
    H, W = d_px.shape

    def diffs(idx):
        col = (idx % W).astype(np.int32)
        col_r = col - np.floor(d_px.ravel()[idx] + np.float32(0.5)).astype(np.int32)
        ok = (col_r >= 0) & (col_r < W)
        idx, col_r = idx[ok], col_r[ok]
        return idx, np.abs(left_grey.ravel()[idx].astype(np.int16) - right_grey[idx // W, col_r].astype(np.int16))

    _, dm = diffs(np.flatnonzero(matched)[::7])
    if dm.size == 0 or not filled.any():
        return np.zeros_like(filled)
    tol = max(2.0 * float(np.percentile(dm, 90)), 6.0)
    n, labels = cv2.connectedComponents(filled.astype(np.uint8), connectivity=8)
    lab = labels.ravel()
    idx, df = diffs(np.flatnonzero(filled))
    bad = np.bincount(lab[idx[df > tol]], minlength=n) > max_fail_frac * np.bincount(lab, minlength=n)
    bad[0] = True
    return (~bad[lab]).reshape(H, W)


# --- rectification -------------------------------------------------------------------------------


@dataclass
class Rectification:
    """A posed pair turned into a standard rectified pair.

    Rectified frame: x along the baseline from camera a (left) to camera b (right), z the mean
    optical axis made orthogonal to x. Both rectified cameras share f, cy and orientation; the right
    principal point is shifted right by `shift_px` so that disparities start near 0:
    depth = f * baseline / (d + shift_px).
    """
    f_px: float
    cx_left: float
    cx_right: float
    cy: float
    width: int
    height: int
    baseline_m: float
    map_R_rect: np.ndarray
    centre_left_map: np.ndarray
    maps_left: tuple
    maps_right: tuple
    rect_R_cam_left: np.ndarray
    rect_R_cam_right: np.ndarray

    @property
    def shift_px(self) -> float:
        return self.cx_right - self.cx_left

    def depth_from_disparity(self, d_px):
        return self.f_px * self.baseline_m / (np.asarray(d_px) + self.shift_px)

    def disparity_from_depth(self, depth_m):
        return self.f_px * self.baseline_m / np.asarray(depth_m) - self.shift_px

    def rectify(self, image_left: np.ndarray, image_right: np.ndarray):
        left = cv2.remap(image_left, *self.maps_left, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        right = cv2.remap(image_right, *self.maps_right, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return left, right

    def rectified_pixels(self, camera: PinholeCamera, uv: np.ndarray, side: str = 'left') -> np.ndarray:
        """Original (distorted) pixels of one camera -> their rectified pixels."""
        rays = camera.unproject(np.asarray(uv, float))
        R = self.rect_R_cam_left if side == 'left' else self.rect_R_cam_right
        return self.rect_to_pixel(rays @ R.T, 'left') + (
            np.array([self.shift_px, 0.0]) if side == 'right' else 0.0)

    def rect_to_pixel(self, xyz_rect: np.ndarray, side: str = 'left') -> np.ndarray:
        """Points in the left rectified camera frame -> rectified pixels (u, v) in the left or right image."""
        p = np.asarray(xyz_rect, float)
        if side == 'right':
            p = p - np.array([self.baseline_m, 0.0, 0.0])
        cx = self.cx_left if side == 'left' else self.cx_right
        return np.stack([self.f_px * p[..., 0] / p[..., 2] + cx, self.f_px * p[..., 1] / p[..., 2] + self.cy], -1)


def _edge_pixels(camera: PinholeCamera, n: int = 24) -> np.ndarray:
    w, h = camera.width - 1.0, camera.height - 1.0
    t = np.linspace(0.0, 1.0, n)
    return np.concatenate([np.stack([t * w, 0 * t], -1), np.stack([t * w, 0 * t + h], -1),
                           np.stack([0 * t, t * h], -1), np.stack([0 * t + w, t * h], -1)])


@functools.lru_cache(maxsize=8)
def _edge_rays(camera: PinholeCamera) -> np.ndarray:
    """Unit rays of the image border; cached because the Newton undistortion costs a millisecond per pair."""
    rays = camera.unproject(_edge_pixels(camera))
    rays.setflags(write=False)
    return rays


def rect_frame(map_T_cam_a: np.ndarray, map_T_cam_b: np.ndarray) -> tuple[np.ndarray, float]:
    """map_R_rect (columns: rectified x, y, z in map) and the baseline length, m."""
    ca, cb = map_T_cam_a[:3, 3], map_T_cam_b[:3, 3]
    base = cb - ca
    baseline = float(np.linalg.norm(base))
    if not baseline > 1e-6:
        raise DataError('the two keyframes of a stereo pair are at the same position: no baseline')
    x = base / baseline
    z = map_T_cam_a[:3, 2] + map_T_cam_b[:3, 2]
    z = z - (z @ x) * x
    if np.linalg.norm(z) < 1e-6:
        raise DataError('stereo pair looks along its own baseline: cannot rectify (forward motion)')
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    return np.column_stack([x, y, z]), baseline


def rectify_pair(camera: PinholeCamera, map_T_cam_a: np.ndarray, map_T_cam_b: np.ndarray,
                 depth_range_m: tuple[float, float], downscale: float = 1.0,
                 max_pixels: int = 4_000_000) -> Rectification:
    """Rectification of camera a (left) and camera b (right) for scene depths within `depth_range_m`.

    Equivalent to cv2.stereoRectify for this pose, but chooses the rectified x axis along the
    baseline whatever the image axes are, and frames the right image so that the expected
    disparity range starts near 0 (SGBM then wastes no columns on impossible disparities).
    """
    map_R_rect, baseline = rect_frame(map_T_cam_a, map_T_cam_b)
    rect_R_cam = [map_R_rect.T @ T[:3, :3] for T in (map_T_cam_a, map_T_cam_b)]
    f = 0.5 * (camera.fx + camera.fy) * downscale
    rays = _edge_rays(camera)
    boxes = []
    for R in rect_R_cam:
        p = rays @ R.T
        if np.any(p[:, 2] <= 0.05):
            raise DataError('stereo pair cameras are rotated too far apart to rectify (> ~85 degrees)')
        uv = f * p[:, :2] / p[:, 2:3]
        boxes.append((uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()))
    (u0a, u1a, v0a, v1a), (u0b, u1b, v0b, v1b) = boxes
    v0, v1 = max(v0a, v0b), min(v1a, v1b)
    if v1 - v0 < 16:
        raise DataError('stereo pair images share no rows after rectification')
    width = int(np.ceil(u1a - u0a)) + 1
    height = int(np.ceil(v1 - v0)) + 1
    if width * height > max_pixels:
        raise DataError(f'rectified image would be {width}x{height}: the pair is too oblique')
    # Shift the right window by the smallest expected disparity (far depth).
    d_far = f * baseline / max(depth_range_m[1], 1e-6)
    cx_l, cy = -u0a, -v0
    cx_r = cx_l + np.floor(d_far)
    K_new_l = np.array([[f, 0, cx_l], [0, f, cy], [0, 0, 1.0]])
    K_new_r = np.array([[f, 0, cx_r], [0, f, cy], [0, 0, 1.0]])
    maps = []
    for R, K_new in zip(rect_R_cam, (K_new_l, K_new_r)):
        m1, m2 = cv2.initUndistortRectifyMap(camera.K, camera.dist_array, R, K_new, (width, height),
                                             cv2.CV_16SC2)
        maps.append((m1, m2))
    return Rectification(float(f), float(cx_l), float(cx_r), float(cy), width, height, baseline, map_R_rect,
                         map_T_cam_a[:3, 3].copy(), maps[0], maps[1], rect_R_cam[0], rect_R_cam[1])


# --- points --------------------------------------------------------------------------------------


def pack_rgb(bgr: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 BGR -> uint32 0x00RRGGBB."""
    b = bgr[..., 0].astype(np.uint32)
    g = bgr[..., 1].astype(np.uint32)
    r = bgr[..., 2].astype(np.uint32)
    return (r << 16) | (g << 8) | b


def _map_source(maps: tuple, flat_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Source image (col, row), integer parts, of rectified flat pixels under CV_16SC2 remap maps.

    m1 holds the integer part of the source position as two int16; one int32 gather reads both.
    """
    xy = maps[0].view(np.int32).ravel()[flat_idx].view(np.int16).reshape(-1, 2)
    return xy[:, 0], xy[:, 1]


def match_inside_right(rect: Rectification, idx: np.ndarray, col: np.ndarray, d_px: np.ndarray, width: int,
                       right_shape: tuple) -> np.ndarray:
    """True where left pixels (flat `idx`, column `col`, disparity `d_px`) match inside the right image.

    The match is the right rectified pixel on the same row, round(d) columns to the left; it is real
    where the right map points inside the right image (elsewhere the remap drew its constant border,
    or the padding of _left_view supplied the match).
    """
    col_r = col - np.floor(d_px + np.float32(0.5)).astype(np.int32)
    ok = (col_r >= 0) & (col_r < width)
    u, v = _map_source(rect.maps_right, np.where(ok, idx - col + col_r, 0))
    # As unsigned, negative positions are large: one comparison per bound.
    ok &= (u.view(np.uint16) < right_shape[1]) & (v.view(np.uint16) < right_shape[0])
    return ok


def points_from_disparity(rect: Rectification, disp: Disparity, left_rect: np.ndarray, params: StereoParams,
                          right_shape: tuple | None = None) -> np.ndarray:
    """Rectified disparity -> cloud (CLOUD_DTYPE) in map, dropping depths out of range and grazing views.

    `left_rect` is the rectified left image (BGR or mono), read at the kept pixels for colour; reading
    the original image through the map instead is slower after SGBM: a rectified row runs down a
    source column when the pair is rectified sideways, one cache miss per point. With `right_shape`
    (the right image's (H, W)), points whose match falls outside the right image (remap border) are
    dropped.

    The grazing test needs no 3D normals: for a plane, the true disparity D = d + shift is affine
    in (u, v), and with g = grad D the plane normal is n ~ (gx, gy, D/f - gx x - gy y) while
    n . ray_left = D/f and n . ray_right = (D/f)(1 - gx), with x, y normalised rectified coordinates.
    Tests run on contiguous float32 views of the image interior (x, y broadcast as a row and a
    column; NaN fails every comparison); only the kept points are then gathered: most pixels are
    candidates, and a gather costs several times a contiguous pass.
    """
    d = disp.disparity_px
    H, W = d.shape
    k = 2   # central differences over 2k pixels: single-pixel steps are too noisy at 1/16 px
    inv_f = np.float32(1.0 / rect.f_px)
    shift = np.float32(rect.shift_px)
    x = ((np.arange(W, dtype=np.float32) - np.float32(rect.cx_left)) * inv_f)
    y = ((np.arange(H, dtype=np.float32) - np.float32(rect.cy)) * inv_f)
    xi, yi = x[k:W - k], y[k:H - k, None]
    di = d[k:H - k, k:W - k]
    a = di + shift
    a *= inv_f                                  # D / f = n . ray_left
    # Central differences of d (= of D), scaled to per-pixel steps.
    half = np.float32(0.5 / k)
    gx = d[k:H - k, 2 * k:] - d[k:H - k, :W - 2 * k]
    gx *= half
    gy = d[2 * k:, k:W - k] - d[:H - 2 * k, k:W - k]
    gy *= half
    c2 = np.float32(np.cos(np.radians(params.max_grazing_deg)) ** 2)
    nz = a - gx * xi - gy * yi
    nn2 = gx * gx
    nn2 += gy * gy
    nn2 += nz * nz
    nn2 *= c2
    y2p1 = yi * yi + np.float32(1.0)
    a2 = a * a
    # cos^2 >= c^2 without square roots: (n.r)^2 >= c^2 |n|^2 |r|^2 for both rays.
    keep_i = a2 >= nn2 * (xi * xi + y2p1)
    xr = xi - a
    xr *= xr
    xr += y2p1
    xr *= nn2
    g1 = np.float32(1.0) - gx
    g1 *= g1
    g1 *= a2
    keep_i &= g1 >= xr
    # Depth range as a disparity range: no division on the full image.
    fb = np.float32(rect.f_px * rect.baseline_m)
    keep_i &= di >= fb / np.float32(params.max_depth_m) - shift
    keep_i &= di <= fb / np.float32(params.min_depth_m) - shift
    keep = np.zeros((H, W), bool)
    keep[k:H - k, k:W - k] = keep_i
    s = params.point_stride
    if s > 1:
        grid = np.zeros_like(keep)
        grid[s // 2::s, s // 2::s] = True
        keep &= grid
    idx = np.flatnonzero(keep)
    dv = d.ravel()[idx]
    row, col = np.divmod(idx.astype(np.int32), np.int32(W))
    if right_shape is not None:
        ok = match_inside_right(rect, idx, col, dv, W, right_shape)
        idx, dv, row, col = idx[ok], dv[ok], row[ok], col[ok]
    depth = fb / (dv + shift)
    xv, yv = x[col], y[row]
    out = np.empty(idx.size, CLOUD_DTYPE)
    R, C = rect.map_R_rect, rect.centre_left_map
    # Per axis, ray direction in map times depth: a (N, 3) @ (3, 3) matmul goes through BLAS
    # threads and is ~30x slower here. float32 until the write into the float64 field.
    ray = np.empty_like(xv)
    for i, name in enumerate(('x', 'y', 'z')):
        np.multiply(xv, np.float32(R[i, 0]), out=ray)
        ray += np.float32(R[i, 1]) * yv
        ray += np.float32(R[i, 2])
        ray *= depth
        field_ = out[name]
        field_[:] = ray
        field_ += C[i]
    if left_rect.ndim == 2:
        grey = left_rect.ravel()[idx].astype(np.uint32)
        out['rgb'] = (grey << 16) | (grey << 8) | grey
    else:
        # take along axis 0 copies whole pixels: about half the cost of fancy indexing here.
        out['rgb'] = pack_rgb(np.take(left_rect.reshape(-1, left_rect.shape[2]), idx, axis=0))
    out['confidence'] = disp.confidence_at(idx)
    return out


def _fill(disp: Disparity, D: np.ndarray, rect: Rectification, left_g: np.ndarray, right_g: np.ndarray,
          shape_a: tuple, shape_b: tuple, params: StereoParams) -> np.ndarray:
    """fill_holes + trusted_fills on a pair's disparity (in place); returns the new true disparity."""
    shift = np.float32(rect.shift_px)
    W = D.shape[1]

    def matchable(idx, d):
        """Inside image a (not the remap's constant border) with a match inside image b."""
        u, v = _map_source(rect.maps_left, idx)
        return ((u.view(np.uint16) < shape_a[1]) & (v.view(np.uint16) < shape_a[0])
                & match_inside_right(rect, idx, (idx % W).astype(np.int32), d, W, shape_b))

    # Matches into the right image's border or padding are no evidence of any surface.
    idx = np.flatnonzero(np.isfinite(D))
    gone = idx[~matchable(idx, disp.disparity_px.ravel()[idx])]
    disp.disparity_px.ravel()[gone] = np.nan
    D.ravel()[gone] = np.nan
    matched = np.isfinite(D)
    if not matched.any():
        return D
    fb = rect.f_px * rect.baseline_m
    depth_m = float(fb / np.median(D[matched]))
    # Holes are the unmatched pixels inside the overlap (at the pair's median disparity): the rest
    # could not have matched, and joined to a hole they would make every hole at the overlap's edge wide.
    idx = np.flatnonzero(~matched)
    holes = np.zeros(D.size, bool)
    holes[idx[matchable(idx, np.full(idx.size, fb / depth_m - shift, np.float32))]] = True
    # The plane must hold to a quarter of a step (as disparity at the pair's depth).
    filled = fill_holes(D, holes.reshape(D.shape), params.fill_holes_m * rect.f_px / depth_m,
                        0.25 * max(params.edge_step_m, 1e-3) * fb / depth_m ** 2, params.edge_margin_px)
    idx = np.flatnonzero(filled)
    d_fill = D.ravel()[idx] - shift
    ok = matchable(idx, d_fill)
    filled.ravel()[idx[~ok]] = False
    disp.disparity_px.ravel()[idx[ok]] = d_fill[ok]
    filled &= trusted_fills(left_g, right_g, disp.disparity_px, matched, filled)
    disp.disparity_px[~matched & ~filled] = np.nan
    valid = matched | filled
    disp.disparity_px[beside_wide_holes(valid, holes.reshape(D.shape), params.fill_holes_m * rect.f_px / depth_m,
                                        params.edge_margin_px)] = np.nan
    filled &= np.isfinite(disp.disparity_px)
    disp.filled, disp.fill_confidence = filled, params.fill_confidence
    return disp.disparity_px + shift


# --- a posed pair end to end ---------------------------------------------------------------------


@dataclass
class StereoResult:
    status: str
    message: str = ''
    cloud: np.ndarray = field(default_factory=lambda: np.empty(0, CLOUD_DTYPE))
    disparity: Disparity | None = None
    rect: Rectification | None = None
    min_disparity: int = 0
    num_disparities: int = 0
    timings_ms: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == OK


def _grey(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img


def stereo_pair(camera: PinholeCamera, image_a: np.ndarray, map_T_cam_a: np.ndarray, image_b: np.ndarray,
                map_T_cam_b: np.ndarray, params: StereoParams, depth_range_m: tuple[float, float] | None = None,
                reprojection_rms_px: tuple | None = None) -> StereoResult:
    """Dense cloud of the scene seen by keyframes a and b (images BGR or mono, poses optical -> map).

    `depth_range_m` bounds the disparity search (e.g. height above ground +- relief); the parameter
    depth range is used when it is None. Poor or unsuitable pairs come back with a skip status.
    """
    t0 = time.perf_counter()
    for img in (image_a, image_b):
        if img is None or img.ndim not in (2, 3) or img.dtype != np.uint8:
            raise DataError('stereo images must be uint8 mono or BGR arrays')
        camera.check_image_size(img.shape[1], img.shape[0])
    lo = params.min_depth_m if depth_range_m is None else max(params.min_depth_m, float(depth_range_m[0]))
    hi = params.max_depth_m if depth_range_m is None else min(params.max_depth_m, float(depth_range_m[1]))
    if not hi > lo:
        raise DataError(f'depth range {depth_range_m} lies outside the valid depths '
                        f'[{params.min_depth_m}, {params.max_depth_m}] m')
    if reprojection_rms_px is not None:
        worst = max(float(r) for r in reprojection_rms_px if r is not None) if any(
            r is not None for r in reprojection_rms_px) else 0.0
        if worst > params.max_reprojection_rms_px:
            return StereoResult(POOR_POSE, f'keyframe reprojection RMS {worst:.2f} px > '
                                           f'{params.max_reprojection_rms_px} px')
    mid = 0.5 * (lo + hi)
    if gsd.unresolved(params):   # lengths left to the GSD: this pair's (the middle of its depth search)
        params, _ = gsd.resolve(params, gsd.derive(camera.width, camera.height, camera.fx, mid))
    baseline = float(np.linalg.norm(map_T_cam_b[:3, 3] - map_T_cam_a[:3, 3]))
    ratio = baseline / mid
    if not params.min_baseline_ratio <= ratio <= params.max_baseline_ratio:
        return StereoResult(BAD_BASELINE, f'baseline/depth {ratio:.3f} outside '
                                          f'[{params.min_baseline_ratio}, {params.max_baseline_ratio}]')
    # A 16x16 grid resolves the overlap to ~1/16 of the image, plenty for a skip threshold, at a
    # quarter of the default grid's undistortion cost (a millisecond per pair).
    overlap = overlap_fraction(camera, map_T_cam_a, map_T_cam_b, mid, n=16)
    if overlap < params.min_overlap:
        return StereoResult(LOW_OVERLAP, f'overlap {overlap:.2f} < {params.min_overlap}')
    rect = rectify_pair(camera, map_T_cam_a, map_T_cam_b, (lo, hi), params.downscale)
    t1 = time.perf_counter()
    left = cv2.remap(image_a, *rect.maps_left, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    left_g = _grey(left)
    right_g = cv2.remap(_grey(image_b), *rect.maps_right, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    d_min = int(np.floor(rect.disparity_from_depth(hi)))
    d_max = int(np.ceil(rect.disparity_from_depth(lo)))
    num = int(min(params.max_num_disparities, 16 * int(np.ceil(max(d_max - d_min + 1, 16) / 16))))
    t2 = time.perf_counter()
    disp = match(left_g, right_g, params, d_min, num)
    t_e = time.perf_counter()
    fb = rect.f_px * rect.baseline_m
    D = disp.disparity_px + np.float32(rect.shift_px)
    if params.fill_holes_m > 0:
        # Before the step filter, which would blank the matched pixels on both sides of a step.
        D = _fill(disp, D, rect, left_g, right_g, image_a.shape[:2], image_b.shape[:2], params)
    if params.edge_step_m > 0 and params.edge_margin_px > 0:
        disp.disparity_px[near_depth_steps(D, fb, params.edge_step_m, params.edge_margin_px)] = np.nan
    disp.filter_ms += (time.perf_counter() - t_e) * 1e3
    t3 = time.perf_counter()
    cloud = points_from_disparity(rect, disp, left, params, image_b.shape[:2])
    t4 = time.perf_counter()
    timings = {'rectify_ms': (t2 - t0) * 1e3, 'sgbm_ms': disp.sgbm_ms, 'lr_ms': disp.lr_ms,
               'filter_ms': disp.filter_ms,
               'points_ms': (t4 - t3) * 1e3, 'total_ms': (t4 - t0) * 1e3, 'maps_ms': (t1 - t0) * 1e3}
    status = OK if cloud.size else NO_POINTS
    return StereoResult(status, f'{cloud.size} points, overlap {overlap:.2f}, B/H {ratio:.3f}', cloud, disp, rect,
                        d_min, num, timings)
