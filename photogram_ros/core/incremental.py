"""Incremental aerial triangulation: two-view start, PnP, triangulation, georeference, sliding window.

Input is one `KeyframeRecord` per keyframe (tracks as ids + distorted pixels, a GNSS fix in WGS84
with its ENU covariance, optional target observations by name). The reconstruction starts in an
arbitrary frame from two keyframes; as soon as the camera centres are not collinear (a straight
line leaves the roll about the line undetermined) a RANSAC similarity to the GNSS positions moves
it into `map` (ENU at the origin), a full adjustment follows, and from then on every adjustment
carries the fixes as priors weighted by their covariance. Surveyed GCPs enter as point priors;
check points are never used, only triangulated afterwards from the adjusted cameras.

Lever arm: the GNSS antenna is `C + map_R_cam @ lever_arm_cam_m`, a fixed offset in the camera
frame. That is exact for a camera rigidly mounted on the body and an approximation for a gimbal:
the error is |lever| times the body-vs-camera attitude difference, 1.7 cm for a 20 cm mast on a
multirotor pitched 5 degrees into its course. A record's `antenna_offset_map_m` (from the body
attitude, core/attitude.py) replaces it for that keyframe.

Memory on long flights (`spill_frozen`): a tracker track that has not been seen for the window plus
a margin can never enter a window again, so it is frozen: its point moves to compact arrays with
only a count of its observations (core/at_store.py), and a keyframe whose tracks are all frozen
moves its observations to disk. The final full adjustment reads them back (its peak is the
solver's); results are bit-identical to keeping everything (tests/test_incremental.py).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from photogram_ros.core.at_store import KeyframeSpill, PointStore
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.rotations import invert_T, make_T
from photogram_ros.core.similarity import similarity_on_line, similarity_ransac, spread
from photogram_ros.core.two_view import relative_pose
from photogram_ros.core.window import select_window
from photogram_ros.errors import DataError

from photogram_ros.core.bundle import BundleOptions, BundleProblem, bundle_adjust


@dataclass
class GnssFix:
    lat_deg: float
    lon_deg: float
    h_m: float                      # ellipsoidal
    cov_enu_m2: np.ndarray          # (3, 3)


@dataclass
class KeyframeRecord:
    stamp_ns: int
    track_ids: np.ndarray           # (K,) int
    uv: np.ndarray                  # (K, 2) distorted pixels
    fix: GnssFix | None = None
    name: str = ''
    target_uv: dict = field(default_factory=dict)   # target name -> (u, v) pixels
    # Antenna minus camera centre in map ENU (m), from the autopilot attitude and the body lever
    # arm; when None the fixed camera-frame lever arm of the options is used instead.
    antenna_offset_map_m: np.ndarray | None = None


@dataclass
class ControlPoint:
    name: str
    map_xyz: np.ndarray             # surveyed, map ENU (m)
    sigma_m: np.ndarray             # (3,) E, N, U
    role: str                       # 'gcp' (used) or 'check' (never used)


@dataclass
class IncrementalOptions:
    window_size: int = 10
    max_fixed_keyframes: int = 30
    min_init_inliers: int = 30
    min_init_angle_deg: float = 2.0
    min_triangulation_angle_deg: float = 1.5
    max_reprojection_px: float = 2.5   # accept a new point / keep an observation
    pnp_threshold_px: float = 3.0
    min_pnp_inliers: int = 12
    loss: str = 'huber'
    loss_scale_px: float = 1.0
    window_iterations: int = 15
    full_iterations: int = 50
    lever_arm_cam_m: tuple = (0.0, 0.0, 0.0)
    georef_min_keyframes: int = 4
    georef_min_spread_ratio: float = 0.05
    assume_nadir: bool = True          # a straight first line georeferences provisionally (see above)
    use_gcps: bool = True
    estimate_gnss_bias: bool = True    # a constant ENU GNSS offset, when >= 3 GCPs make it observable
    bias_iterations: int = 10
    # Long flights: keyframes and tracks that can no longer enter a window leave the Python heap
    # (points to compact arrays, keyframe observations to disk) so memory stays flat; a track id
    # seen again later brings them back, so results are the same either way.
    spill_frozen: bool = True
    spill_dir: str = ''                # '' = a private temporary folder, removed afterwards
    freeze_margin_keyframes: int = 5   # a track is dead this many registrations before the window
    freeze_every: int = 5              # keyframes between freeze passes
    max_thaws: int = 3                 # keyframes bringing back (or looking up) ended tracks before freezing stops


class _Keyframe:
    """One keyframe: metadata always in memory, observation arrays in memory while it is *hot* and
    on disk (`KeyframeSpill`) once frozen. Reading an array of a frozen keyframe thaws it, so every
    caller stays correct; the freeze pass of IncrementalAT spills it again when it may."""

    __slots__ = ('kid', 'stamp_ns', 'name', 'fix_enu', 'fix_cov', 'map_T_cam', 'antenna_offset', 'reg_seq',
                 'id_lo', 'id_hi', 'has_targets', '_arr', '_spill', '_disk_active')

    def __init__(self, kid, stamp_ns, name, track_ids, uv, xn, active, fix_enu, fix_cov, map_T_cam=None,
                 antenna_offset=None):
        self.kid, self.stamp_ns, self.name = kid, stamp_ns, name
        self.fix_enu, self.fix_cov, self.map_T_cam, self.antenna_offset = fix_enu, fix_cov, map_T_cam, antenna_offset
        self.reg_seq = -1          # position in IncrementalAT.registered, -1 while not registered
        nonneg = track_ids[track_ids >= 0]
        self.id_lo = int(nonneg.min()) if len(nonneg) else 0
        self.id_hi = int(nonneg.max()) if len(nonneg) else -1
        self.has_targets = bool(len(nonneg) < len(track_ids))
        self._arr = (track_ids, uv, xn, active)
        self._spill = None
        self._disk_active = None   # `active` as last written to disk (an unchanged keyframe is not rewritten)

    @property
    def frozen(self) -> bool:
        return self._arr is None

    def _arrays(self):
        if self._arr is None:
            self._arr = self._spill.load(self.kid)
            self._disk_active = self._arr[3].copy()
        return self._arr

    def peek(self):
        """(track_ids, uv, xn, active) without thawing (read-only use)."""
        return self._arr if self._arr is not None else self._spill.load(self.kid)

    def freeze(self, spill) -> None:
        if self._arr is None:
            return
        if self._disk_active is None or not np.array_equal(self._disk_active, self._arr[3]):
            spill.save(self.kid, *self._arr)
        self._spill = spill
        self._arr = None
        self._disk_active = None

    track_ids = property(lambda self: self._arrays()[0])
    uv = property(lambda self: self._arrays()[1])
    xn = property(lambda self: self._arrays()[2])
    active = property(lambda self: self._arrays()[3])

    def index(self, tid: int) -> int | None:
        """Observation index of track `tid` (track ids are sorted), None if not observed."""
        ids = self.track_ids
        i = int(np.searchsorted(ids, tid))
        return i if i < len(ids) and ids[i] == tid else None

    @property
    def index_of(self) -> dict:
        return {int(t): i for i, t in enumerate(self.track_ids)}


@dataclass
class StepReport:
    kid: int
    registered: bool
    status: str
    solve_s: float = 0.0
    cost: float = float('nan')
    reprojection_rms_px: float = float('nan')
    gnss_rms_m: float = float('nan')
    window_size: int = 0
    n_points: int = 0


def _adjust(prob, loss: str, scale_px: float, iterations: int, refine: tuple = ()):
    return bundle_adjust(prob, BundleOptions(loss=loss, loss_scale_px=scale_px, max_iterations=iterations,
                                             refine_intrinsics=tuple(refine)))


def lever_arm_cam_from_frd(lever_frd_m) -> np.ndarray:
    """Body-FRD lever arm -> camera frame, for a nadir camera whose image top points forward.

    Optical x = body right, optical y = body backward, optical z = body down.
    """
    f, r, d = np.asarray(lever_frd_m, float)
    return np.array([r, -f, d])


def triangulate_rays(centres: np.ndarray, dirs: np.ndarray, groups: np.ndarray, n: int) -> np.ndarray:
    """Least-squares intersection of rays grouped by point: (n, 3), NaN where undetermined."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    A = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    b = np.einsum('nij,nj->ni', A, centres)
    As = np.zeros((n, 3, 3))
    bs = np.zeros((n, 3))
    np.add.at(As, groups, A)
    np.add.at(bs, groups, b)
    out = np.full((n, 3), np.nan)
    ok = np.abs(np.linalg.det(As)) > 1e-12
    out[ok] = np.linalg.solve(As[ok], bs[ok][..., None])[..., 0]
    return out


class IncrementalAT:
    """The aerial-triangulation state; feed `add_keyframe`, call `full_adjustment` at the end."""

    def __init__(self, camera: PinholeCamera, options: IncrementalOptions | None = None,
                 origin: LocalFrame | None = None, control: list[ControlPoint] | None = None):
        self.camera = camera
        self.opt = options or IncrementalOptions()
        self.origin = origin
        self.kfs: list[_Keyframe] = []
        self.registered: list[int] = []
        self.points = PointStore()                  # dict-like {track id: (3,) map ENU}
        self.track_kfs: dict[int, list[int]] = {}    # hot tracks: registered keyframes with an active observation
        # Hot tracker tracks (id >= 0) -> newest keyframe observing them; a track whose newest
        # observation is older than the window (and its margin) is frozen.
        self.last_seen: dict[int, int] = {}
        self._max_seen_id = -1
        self._spill: KeyframeSpill | None = None
        # Records whose track ids come back after a gap (ground-point ids, a loop-closing matcher)
        # make every thaw a scan of the block: after a few, freezing stops for this block.
        self._thaw_keyframes = 0
        self.freezing_stopped = ''
        self.georeferenced = False
        self.georef_provisional = False
        self.control = {c.name: c for c in (control or [])}
        self._target_ids: dict[str, int] = {}
        self.lever = np.asarray(self.opt.lever_arm_cam_m, float)
        self.history: list[StepReport] = []
        self.rng = np.random.default_rng(0)
        # A GNSS receiver without corrections is off by a bias that wanders over minutes; weighting
        # its fixes as independent lets them bend the block away from the GCPs (camera position
        # and tilt trade off over flat ground). With GCPs the bias is observable: estimated here.
        self.gnss_bias_enu = np.zeros(3)

    # --- input --------------------------------------------------------------------------------

    def _target_track(self, name: str) -> int:
        if name not in self._target_ids:
            self._target_ids[name] = -(len(self._target_ids) + 1)   # tracker ids are >= 0
        return self._target_ids[name]

    def _is_check(self, tid: int) -> bool:
        if tid >= 0:
            return False
        name = self.target_name(tid)
        c = self.control.get(name)
        return c is None or c.role != 'gcp' or not self.opt.use_gcps

    def target_name(self, tid: int) -> str:
        for n, t in self._target_ids.items():
            if t == tid:
                return n
        return ''

    def add_keyframe(self, rec: KeyframeRecord) -> StepReport:
        ids = np.asarray(rec.track_ids, dtype=np.int64).ravel()
        uv = np.asarray(rec.uv, float).reshape(-1, 2)
        if len(ids) != len(uv):
            raise DataError(f'keyframe {rec.stamp_ns}: {len(ids)} track ids but {len(uv)} pixel positions')
        if rec.target_uv:
            ids = np.concatenate([ids, [self._target_track(n) for n in rec.target_uv]])
            uv = np.vstack([uv, np.asarray(list(rec.target_uv.values()), float).reshape(-1, 2)])
        ids, first = np.unique(ids, return_index=True)   # a duplicated id would be a tracker bug
        uv = uv[first]
        fix_enu = fix_cov = None
        if rec.fix is not None:
            if self.origin is None:
                self.origin = LocalFrame(rec.fix.lat_deg, rec.fix.lon_deg, rec.fix.h_m)
            fix_enu = np.asarray(self.origin.geodetic_to_enu(rec.fix.lat_deg, rec.fix.lon_deg, rec.fix.h_m))
            fix_cov = np.asarray(rec.fix.cov_enu_m2, float).reshape(3, 3)
        kf = _Keyframe(len(self.kfs), int(rec.stamp_ns), rec.name or str(rec.stamp_ns), ids, uv,
                       self.camera.pixel_to_normalized(uv), np.ones(len(ids), bool), fix_enu, fix_cov)
        if rec.antenna_offset_map_m is not None:
            kf.antenna_offset = np.asarray(rec.antenna_offset_map_m, float).reshape(3)
        self._thaw_tracks_seen_again(ids)
        self.kfs.append(kf)
        for t in ids[ids >= 0].tolist():
            self.last_seen[t] = kf.kid
        if len(ids) and ids[-1] >= 0:
            self._max_seen_id = max(self._max_seen_id, int(ids[-1]))
        t0 = time.perf_counter()
        if not self.registered:
            rep = self._try_initialise()
        else:
            rep = self._register(kf)
            if rep.registered:
                self._triangulate_new(kf)
                if not self.georeferenced or self.georef_provisional:
                    self._try_georeference()
                rep = self._window_adjust(kf.kid)
        rep.solve_s = time.perf_counter() - t0
        rep.n_points = len(self.points)
        self.history.append(rep)
        if self.opt.spill_frozen and kf.kid % max(self.opt.freeze_every, 1) == 0:
            self.freeze()
        return rep

    # --- geometry steps -------------------------------------------------------------------------

    def _usable(self, kf: _Keyframe) -> np.ndarray:
        """Observations that may build geometry: active and not a check point."""
        m = kf.active.copy()
        neg = kf.track_ids < 0
        if neg.any():
            m[neg] &= ~np.array([self._is_check(int(t)) for t in kf.track_ids[neg]])
        return m

    def _try_initialise(self) -> StepReport:
        new = self.kfs[-1]
        for first in self.kfs[:-1]:
            ids, i1, i2 = np.intersect1d(first.track_ids[self._usable(first)], new.track_ids[self._usable(new)],
                                         return_indices=True)
            i1 = np.flatnonzero(self._usable(first))[i1]
            i2 = np.flatnonzero(self._usable(new))[i2]
            if len(ids) < self.opt.min_init_inliers:
                continue
            thr = self.opt.pnp_threshold_px / self.camera.fx
            res = relative_pose(first.xn[i1], new.xn[i2], thr, self.opt.min_init_inliers)
            if not res.ok or res.median_angle_deg < self.opt.min_init_angle_deg:
                continue
            first.map_T_cam = np.eye(4)
            new.map_T_cam = invert_T(res.cam2_T_cam1)
            self.registered = [first.kid, new.kid]
            first.reg_seq, new.reg_seq = 0, 1
            for kf in (first, new):
                for t in kf.track_ids[kf.active].tolist():
                    self.track_kfs.setdefault(t, []).append(kf.kid)
            self._triangulate_new(new)
            # Keyframes between the pair were waiting: register them now.
            for kf in self.kfs:
                if kf.map_T_cam is None and kf.kid > first.kid:
                    if self._register(kf).registered:
                        self._triangulate_new(kf)
            rep = self._window_adjust(new.kid, full=True)
            rep.status = 'initialised'
            return rep
        # No pair yet: drop keyframes too old to ever pair with the newest one.
        return StepReport(new.kid, False, 'waiting_for_initialisation')

    def _register(self, kf: _Keyframe) -> StepReport:
        import cv2
        use = self._usable(kf)
        self._thaw_tracks_seen_again(kf.track_ids)   # a second chance for an old keyframe (triangulate)
        have = self.points.contains_many(kf.track_ids) & use
        n = int(have.sum())
        if n < max(self.opt.min_pnp_inliers, 6):
            return StepReport(kf.kid, False, f'too_few_known_points ({n})')
        obj = self.points.get_many(kf.track_ids[have])
        img = kf.xn[have]
        prev = self.kfs[self.registered[-1]].map_T_cam
        cam_T_map = invert_T(prev)
        rvec0, _ = cv2.Rodrigues(cam_T_map[:3, :3])
        # No pose guess inside RANSAC: after a turn the previous pose is far off (and it is tried
        # separately below anyway).
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj, img, np.eye(3), None, iterationsCount=200, flags=cv2.SOLVEPNP_AP3P,
            reprojectionError=self.opt.pnp_threshold_px / self.camera.fx, confidence=0.999)
        if not ok or inl is None or len(inl) < self.opt.min_pnp_inliers:
            return StepReport(kf.kid, False, 'pnp_failed')
        inl = inl.ravel()
        # Over flat ground a minimal PnP sample can land on the mirror-image pose; refining from the
        # previous keyframe's pose as well and keeping the better-supported answer avoids it.
        thr = self.opt.pnp_threshold_px / self.camera.fx
        best = None
        # The continuation of the previous pose goes first and a jump must win clearly (10 % more
        # support): the mirror pose fits near-planar ground almost as well.
        for r0, t0 in ((rvec0, cam_T_map[:3, 3].reshape(3, 1)), (rvec, tvec)):
            r1, t1 = cv2.solvePnPRefineLM(obj[inl], img[inl], np.eye(3), None, r0.copy(), t0.copy())
            R1, _ = cv2.Rodrigues(r1)
            pc = obj @ R1.T + t1.ravel()
            z = np.where(pc[:, 2] > 1e-9, pc[:, 2], np.nan)
            e = np.linalg.norm(pc[:, :2] / z[:, None] - img, axis=1)
            ok = e < thr
            score = int(ok.sum())
            if best is None or score > 1.1 * best[0]:
                best = (score, R1, t1, ok)
        _, R, tvec, ok = best
        if ok.sum() < self.opt.min_pnp_inliers:
            return StepReport(kf.kid, False, 'pnp_failed')
        kf.map_T_cam = invert_T(make_T(R, tvec.ravel()))
        out = ~ok
        kf.active[np.flatnonzero(have)[out]] = False
        kf.reg_seq = len(self.registered)
        self.registered.append(kf.kid)
        for t in kf.track_ids[kf.active].tolist():
            self.track_kfs.setdefault(t, []).append(kf.kid)
        return StepReport(kf.kid, True, 'registered')

    def _reprojection_px(self, T: np.ndarray, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
        pc = (X - T[:3, 3]) @ T[:3, :3]
        z = np.where(pc[:, 2] > 1e-9, pc[:, 2], np.nan)
        proj = self.camera.normalized_to_pixel(pc[:, :2] / z[:, None])
        e = np.linalg.norm(proj - uv, axis=1)
        return np.where(np.isfinite(e), e, np.inf)

    def _gather(self, tracks, kids=None):
        """Active observations of `tracks` (in `kids`, default every registered keyframe that sees
        them): point slot, keyframe id, observation index; vectorised per keyframe."""
        tr = np.asarray(tracks, dtype=np.int64)
        if kids is None:
            ks = set()
            for t in tracks:
                ks.update(self.track_kfs.get(int(t), ()))
            kids = sorted(ks)
        if not len(tr) or not len(kids):
            return np.zeros(0, int), np.zeros(0, int), np.zeros(0, int)
        sorter = np.argsort(tr)
        tr_sorted = tr[sorter]
        slot, kid, oi = [], [], []
        for k in kids:
            kf = self.kfs[k]
            pos = np.clip(np.searchsorted(tr_sorted, kf.track_ids), 0, len(tr) - 1)
            m = kf.active & (tr_sorted[pos] == kf.track_ids)
            idx = np.flatnonzero(m)
            slot.append(sorter[pos[idx]])
            kid.append(np.full(len(idx), k))
            oi.append(idx)
        return np.concatenate(slot), np.concatenate(kid), np.concatenate(oi)

    def _poses_of(self, kid: np.ndarray) -> np.ndarray:
        uk, inv = np.unique(kid, return_inverse=True)
        return np.array([self.kfs[k].map_T_cam for k in uk]).reshape(-1, 4, 4)[inv]

    def _triangulate_tracks(self, tracks: list[int]) -> None:
        if not tracks:
            return
        for _ in range(2):   # second pass after dropping the observations that disagree
            slot, kid, oi = self._gather(tracks)
            if len(slot) == 0:
                return
            counts = np.bincount(slot, minlength=len(tracks))
            ks = list(dict.fromkeys(kid.tolist()))     # _gather groups by keyframe, in this order
            Ts = self._poses_of(kid)
            xn = np.concatenate([self.kfs[k].xn[oi[kid == k]] for k in ks])
            uv = np.concatenate([self.kfs[k].uv[oi[kid == k]] for k in ks])
            dirs = np.einsum('nij,nj->ni', Ts[:, :3, :3], np.column_stack([xn, np.ones(len(xn))]))
            X = triangulate_rays(Ts[:, :3, 3], dirs, slot, len(tracks))
            Xo = X[slot]
            pc = np.einsum('nji,nj->ni', Ts[:, :3, :3], Xo - Ts[:, :3, 3])
            z = np.where(pc[:, 2] > 1e-9, pc[:, 2], np.nan)
            err = np.linalg.norm(self.camera.normalized_to_pixel(pc[:, :2] / z[:, None]) - uv, axis=1)
            bad = ~(err <= self.opt.max_reprojection_px)
            if not bad.any() or _ == 1:
                break
            # Only drop observations of points that still have two good ones.
            good_counts = np.bincount(slot[~bad], minlength=len(tracks))
            drop = bad & (good_counts[slot] >= 2)
            if not drop.any():
                break
            for k, i, t in zip(kid[drop], oi[drop], np.asarray(tracks)[slot[drop]]):
                self._deactivate(int(k), int(i), int(t))
        # Triangulation angle: widest pair of rays, approximated by each ray against the mean ray.
        rays = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        mean = np.zeros((len(tracks), 3))
        np.add.at(mean, slot, rays)
        mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
        ang = np.degrees(np.arccos(np.clip(np.einsum('ij,ij->i', rays, mean[slot]), -1, 1)))
        max_ang = np.zeros(len(tracks))
        np.maximum.at(max_ang, slot, ang)
        worst = np.zeros(len(tracks))
        np.maximum.at(worst, slot, np.where(np.isfinite(err), err, 1e9))
        ok = (counts >= 2) & np.all(np.isfinite(X), axis=1) & (2 * max_ang >= self.opt.min_triangulation_angle_deg) \
            & (worst <= self.opt.max_reprojection_px)
        for s in np.flatnonzero(ok):
            self.points[int(tracks[s])] = X[s]

    def _triangulate_new(self, kf: _Keyframe) -> None:
        use = self._usable(kf)
        cand = kf.track_ids[use]
        tracks = [int(t) for t in cand[~self.points.contains_many(cand)]
                  if len(self.track_kfs.get(int(t), ())) >= 2]
        self._triangulate_tracks(tracks)
        # Existing points seen again: drop the observations that disagree with them.
        act = np.flatnonzero(use & kf.active)
        idx = act[self.points.contains_many(kf.track_ids[act])].tolist()
        if idx:
            X = self.points.get_many(kf.track_ids[idx])
            e = self._reprojection_px(kf.map_T_cam, X, kf.uv[idx])
            for i in np.asarray(idx)[e > 2 * self.opt.max_reprojection_px]:
                self._deactivate(kf.kid, int(i), int(kf.track_ids[i]))

    def _deactivate(self, kid: int, i: int, t: int) -> None:
        kf = self.kfs[kid]
        kf.active[i] = False
        lst = self.track_kfs.get(t)
        if lst and kid in lst:
            lst.remove(kid)
            if len(lst) < 2:
                self.points.pop(t, None)
        elif lst is None:
            # A frozen track keeps only its count (an active observation is always in its list).
            n = self.points.frozen_count_decrement(t)
            if n is not None and n < 2:
                self.points.pop(t, None)

    # --- georeference -------------------------------------------------------------------------

    def _try_georeference(self, force: bool = False) -> bool:
        """`force`: accept any non-collinear geometry (end of flight: nothing better will come)."""
        ks = [k for k in self.registered if self.kfs[k].fix_enu is not None]
        if len(ks) < max(self.opt.georef_min_keyframes, 3):
            return False
        src = np.array([self.kfs[k].map_T_cam[:3, 3] for k in ks])
        dst = np.array([self.kfs[k].fix_enu if self.kfs[k].antenna_offset is None
                        else self.kfs[k].fix_enu - self.kfs[k].antenna_offset for k in ks])
        sig = np.sqrt(np.median([np.trace(self.kfs[k].fix_cov) for k in ks]))
        sv = spread(dst)
        # A block made without GNSS drifts in scale along the line: tolerate ~2 % of its extent.
        thr = 4.0 * sig + np.linalg.norm(self.lever) + 0.05 + 0.02 * 2 * sv[0]
        res = similarity_ransac(src, dst, thr, self.rng,
                                min_spread_ratio=0.005 if force else self.opt.georef_min_spread_ratio)
        n_in = int(res.inliers.sum()) if res.ok else len(ks)
        side = spread(dst[res.inliers])[1] if res.ok else 0.0
        # The turn must be wide against the GNSS noise averaged over the fixes, or the roll about
        # the line is noise (the adjustment that follows refines it, but needs a fair start).
        if res.ok and (force or side >= 3.0 * sig / np.sqrt(n_in)):
            s = res.sim
            provisional = False
        elif self.georeferenced:
            return False    # provisional already; wait for the turn
        elif self.opt.assume_nadir and sv[0] > max(10.0 * sig, 5.0) and len(ks) >= 2 * self.opt.georef_min_keyframes:
            # Straight line: everything but the roll about it comes from GNSS; the roll from the
            # near-nadir camera. Provisional until the first turn.
            s = similarity_on_line(src, dst, np.array([self.kfs[k].map_T_cam[:3, 2] for k in ks]))
            provisional = True
        else:
            return False
        if self.georeferenced:   # provisional -> final: GNSS priors of the whole block fix the roll
            self.georef_provisional = False
            self.full_adjustment(iterations=self.opt.full_iterations, rounds=1)
            return True
        for k in self.registered:
            self.kfs[k].map_T_cam = s.apply_pose(self.kfs[k].map_T_cam)
        ids, P = self.points.arrays()
        if len(ids):
            self.points.set_many(ids, np.array([s.apply(p[None])[0] for p in P]))
        self.georeferenced = True
        self.georef_provisional = provisional
        self.full_adjustment(iterations=self.opt.full_iterations, rounds=1)
        return True

    # --- adjustment -----------------------------------------------------------------------------

    def _solve(self, free: list[int], fixed: list[int], tracks, iterations: int, refine: tuple = ()) -> StepReport:
        kids = list(free) + list(fixed)
        col = {k: j for j, k in enumerate(kids)}
        tracks = np.asarray(tracks, dtype=np.int64).ravel()
        tracks = tracks[self.points.contains_many(tracks)].tolist()
        slot, kid, oi = self._gather(tracks, kids)
        if len(slot) == 0:
            return StepReport(kids[-1] if kids else -1, True, 'nothing_to_adjust')
        fixed_mask = np.array([k not in set(free) for k in kids])
        if not self.georeferenced and not fixed_mask.any():
            fixed_mask[:2] = True     # gauge: no datum yet, hold the first two keyframes
        gk = [j for j, k in enumerate(kids) if self.georeferenced and not fixed_mask[j]
              and self.kfs[k].fix_enu is not None]
        pri = [(s, self.control[self.target_name(t)]) for s, t in enumerate(tracks)
               if t < 0 and not self._is_check(t)] if self.georeferenced else []
        prob = BundleProblem(
            camera=self.camera, map_T_cams=np.array([self.kfs[k].map_T_cam for k in kids]),
            points_map=self.points.get_many(tracks).reshape(-1, 3),
            obs_cam=np.concatenate([np.full(int(np.sum(kid == k)), col[k]) for k in kids]),
            obs_pt=np.concatenate([slot[kid == k] for k in kids]),
            obs_uv=np.concatenate([self.kfs[k].uv[oi[kid == k]] for k in kids]) if len(kids) else np.zeros((0, 2)),
            fixed_cams=fixed_mask, fixed_points=None,
            gnss_cam=np.array(gk, int) if gk else None,
            gnss_pos_map=np.array([self._gnss_target(self.kfs[kids[j]]) for j in gk]).reshape(-1, 3),
            gnss_cov_map=np.array([self.kfs[kids[j]].fix_cov for j in gk]).reshape(-1, 3, 3),
            lever_arm_cam_m=self.lever,
            point_priors_idx=np.array([s for s, _ in pri], int) if pri else None,
            point_priors_map=np.array([c.map_xyz for _, c in pri]).reshape(-1, 3),
            point_priors_sigma_m=np.array([c.sigma_m for _, c in pri]).reshape(-1, 3))
        res = _adjust(prob, self.opt.loss, self.opt.loss_scale_px, iterations, refine)
        if refine and res.status != 'failed':
            self.camera = res.camera   # self-calibration: every later step uses the refined intrinsics
        for j, k in enumerate(kids):
            if not fixed_mask[j]:
                self.kfs[k].map_T_cam = np.asarray(res.map_T_cams[j])
        if tracks:
            self.points.set_many(tracks, np.asarray(res.points_map))
        # Observations the robust loss down-weighted past the threshold are outliers: remove them.
        P = np.asarray(res.points_map)[slot]
        Ts = self._poses_of(kid)
        pc = np.einsum('nji,nj->ni', Ts[:, :3, :3], P - Ts[:, :3, 3])
        z = np.where(pc[:, 2] > 1e-9, pc[:, 2], np.nan)
        uv = prob.obs_uv
        err = np.linalg.norm(self.camera.normalized_to_pixel(pc[:, :2] / z[:, None]) - uv, axis=1)
        bad = ~(err <= self.opt.max_reprojection_px)
        if res.status == 'failed' or np.median(err[np.isfinite(err)]) > self.opt.max_reprojection_px:
            bad[:] = False   # not converged: residuals say nothing about outliers yet
        for k, i, s in zip(kid[bad], oi[bad], slot[bad]):
            t = tracks[s]
            if t < 0 and not self._is_check(t):
                continue   # a GCP observation is measured by hand: keep it, its prior holds it
            self._deactivate(int(k), int(i), int(t))
        good = ~bad
        rep = StepReport(kids[0], True, res.status, cost=float(res.final_cost),
                         reprojection_rms_px=float(np.sqrt(np.mean(err[good] ** 2))) if good.any() else float('nan'),
                         window_size=int((~fixed_mask).sum()))
        rep.gnss_rms_m = self.gnss_rms_m([kids[j] for j in gk])
        return rep

    def _gnss_target(self, kf: _Keyframe) -> np.ndarray:
        """The fix moved so that `C + map_R_cam @ lever` should meet it (exact offset when known)."""
        fix = kf.fix_enu - self.gnss_bias_enu
        if kf.antenna_offset is None:
            return fix
        return fix - kf.antenna_offset + kf.map_T_cam[:3, :3] @ self.lever

    def gnss_residuals(self, kids=None) -> dict:
        """Keyframe id -> ENU residual (m) of the adjusted antenna position minus the fix."""
        out = {}
        for k in (self.registered if kids is None else kids):
            kf = self.kfs[k]
            if kf.fix_enu is not None and kf.map_T_cam is not None:
                out[k] = kf.map_T_cam[:3, 3] + kf.map_T_cam[:3, :3] @ self.lever - self._gnss_target(kf)
        return out

    def gnss_rms_m(self, kids=None) -> float:
        r = list(self.gnss_residuals(kids).values())
        return float(np.sqrt(np.mean(np.sum(np.array(r) ** 2, axis=1)))) if r else float('nan')

    def _kf_tracks(self, k: int) -> np.ndarray:
        kf = self.kfs[k]
        t = kf.track_ids[kf.active]
        return t[self.points.contains_many(t)].astype(np.int64)

    def _window_adjust(self, kid: int, full: bool = False) -> StepReport:
        if full:
            return self.full_adjustment(iterations=self.opt.full_iterations, rounds=1)
        sel = select_window(self.registered, self.opt.window_size, {k: self._kf_tracks(k)
                                                                    for k in self.registered[-self.opt.window_size:]},
                            self.track_kfs, self.opt.max_fixed_keyframes)
        rep = self._solve(sel.free_kfs, sel.fixed_kfs, sel.track_ids, self.opt.window_iterations)
        rep.kid = kid
        return rep

    def full_adjustment(self, iterations: int | None = None, rounds: int = 2,
                        refine_intrinsics: tuple = ()) -> StepReport:
        """Adjust every registered keyframe and point; repeated so that removed outliers settle.

        refine_intrinsics (e.g. ('f', 'k1')) self-calibrates the shared camera in this adjustment.
        """
        rep = StepReport(-1, False, 'not_initialised')
        if not self.registered:
            return rep
        if not self.georeferenced and self._try_georeference(force=True):
            rounds = max(rounds - 1, 1)
        for _ in range(rounds):
            tracks = list(self.points)
            rep = self._solve(list(self.registered), [], tracks, iterations or self.opt.full_iterations,
                              refine_intrinsics)
        if self.opt.estimate_gnss_bias and self._n_gcps() >= 3:
            for _ in range(self.opt.bias_iterations):
                r = np.array(list(self.gnss_residuals().values()))
                if not len(r):
                    break
                # The residual mean is a fraction of the bias (the fixes still pull): iterate.
                step = np.mean(r, axis=0)
                self.gnss_bias_enu -= step
                rep = self._solve(list(self.registered), [], list(self.points), iterations or self.opt.full_iterations)
                if np.linalg.norm(step) < 0.005:
                    break
        if self.opt.spill_frozen:
            self.freeze()   # the adjustment read every keyframe back: spill the frozen ones again
        return rep

    # --- memory: freezing what can no longer enter a window ----------------------------------------

    def freeze(self) -> None:
        """Freeze the tracks whose newest observation is older than the window (plus a margin) and
        the keyframes that only observe frozen tracks; called every `freeze_every` keyframes.

        No future window can hold them: the free keyframes are the newest ones, and a fixed keyframe
        enters only through a point that a free keyframe observes. A tracker never reuses an id
        after its track ended; if a record does anyway, `_thaw_tracks_seen_again` undoes this.
        Keyframes with target (GCP) observations stay in memory: targets are seen again anywhere.
        """
        n_keep = self.opt.window_size + max(self.opt.freeze_margin_keyframes, 0)
        if len(self.registered) <= n_keep or self.freezing_stopped:
            return
        horizon = min(self.registered[-n_keep:])
        dead = [t for t, k in self.last_seen.items() if k < horizon]
        counts = []
        for t in dead:
            del self.last_seen[t]
            counts.append(len(self.track_kfs.pop(t, ())))
        self.points.freeze(dead, counts)
        if self._spill is None:
            self._spill = KeyframeSpill(self.opt.spill_dir or None)
        for kf in self.kfs[:horizon]:
            if not kf.frozen and not kf.has_targets and not any(t in self.last_seen for t in kf.track_ids.tolist()):
                kf.freeze(self._spill)

    def _thaw_tracks_seen_again(self, ids: np.ndarray) -> None:
        """Tracks of a new record that were frozen: restore their keyframe lists (in registration
        order, as they were built), points and keyframes, so the result is what it would have been."""
        if self._spill is None or self.freezing_stopped:
            return   # nothing was ever frozen / everything is back in memory
        ids = np.asarray(ids, np.int64)
        cand = ids[(ids >= 0) & (ids <= self._max_seen_id)]
        if not len(cand):
            return
        cand = np.array([t for t in cand.tolist() if t not in self.last_seen], np.int64)
        if not len(cand):
            return
        # A tracker's new ids are above every id seen so far: a lower unknown id costs a scan of
        # the block, and a source doing that repeatedly is not frozen any more (see below).
        self._thaw_keyframes += 1
        lists: dict[int, list] = {}
        for kf in self.kfs:
            if kf.id_hi < cand[0] or kf.id_lo > cand[-1]:
                continue
            tids, _, _, active = kf.peek()
            hit = np.isin(tids, cand)
            if not hit.any():
                continue
            if kf.frozen:
                kf._arrays()
            for t, a in zip(tids[hit].tolist(), active[hit].tolist()):
                self.last_seen[t] = max(self.last_seen.get(t, -1), kf.kid)
                if a and kf.reg_seq >= 0:
                    lists.setdefault(t, []).append(kf)
        for t, kfs in lists.items():
            self.track_kfs[t] = [kf.kid for kf in sorted(kfs, key=lambda kf: kf.reg_seq)]
            self.points.thaw(t)
        if self._thaw_keyframes >= self.opt.max_thaws:
            self._stop_freezing(f'track ids below the newest ones not in memory (ended tracks seen again?) '
                                f'in {self._thaw_keyframes} keyframes')

    def _stop_freezing(self, why: str) -> None:
        """Everything back in memory (same values, same order): from now on this block is not frozen."""
        self.freezing_stopped = why
        for kf in self.kfs:
            if kf.frozen:
                kf._arrays()
        ids = [t for t in self.points.ids().tolist() if self.points.is_frozen(t)]
        for t in ids:
            self.points.thaw(t)
        # Rebuild the keyframe lists of every track (frozen ones kept only their count).
        lists: dict[int, list] = {}
        for k in self.registered:
            kf = self.kfs[k]
            for t in kf.track_ids[kf.active].tolist():
                if t not in self.track_kfs:
                    lists.setdefault(t, []).append(kf)
        for t, kfs in lists.items():
            self.track_kfs[t] = [kf.kid for kf in sorted(kfs, key=lambda kf: kf.reg_seq)]
            self.last_seen.setdefault(t, max(kf.kid for kf in kfs))

    def memory_stats(self) -> dict:
        """What the triangulation holds: keyframes/points in memory and frozen, bytes spilled."""
        return {'keyframes': len(self.kfs), 'keyframes_in_memory': sum(not kf.frozen for kf in self.kfs),
                'points': len(self.points), 'points_in_memory': self.points.n_hot,
                'hot_tracks': len(self.track_kfs), 'frozen_points_mb': round(self.points.frozen_bytes / 1e6, 2),
                'spilled_mb': round(self._spill.bytes_on_disk / 1e6, 2) if self._spill else 0.0,
                'freezing_stopped': self.freezing_stopped}

    def set_control(self, control: list[ControlPoint]) -> None:
        """Surveyed targets in this block's map frame; may come after the first keyframes (a flight
        knows its origin only from the first fix): roles are looked up at every adjustment."""
        self.control = {c.name: c for c in control}

    def control_summary(self) -> dict:
        """GCPs and check points: how many were observed, how many GCPs constrain the block (triangulated,
        with their prior: georeferenced), and the RMS of the adjusted GCPs minus their survey (m)."""
        seen = [n for n in self._target_ids if n in self.control]
        gcps = [n for n in seen if not self._is_check(self._target_ids[n])]
        used = [n for n in gcps if self._target_ids[n] in self.points] if self.georeferenced else []
        r = np.array([self.points[self._target_ids[n]] - self.control[n].map_xyz for n in used]).reshape(-1, 3)
        n_gcps = sum(c.role == 'gcp' for c in self.control.values()) if self.opt.use_gcps else 0
        out = {'gcps': n_gcps, 'gcps_seen': len(gcps), 'gcps_used': len(used), 'checks_seen': len(seen) - len(gcps),
               'gcp_residual_rms_h_m': float('nan'), 'gcp_residual_rms_v_m': float('nan')}
        if len(r):
            out['gcp_residual_rms_h_m'] = float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1))))
            out['gcp_residual_rms_v_m'] = float(np.sqrt(np.mean(r[:, 2] ** 2)))
        return out

    def _n_gcps(self) -> int:
        return sum(1 for n, t in self._target_ids.items() if t in self.points and not self._is_check(t))

    # --- results ----------------------------------------------------------------------------------

    def poses(self) -> dict[int, np.ndarray]:
        return {k: self.kfs[k].map_T_cam for k in self.registered}

    def observations_of(self, tid: int):
        """(map_T_cams, uv) of one track in the registered keyframes (active or not)."""
        Ts, uvs = [], []
        for k in self.registered:
            kf = self.kfs[k]
            i = kf.index(tid)
            if i is not None:
                Ts.append(kf.map_T_cam)
                uvs.append(kf.uv[i])
        return Ts, np.array(uvs).reshape(-1, 2)

    def intersect_target(self, name: str):
        """Triangulate a target (check point) from the adjusted cameras: (xyz, n_images, rms_px)."""
        tid = self._target_ids.get(name)
        if tid is None:
            return None
        Ts, uv = self.observations_of(tid)
        if len(Ts) < 2:
            return None
        return intersect_point(self.camera, np.array(Ts), uv)


def intersect_point(camera: PinholeCamera, map_T_cams: np.ndarray, uv: np.ndarray):
    """Multi-ray intersection refined by Gauss-Newton on the reprojection error (cameras fixed)."""
    xn = camera.pixel_to_normalized(uv)
    dirs = np.einsum('nij,nj->ni', map_T_cams[:, :3, :3], np.column_stack([xn, np.ones(len(xn))]))
    X = triangulate_rays(map_T_cams[:, :3, 3], dirs, np.zeros(len(xn), int), 1)[0]
    if not np.all(np.isfinite(X)):
        return None

    def res(X):
        pc = np.einsum('nji,nj->ni', map_T_cams[:, :3, :3], X[None] - map_T_cams[:, :3, 3])
        return (camera.normalized_to_pixel(pc[:, :2] / pc[:, 2:3]) - uv).ravel()

    for _ in range(10):
        r = res(X)
        J = np.column_stack([(res(X + d) - r) / 1e-6 for d in np.eye(3) * 1e-6])
        dx = np.linalg.lstsq(J, -r, rcond=None)[0]
        X = X + dx
        if np.linalg.norm(dx) < 1e-7:
            break
    r = res(X).reshape(-1, 2)
    return X, len(uv), float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))
