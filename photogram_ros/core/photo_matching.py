"""Tie points for a folder of survey photos: SIFT features, verified matches, tracks.

What it produces: per photo its features (`PhotoFeatures`: positions in full-photo pixels, RootSIFT
descriptors), per candidate pair the verified matches with the count of every stage (`PairMatch`:
features, ratio-test matches, RANSAC inliers, and a status naming the stage that failed), and the
tracks: one id per feature, chained through every photo that saw it (`build_tracks`).

Resolution. Survey photos of 12-20 MP hold detail (leaves, grass blades, sand, ripples) that does not
look the same from two stations 15 m apart: SIFT on a full 4000 px DJI frame keeps its 3000 strongest
features there and matched 20-40 of them between neighbours of a real survey, 5-10 surviving
verification. Features are detected on the photo reduced to `max_image_px` on its long side (the
caller decodes it so; `reduced_size`), SIFT's own scale pyramid covering the coarser scales, as many
as `features_per_mpx` of the reduced photo allows (up to `max_features`), and mapped back to
full-photo pixels (`to_full_px`): on the same survey 100-700 matches per pair.

Matching: FLANN kd-tree two nearest neighbours (OpenCV), Lowe's ratio test, one match per feature of
the second photo (the closest), then an essential matrix by RANSAC with the camera (normalised
coordinates, threshold in reduced-image pixels: the features' own accuracy). A pair needs
`min_inliers` inliers and `min_inlier_ratio` of its ratio-test matches: repeated texture (rows of
trees, parked cars) can give consistent but wrong matches, never a large share of them.

Candidate pairs (`candidate_order`, `candidate_pairs`): each photo with its `neighbours` nearest
photos by position and every photo closer than that plus the geotags' uncertainty (a consumer GNSS:
a few metres), or, when heading and height above ground are known (a DJI XMP has both), with the
photos whose ground footprints overlap it most; `more_candidates` widens the search for photos left
with too few verified pairs.

Tracks: union-find over (photo, feature); a track that would hold two features of one photo is
dropped (an ambiguous chain).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.two_view import essential_ransac
from photogram_ros.params import param


@dataclass
class MatchingOptions:
    """Features and matching of survey photos (`triangulate PHOTOS`)."""
    max_image_px: int = param(1000, 'long side of the reduced photo that features are detected on, px (a 4000 px '
                                    'frame is reduced 4x; smaller photos are used as they are)', min=200, max=20000)
    max_features: int = param(4000, 'SIFT features kept per photo (the strongest), at most', min=100, max=100000)
    features_per_mpx: float = param(7000.0, 'SIFT features kept per megapixel of the reduced photo (up to '
                                            'max_features: 4000 on a 1000 x 563 DJI frame, 2150 on 640 x 480)',
                                    min=100.0, max=1e6)
    contrast_threshold: float = param(0.02, 'SIFT contrast threshold (lower keeps features in faint texture: '
                                            'grass, sand, water)', min=0.001, max=0.2)
    ratio: float = param(0.8, 'Lowe ratio test: best match distance below this share of the second best',
                         min=0.3, max=1.0)
    ransac_px: float = param(1.0, 'essential-matrix RANSAC threshold in reduced-image pixels', min=0.1, max=20.0)
    ransac_method: str = param('ransac', 'essential-matrix estimator: OpenCV RANSAC, or USAC (as many inliers, '
                                         'several times faster at low inlier ratios; the in-flight tracker uses it)',
                               choices=('ransac', 'usac'))
    min_inliers: int = param(15, 'a pair is verified with at least this many RANSAC inliers', min=6, max=10000)
    min_inlier_ratio: float = param(0.15, 'and at least this share of its ratio-test matches', min=0.0, max=1.0)
    neighbours: int = param(8, 'candidate pairs of each photo: its nearest photos by position (or largest '
                               'footprint overlap when heading and height are known)', min=1, max=1000)
    min_pairs: int = param(3, 'a photo with fewer verified pairs is matched with its next candidates',
                           min=0, max=100)
    max_extra: int = param(8, 'at most this many extra candidates per photo when widening', min=0, max=1000)


@dataclass
class PhotoFeatures:
    name: str
    uv: np.ndarray          # (K, 2) full-photo pixels
    desc: np.ndarray        # (K, 128) float32, RootSIFT
    response: np.ndarray | None = None   # (K,) SIFT response (strength) of each feature, when known


@dataclass
class PairMatch:
    """One candidate pair after matching: the counts of every stage and the verified matches."""
    i: int
    j: int
    features: tuple         # (len a, len b)
    ratio_matches: int      # after the ratio test and the one-to-one filter
    inliers: int            # RANSAC inliers (0 when RANSAC did not run or found nothing)
    matches: np.ndarray     # (M, 2) feature indices i -> j; empty unless verified
    status: str             # 'verified' | 'too_few_features' | 'too_few_matches' | 'no_geometry' | 'too_few_inliers'

    @property
    def verified(self) -> bool:
        return self.status == 'verified'


def reduced_size(width: int, height: int, max_image_px: int) -> tuple[int, int, int]:
    """(reduce, width_px, height_px): the power-of-two decode reduction (1, 2, 4 or 8, as libjpeg
    decodes directly) and the size features are detected at (long side <= max_image_px, never enlarged)."""
    long_side = max(width, height)
    r = 1
    while r < 8 and -(-long_side // (2 * r)) >= max_image_px:
        r *= 2
    w, h = -(-width // r), -(-height // r)
    s = min(1.0, max_image_px / max(w, h))
    return r, max(1, int(round(w * s))), max(1, int(round(h * s)))


def to_full_px(uv_work: np.ndarray, factor_xy) -> np.ndarray:
    """Reduced-image pixels -> full-photo pixels (pixel centres at integers in both; `factor_xy`:
    full pixels per reduced pixel along x and y)."""
    f = np.asarray(factor_xy, float).reshape(1, 2)
    return (np.asarray(uv_work, float).reshape(-1, 2) + 0.5) * f - 0.5


def extract(name: str, gray: np.ndarray, factor_xy=(1.0, 1.0), opt: MatchingOptions | None = None) -> PhotoFeatures:
    """SIFT features of one (reduced) grey photo; positions in full-photo pixels, RootSIFT descriptors
    (Arandjelovic & Zisserman 2012: L1-normalised, square-rooted; matched with L2)."""
    opt = opt or MatchingOptions()
    if gray.ndim == 3:
        gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
    # Precise upscaling: OpenCV's default doubling of the first octave shifts every feature by a quarter
    # of a pixel (of the reduced image: 1 px of a 4x reduced photo).
    n = int(min(opt.max_features, max(100.0, opt.features_per_mpx * gray.shape[0] * gray.shape[1] / 1e6)))
    sift = cv2.SIFT_create(nfeatures=n, contrastThreshold=opt.contrast_threshold,
                           enable_precise_upscale=True)
    kps, desc = sift.detectAndCompute(gray, None)
    if desc is None or not len(kps):
        return PhotoFeatures(name, np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    desc = desc / np.maximum(desc.sum(axis=1, keepdims=True), 1e-9)
    uv = to_full_px(np.array([k.pt for k in kps], float), factor_xy)
    return PhotoFeatures(name, uv, np.sqrt(desc).astype(np.float32), np.array([k.response for k in kps], np.float32))


class DescriptorIndex:
    """FLANN kd-trees (OpenCV, 4 randomised trees, 32 checks) over one photo's descriptors, built once and
    searched by the features of any number of other photos: a frame matched against several earlier
    keyframes pays for its index once. The trees are seeded, so matches are the same on every run and the
    same as an index built for a single pair."""

    def __init__(self, desc: np.ndarray):
        cv2.setRNGSeed(0)       # FLANN's randomised kd-trees: the same matches on every run
        self.size = len(desc)
        self._flann = cv2.FlannBasedMatcher(dict(algorithm=1, trees=4), dict(checks=32))
        if self.size >= 2:
            self._flann.add([np.ascontiguousarray(desc, np.float32)])
            self._flann.train()

    def knn2(self, query: np.ndarray) -> list:
        """The two nearest indexed descriptors of each query descriptor (cv2.DMatch pairs)."""
        if self.size < 2 or not len(query):
            return []
        return self._flann.knnMatch(np.ascontiguousarray(query, np.float32), k=2)


def _ratio_matches(a: PhotoFeatures, b: PhotoFeatures, ratio: float, index_b: DescriptorIndex | None = None
                   ) -> np.ndarray:
    """(M, 2) ratio-test matches a -> b, one per feature of b (the closest); index_b: b's DescriptorIndex
    (built here when not given)."""
    knn = (index_b or DescriptorIndex(b.desc)).knn2(a.desc)
    rows = [(m[0].queryIdx, m[0].trainIdx, m[0].distance) for m in knn
            if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    if not rows:
        return np.zeros((0, 2), int)
    r = np.array(rows)
    order = np.lexsort((r[:, 2], r[:, 1]))          # by b index, closest first
    r = r[order]
    first = np.concatenate([[True], r[1:, 1] != r[:-1, 1]])
    return r[first, :2].astype(int)


def match_pair(a: PhotoFeatures, b: PhotoFeatures, camera: PinholeCamera, opt: MatchingOptions | None = None,
               px_per_feature_px: float = 1.0, i: int = 0, j: int = 1,
               index_b: DescriptorIndex | None = None) -> PairMatch:
    """Ratio-test matches of `a` and `b` verified by an essential matrix (see the module docstring).

    `px_per_feature_px`: full-photo pixels per reduced-image pixel (the RANSAC threshold's unit); `index_b`:
    b's DescriptorIndex when b is matched against several photos (built once by the caller)."""
    opt = opt or MatchingOptions()
    sizes = (len(a.uv), len(b.uv))
    none = np.zeros((0, 2), int)
    if min(sizes) < opt.min_inliers:
        return PairMatch(i, j, sizes, 0, 0, none, 'too_few_features')
    pairs = _ratio_matches(a, b, opt.ratio, index_b)
    if len(pairs) < opt.min_inliers:
        return PairMatch(i, j, sizes, len(pairs), 0, none, 'too_few_matches')
    thr_n = opt.ransac_px * px_per_feature_px / camera.fx
    E, inl = essential_ransac(camera.pixel_to_normalized(a.uv[pairs[:, 0]]),
                              camera.pixel_to_normalized(b.uv[pairs[:, 1]]), thr_n, method=opt.ransac_method)
    if E is None:
        return PairMatch(i, j, sizes, len(pairs), 0, none, 'no_geometry')
    n = int(inl.sum())
    if n < opt.min_inliers or n < opt.min_inlier_ratio * len(pairs):
        return PairMatch(i, j, sizes, len(pairs), n, none, 'too_few_inliers')
    return PairMatch(i, j, sizes, len(pairs), n, pairs[inl], 'verified')


def _overlap_scores(positions_m, footprints) -> np.ndarray:
    """(N, N) share of each photo's ground footprint covered by the other's: footprints (N, 3) of
    width_m, height_m, heading_deg (image x axis, clockwise from east... as cv2 rotated rects)."""
    n = len(positions_m)
    s = np.zeros((n, n))
    rects = [((float(p[0]), float(p[1])), (float(f[0]), float(f[1])), float(f[2]))
             for p, f in zip(positions_m, footprints)]
    for i in range(n):
        for j in range(i + 1, n):
            ok, pts = cv2.rotatedRectangleIntersection(rects[i], rects[j])
            if ok == cv2.INTERSECT_NONE or pts is None or len(pts) < 3:
                continue
            area = float(cv2.contourArea(cv2.convexHull(pts.astype(np.float32))))
            s[i, j] = area / max(footprints[i][0] * footprints[i][1], 1e-9)
            s[j, i] = area / max(footprints[j][0] * footprints[j][1], 1e-9)
    return s


MIN_OVERLAP = 0.05      # footprint share below which two photos are no first candidates


def candidate_order(positions_m: np.ndarray, neighbours: int, sigma_h_m: float = 0.0,
                    footprints: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per photo every other photo from the most to the least promising partner, and how many of
    them are first candidates: with `footprints` (N, 3: width_m, height_m, rotation_deg of the image
    x axis from east) the `neighbours` with the largest footprint overlap (at least MIN_OVERLAP);
    else the nearest `neighbours` by position plus every photo within the k-th distance +
    2 sqrt(2) sigma_h_m (two geotags' uncertainty: poor GNSS, more candidates). A photo without a
    position (NaN) has every photo as a first candidate. Returns (order (N, N-1), first (N,))."""
    p = np.asarray(positions_m, float)[:, :2]
    n = len(p)
    unknown = ~np.all(np.isfinite(p), axis=1)
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    d[unknown] = 0.0
    d[:, unknown] = 0.0
    use_fp = footprints is not None and np.all(np.isfinite(footprints)) and not unknown.any()
    score = _overlap_scores(p, footprints) if use_fp else None
    key = -score + 1e-9 * d if use_fp else d.copy()      # ties (no overlap) by distance
    np.fill_diagonal(key, np.inf)
    order = np.argsort(key, axis=1, kind='stable')[:, :n - 1]
    k = min(neighbours, n - 1)
    first = np.zeros(n, int)
    for i in range(n):
        if unknown[i]:
            first[i] = n - 1
        elif use_fp:
            first[i] = min(k, int(np.sum(score[i, order[i]] >= MIN_OVERLAP)))
        else:
            reach = (d[i, order[i, k - 1]] if k else 0.0) + 2.0 * np.sqrt(2.0) * sigma_h_m
            first[i] = max(k, int(np.sum(d[i, order[i]] <= reach)))
    return order, first


def earlier_candidates(positions_m: np.ndarray, new_m: np.ndarray, neighbours: int,
                       sigma_h_m: float = 0.0) -> tuple[np.ndarray, int]:
    """A new photo's partners among earlier ones (all with a position), as `candidate_order` ranks a photo's
    partners in a block of them all: (indices into `positions_m` from the nearest, how many of them are first
    candidates: the `neighbours` nearest and every one within the k-th distance + 2 sqrt(2) sigma_h_m)."""
    p = np.vstack([np.asarray(positions_m, float).reshape(-1, np.shape(new_m)[-1]),
                   np.asarray(new_m, float).reshape(1, -1)])
    if len(p) < 2:
        return np.zeros(0, int), 0
    order, first = candidate_order(p, neighbours, sigma_h_m)
    return order[-1], int(first[-1])


def candidate_pairs(order: np.ndarray, first: np.ndarray) -> list[tuple[int, int]]:
    """Pairs (i < j) to match first: each photo's `first[i]` candidates of `candidate_order`."""
    out = set()
    for i in range(len(order)):
        out.update((min(i, int(j)), max(i, int(j))) for j in order[i, :first[i]])
    return sorted(out)


def more_candidates(order: np.ndarray, tried: set, verified_count: np.ndarray, min_pairs: int,
                    max_extra: int) -> list[tuple[int, int]]:
    """Next pairs for photos with fewer than `min_pairs` verified pairs: their next `max_extra`
    untried partners in candidate order."""
    out = set()
    for i in np.flatnonzero(np.asarray(verified_count) < min_pairs):
        extra = [int(j) for j in order[i] if (min(i, j), max(i, j)) not in tried][:max_extra]
        out.update((min(i, j), max(i, j)) for j in extra)
    return sorted(out)


def build_tracks(n_features: list[int], matches: dict) -> list[np.ndarray]:
    """Union-find over (photo, feature) nodes -> per photo an array of track ids (-1 = none)."""
    offsets = np.concatenate([[0], np.cumsum(n_features)]).astype(np.int64)
    parent = np.arange(offsets[-1])

    def find(x):
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:
            parent[x], x = root, parent[x]
        return root

    for (i, j), pairs in matches.items():
        for fa, fb in pairs:
            ra, rb = find(offsets[i] + fa), find(offsets[j] + fb)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    # Every node's root: pointer jumping until stable (vectorised).
    roots = parent.copy()
    while True:
        nxt = roots[roots]
        if np.array_equal(nxt, roots):
            break
        roots = nxt
    photo_of = np.repeat(np.arange(len(n_features)), n_features)
    # Tracks: roots with >= 2 members, each in a different photo.
    uniq, inv, counts = np.unique(roots, return_inverse=True, return_counts=True)
    pair_key = inv.astype(np.int64) * len(n_features) + photo_of
    dup = np.zeros(len(uniq), bool)
    keys_u, cnt = np.unique(pair_key, return_counts=True)
    dup[(keys_u[cnt > 1] // len(n_features))] = True
    good = (counts >= 2) & ~dup
    track_of = np.where(good[inv], inv, -1)
    return [track_of[offsets[i]:offsets[i + 1]] for i in range(len(n_features))]


def track_lengths(tracks: list[np.ndarray]) -> np.ndarray:
    """Photos per track (index = track id; 0 for ids no photo holds)."""
    ids = np.concatenate([t[t >= 0] for t in tracks] or [np.zeros(0, int)])
    return np.bincount(ids) if len(ids) else np.zeros(0, int)
