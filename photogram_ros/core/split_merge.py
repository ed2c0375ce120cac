"""Split-merge adjustment of a large photo block: partition, similarities between overlapping sub-blocks, merge.

A block's adjustment grows faster than linearly with its photos; a large block is cut into spatially compact
sub-blocks that overlap, each adjusted on its own (georeferenced by its own GNSS and the GCPs it sees, in the
block's map frame: ENU metres at one origin), and merged:

- `partition(positions_en_m, opt)`: k = ceil(N / split_photos) clusters of the photos' horizontal positions
  (k-means, deterministic seeding), each the core of one sub-block; a sub-block also takes every photo within
  `overlap_m` of one of its core photos (default: the median distance from a photo to its
  `overlap_neighbours`-th nearest photo, the photos it is matched with), so each boundary strip belongs to
  two sub-blocks. Photos without a position join the core of the photo nearest to them in the input order.
- `merge(sub_blocks, n_sub_blocks, opt)`: one similarity per sub-block to a common frame from all pairwise
  overlaps at once (least squares over the shared cameras' centres and the shared tie points, found by
  track id; the similarities of each connected group of sub-blocks average to the identity, so the merged
  block stays where the sub-blocks' GNSS and GCPs put it); each photo's pose from its core sub-block (from
  another one that oriented it otherwise), each tie point and check point the mean of its copies. An
  overlap whose shared cameras still disagree beyond `overlap_warn_m` / `overlap_fail_m` after the
  similarities, a sub-block that failed (left out of the merge) and a sub-block that shares nothing with
  the rest (kept where its own GNSS puts it) are findings naming the sub-blocks, never silently merged.
- The global adjustment starts from the merged block as the state of an empty adjuster (core/incremental.py
  `IncrementalAT.seed`): every photo a keyframe, the merged ones oriented at their
  merged poses, the merged tie points as its points (observations that reproject beyond the gate left out), the
  GCPs intersected from the merged cameras, georeferenced for good. Its `full_adjustment` is then the global
  adjustment of the whole block (GNSS, GCPs, the final self-calibration) without an incremental pass.
- `camera_moves(before, after)`: how far an adjustment moved the cameras (centres in m, attitudes in deg).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.cluster.vq import kmeans2

from photogram_ros.core.block_check import STATUS_ORDER, Finding
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.rotations import R_from_rotvec
from photogram_ros.core.similarity import Similarity
from photogram_ros.errors import DataError
from photogram_ros.params import param


@dataclass
class SplitMergeOptions:
    """When and how a photo block is split into overlapping sub-blocks and merged back."""
    split_photos: int = param(250, 'photos a block may have before it is split; also the target size of a '
                                   'sub-block\'s core (photos), the overlap comes on top', min=10, max=100000)
    overlap_m: float = param(0.0, 'overlap radius (m): photos within it of a sub-block\'s core photos join that '
                                  'sub-block; 0: the median distance from a photo to its overlap_neighbours-th '
                                  'nearest photo', min=0.0, max=100000.0)
    overlap_neighbours: int = param(8, 'neighbour count that sets the default overlap radius (the photos matched '
                                       'with each photo)', min=1, max=100)
    overlap_warn_m: float = param(0.15, 'RMS (m) of the shared cameras\' centres between two sub-blocks after the '
                                        'merge\'s similarities: a warning above, naming both', min=0.0, max=1000.0)
    overlap_fail_m: float = param(1.0, 'the same RMS (m): the merge is failed above', min=0.0, max=1000.0)
    max_shared_points: int = param(1000, 'shared tie points per overlap used for the similarities (an even '
                                          'subsample above it)', min=0, max=1000000)
    iterations: int = param(8, 'Gauss-Newton iterations of the similarities', min=1, max=100)
    global_adjustment: bool = param(True, 'after the merge, one bundle adjustment of the whole block (every photo, '
                                          'its GNSS, the GCPs, the final self-calibration) starting from the merged '
                                          'poses and tie points; off: the merged block is the result')
    seed_gate_px: float = param(5.0, 'global adjustment: an observation of a merged tie point that reprojects '
                                     'further than this (px) from it through the merged camera is left out',
                                min=0.5, max=1000.0)


@dataclass
class Partition:
    labels: np.ndarray                  # (N,) the sub-block whose core each photo is in
    members: list                       # per sub-block: sorted photo indices (core and overlap)
    overlap_m: float                    # the radius used

    @property
    def n(self) -> int:
        return len(self.members)


def partition(positions_en_m: np.ndarray, opt: SplitMergeOptions | None = None, seed: int = 0) -> Partition:
    """Overlapping, spatially compact sub-blocks of photos at `positions_en_m` (N, 2+; E, N in metres; NaN
    rows: no position). One sub-block when N <= split_photos."""
    opt = opt or SplitMergeOptions()
    P = np.asarray(positions_en_m, float)
    if P.ndim != 2 or P.shape[1] < 2:
        raise DataError(f'partition needs (N, 2) photo positions E, N (m), got shape {P.shape}')
    P = P[:, :2]
    n = len(P)
    has = np.all(np.isfinite(P), axis=1)
    k = max(1, math.ceil(n / opt.split_photos))
    if k == 1 or has.sum() < 2 * k:
        return Partition(np.zeros(n, int), [np.arange(n)], 0.0)
    X = P[has]
    labels_has = kmeans2(X, k, minit='++', seed=np.random.default_rng(seed))[1]
    # Empty clusters (duplicate positions) are dropped and the rest renumbered.
    used = np.unique(labels_has)
    labels_has = np.searchsorted(used, labels_has)
    k = len(used)
    labels = np.zeros(n, int)
    labels[has] = labels_has
    idx_has = np.flatnonzero(has)
    for i in np.flatnonzero(~has):            # nearest photo in the input order that has a position
        labels[i] = labels[idx_has[np.argmin(np.abs(idx_has - i))]]
    D = np.sqrt(np.sum((X[:, None, :] - X[None]) ** 2, axis=2))
    radius = opt.overlap_m
    if radius <= 0:
        kk = min(opt.overlap_neighbours, len(X) - 1)
        radius = float(np.median(np.sort(D, axis=1)[:, kk]))
    members = []
    for j in range(k):
        core = labels_has == j
        near = np.any(D[:, core] <= radius, axis=1)
        m = set(idx_has[near | core].tolist()) | set(np.flatnonzero(labels == j).tolist())
        members.append(np.array(sorted(m), int))
    return Partition(labels, members, radius)


@dataclass
class SubBlock:
    """One adjusted sub-block, in the map frame its own GNSS and GCPs put it."""
    index: int
    names: list                                       # its photos (core and overlap)
    map_T_cam: dict = field(default_factory=dict)     # photo name -> (4, 4) pose of the oriented ones
    point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))   # (M,) tie point track ids
    points_map_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))    # (M, 3)
    checks: dict = field(default_factory=dict)        # check point name -> ((3,) map m, images)
    status: str = 'ok'                                # its own verdict: 'ok', 'warning', 'failed'
    summary: str = ''                                 # its verdict's summary


@dataclass
class MergeResult:
    map_T_cam: dict                       # photo name -> (4, 4) merged pose
    source: dict                          # photo name -> sub-block its pose came from
    point_ids: np.ndarray                 # (M,) merged tie points' track ids
    points_map_m: np.ndarray              # (M, 3)
    checks: dict                          # check point name -> ((3,) map m, images)
    similarities: list                    # per sub-block: Similarity to the common frame (None: left out)
    overlaps: list                        # per overlapping pair: figures before and after the similarities
    findings: list                        # block_check.Finding of the merge
    left_out: list                        # sub-blocks not merged (failed)

    @property
    def status(self) -> str:
        s = 'ok'
        for f in self.findings:
            s = f.status if STATUS_ORDER.index(f.status) > STATUS_ORDER.index(s) else s
        return s


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices of (N, 3) vectors."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return S


def _pair_correspondences(a: SubBlock, b: SubBlock, max_points: int) -> tuple:
    """(xa, xb, n_cameras): shared camera centres first, then shared tie points (by track id)."""
    shared = sorted(set(a.map_T_cam) & set(b.map_T_cam))
    ca = np.array([a.map_T_cam[s][:3, 3] for s in shared]).reshape(-1, 3)
    cb = np.array([b.map_T_cam[s][:3, 3] for s in shared]).reshape(-1, 3)
    _, ia, ib = np.intersect1d(a.point_ids, b.point_ids, assume_unique=True, return_indices=True)
    if max_points and len(ia) > max_points:
        pick = np.linspace(0, len(ia) - 1, max_points).astype(int)
        ia, ib = ia[pick], ib[pick]
    elif not max_points:
        ia = ib = np.zeros(0, int)
    return (np.vstack([ca, a.points_map_m[ia]]), np.vstack([cb, b.points_map_m[ib]]), len(shared))


def _components(n: int, edges: list) -> list:
    parent = list(range(n))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i
    for a, b in edges:
        parent[root(a)] = root(b)
    groups: dict = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(i)
    return list(groups.values())


def solve_similarities(pairs: list, n: int, iterations: int = 8, centre: np.ndarray | None = None) -> tuple:
    """Similarities (list of n) that bring n frames together: pairs [(a, b, xa (K, 3), xb (K, 3))] of the
    same points in frames a and b. Least squares of |S_a(xa) - S_b(xb)| (Gauss-Newton, left updates about
    `centre`; correspondences beyond 5 robust sigmas and 5 cm dropped after the second iteration); the
    similarities of each connected group average to the identity. Returns (similarities, inlier masks per
    pair)."""
    sims = [Similarity() for _ in range(n)]
    xs = [np.vstack([p[2] for p in pairs] + [np.zeros((0, 3))])]
    c0 = np.asarray(centre, float) if centre is not None else (xs[0].mean(axis=0) if len(xs[0]) else np.zeros(3))
    L = max(float(np.sqrt(np.mean(np.sum((xs[0] - c0) ** 2, axis=1)))) if len(xs[0]) else 1.0, 1.0)
    inl = [np.ones(len(p[2]), bool) for p in pairs]
    groups = _components(n, [(p[0], p[1]) for p in pairs])
    for it in range(iterations):
        rows_J, rows_r = [], []
        for (a, b, xa, xb), m in zip(pairs, inl):
            ya, yb = sims[a].apply(xa[m]) - c0, sims[b].apply(xb[m]) - c0
            K = len(ya)
            if not K:
                continue
            J = np.zeros((K, 3, 7 * n))
            # d(y)/d(ds, dw, dt) at the identity, with ds and dw scaled by L (all columns in metres).
            for y, k, sign in ((ya, a, 1.0), (yb, b, -1.0)):
                J[:, :, 7 * k] = sign * y / L
                J[:, :, 7 * k + 1:7 * k + 4] = -sign * _skew(y) / L
                J[:, :, 7 * k + 4:7 * k + 7] = sign * np.eye(3)
            rows_J.append(J.reshape(3 * K, 7 * n))
            rows_r.append((ya - yb).reshape(-1))
        w = 1e3
        for g in groups:   # gauge: the group's updates sum to zero
            G = np.zeros((7, 7 * n))
            for k in g:
                G[:, 7 * k:7 * k + 7] = w * np.eye(7)
            rows_J.append(G)
            rows_r.append(np.zeros(7))
        rows_J.append(1e-6 * np.eye(7 * n))       # a sub-block without overlap stays where it is
        rows_r.append(np.zeros(7 * n))
        J, r = np.vstack(rows_J), np.concatenate(rows_r)
        dp = np.linalg.lstsq(J, -r, rcond=None)[0]
        for k in range(n):
            p = dp[7 * k:7 * k + 7]
            ds, dR, dt = p[0] / L, R_from_rotvec(p[1:4] / L), p[4:7]
            s = sims[k]
            # new(x) = c0 + (1 + ds) dR (s(x) - c0) + dt
            sims[k] = Similarity((1 + ds) * s.scale, dR @ s.R, (1 + ds) * dR @ (s.t - c0) + c0 + dt)
        if it == 1:
            for i, (a, b, xa, xb) in enumerate(pairs):
                d = np.linalg.norm(sims[a].apply(xa) - sims[b].apply(xb), axis=1)
                if len(d):
                    inl[i] = d <= max(5 * 1.4826 * float(np.median(d)), 0.05)
        if np.max(np.abs(dp), initial=0.0) < 1e-7:
            break
    return sims, inl


def merge(sub_blocks: list, opt: SplitMergeOptions | None = None, core_of: dict | None = None) -> MergeResult:
    """Sub-blocks (SubBlock, any order; index 0..K-1) -> one block (see the module docstring). core_of:
    photo name -> the sub-block whose core it is (its pose comes from there)."""
    opt = opt or SplitMergeOptions()
    n = max((s.index for s in sub_blocks), default=-1) + 1
    by = {s.index: s for s in sub_blocks}
    findings, left_out = [], []
    for k in range(n):
        s = by.get(k)
        if s is None or s.status == 'failed' or not s.map_T_cam:
            left_out.append(k)
            why = 'it did not run' if s is None else (s.summary or 'nothing oriented')
            findings.append(Finding('sub_block', 'failed' if s is not None and s.status == 'failed' else 'warning',
                                    f'sub-block {k} left out of the merge: {why}',
                                    [] if s is None else list(s.names)[:50]))
    good = [k for k in range(n) if k not in left_out]
    pairs, meta = [], []
    for i, a in enumerate(good):
        for b in good[i + 1:]:
            xa, xb, n_cam = _pair_correspondences(by[a], by[b], opt.max_shared_points)
            if n_cam >= 1 and len(xa) >= 3:
                pairs.append((a, b, xa, xb))
                meta.append(n_cam)
    allc = np.array([T[:3, 3] for k in good for T in by[k].map_T_cam.values()]).reshape(-1, 3)
    sims, inl = solve_similarities(pairs, n, opt.iterations, allc.mean(axis=0) if len(allc) else None)
    overlaps = []
    for (a, b, xa, xb), m, n_cam in zip(pairs, inl, meta):
        before = np.linalg.norm(xa[:n_cam] - xb[:n_cam], axis=1)
        after = np.linalg.norm(sims[a].apply(xa[:n_cam]) - sims[b].apply(xb[:n_cam]), axis=1)
        pts = np.linalg.norm(sims[a].apply(xa[n_cam:]) - sims[b].apply(xb[n_cam:]), axis=1)
        o = {'sub_blocks': [a, b], 'shared_photos': n_cam, 'shared_points_used': int(m[n_cam:].sum()),
             'camera_rms_before_m': float(np.sqrt(np.mean(before ** 2))),
             'camera_rms_m': float(np.sqrt(np.mean(after ** 2))), 'camera_max_m': float(after.max()),
             'point_median_m': float(np.median(pts)) if len(pts) else None}
        overlaps.append(o)
        if o['camera_rms_m'] > opt.overlap_warn_m:
            st = 'failed' if o['camera_rms_m'] > opt.overlap_fail_m else 'warning'
            shared = sorted(set(by[a].map_T_cam) & set(by[b].map_T_cam))
            findings.append(Finding('overlap', st, f'sub-blocks {a} and {b} disagree in their overlap by '
                                    f'{o["camera_rms_m"]:.2f} m RMS over {n_cam} shared cameras (max '
                                    f'{o["camera_max_m"]:.2f} m) after the merge\'s similarities (tolerance '
                                    f'{opt.overlap_warn_m:.2f} m): one of them is deformed', shared[:50]))
    linked = {k for p in pairs for k in p[:2]}
    for k in good:
        if len(good) > 1 and k not in linked:
            findings.append(Finding('overlap', 'warning', f'sub-block {k} shares no oriented photo with the others: '
                                    'kept where its own GNSS and GCPs put it', list(by[k].names)[:50]))
    out_sims = [sims[k] if k in good else None for k in range(n)]
    core_of = core_of or {}
    poses, source = {}, {}
    for k in good:
        for name, T in by[k].map_T_cam.items():
            if name not in poses or core_of.get(name) == k and source[name] != k:
                poses[name], source[name] = sims[k].apply_pose(T), k
    ids = np.concatenate([by[k].point_ids for k in good] + [np.zeros(0, np.int64)])
    P = np.vstack([sims[k].apply(by[k].points_map_m) for k in good] + [np.zeros((0, 3))])
    uid, inv = np.unique(ids, return_inverse=True)
    cnt = np.bincount(inv, minlength=len(uid)).astype(float)
    Pm = np.stack([np.bincount(inv, P[:, j], minlength=len(uid)) for j in range(3)], axis=1) / cnt[:, None] \
        if len(uid) else np.zeros((0, 3))
    checks: dict = {}
    for k in good:
        for name, (X, n_img) in by[k].checks.items():
            acc = checks.setdefault(name, [np.zeros(3), 0])
            acc[0] = acc[0] + n_img * sims[k].apply(np.asarray(X, float)[None])[0]
            acc[1] += n_img
    checks = {nm: (v[0] / v[1], v[1]) for nm, v in checks.items() if v[1] > 0}
    return MergeResult(poses, source, uid, Pm, checks, out_sims, overlaps, findings, left_out)


def mean_camera(cameras: list, weights) -> PinholeCamera:
    """The weighted mean of the intrinsics of cameras of one size (the sub-blocks' self-calibrations): the
    starting camera of the global adjustment."""
    if not cameras:
        raise DataError('mean_camera needs at least one camera')
    w = np.asarray(weights, float).reshape(-1)
    if len(w) != len(cameras) or not np.all(w >= 0) or w.sum() <= 0:
        raise DataError(f'mean_camera: {len(cameras)} cameras need as many non-negative weights, got {w}')
    if len({(c.width, c.height) for c in cameras}) != 1:
        raise DataError('mean_camera: the cameras differ in image size: '
                        f'{sorted({(c.width, c.height) for c in cameras})}')
    w = w / w.sum()

    def avg(get):
        return float(np.sum(w * np.array([get(c) for c in cameras], float)))
    c0 = cameras[0]
    return PinholeCamera(c0.width, c0.height, avg(lambda c: c.fx), avg(lambda c: c.fy), avg(lambda c: c.cx),
                         avg(lambda c: c.cy), tuple(avg(lambda c, i=i: c.dist[i]) for i in range(5)))


def camera_moves(before: dict, after: dict) -> dict:
    """How far `after` (photo name -> (4, 4) camera-to-map pose) moved the cameras of `before`: RMS and max of
    the centres' displacement (m, 3D and horizontal) and of the attitude change (deg), over the photos in both;
    the photos in only one of them counted."""
    common = sorted(set(before) & set(after))
    out = {'photos': len(common), 'only_before': len(set(before) - set(after)),
           'only_after': len(set(after) - set(before))}
    if not common:
        return out
    A = np.array([before[n] for n in common], float)
    B = np.array([after[n] for n in common], float)
    d = B[:, :3, 3] - A[:, :3, 3]
    dR = np.einsum('nji,njk->nik', A[:, :3, :3], B[:, :3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)))
    d3, dh = np.linalg.norm(d, axis=1), np.linalg.norm(d[:, :2], axis=1)
    out.update(centre_rms_m=float(np.sqrt(np.mean(d3 ** 2))), centre_max_m=float(d3.max()),
               centre_h_rms_m=float(np.sqrt(np.mean(dh ** 2))), centre_v_rms_m=float(np.sqrt(np.mean(d[:, 2] ** 2))),
               centre_mean_m=d.mean(axis=0).tolist(),
               attitude_rms_deg=float(np.sqrt(np.mean(ang ** 2))), attitude_max_deg=float(ang.max()))
    return out
