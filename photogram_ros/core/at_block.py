"""The aerial triangulation's block: its keyframes, tie points, targets and manual tie points, the camera they
share, and whether it stands in the map frame; with the queries everything else reads it through.

`Block` holds the state that the adjuster (core/incremental.py `IncrementalAT`) grows keyframe by keyframe: the
keyframes (core/at_store.py `Keyframe`) in arrival order, the oriented ones in order of registration, the tie points
(`PointStore`, {track id: map ENU m}), the hot tracks' keyframes, the targets by name (negative track ids) with the
surveyed control and the manual tie points, and the freezing of what can no longer enter a window
(core/at_freeze.py). Readers outside core/ use the public queries (`keyframe`, `oriented`, `point`, ...), never the
containers.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from photogram_ros.core.at_freeze import Freezer, FreezeOptions
from photogram_ros.core.at_geometry import intersect_point, triangulate_rays
from photogram_ros.core.at_problem import ProblemOptions
from photogram_ros.core.at_store import Keyframe, PointStore
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.core.part_options import check, declared, nested
from photogram_ros.errors import ConfigError, DataError
from photogram_ros.params import param


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
    # The camera's orientation in map ENU (3x3, camera -> map) from the autopilot's attitude and the camera's
    # mount or gimbal, before any adjustment; None when unknown. A prior, not a measurement of the block.
    map_R_cam_prior: np.ndarray | None = None


@dataclass
class ControlPoint:
    name: str
    map_xyz: np.ndarray             # surveyed, map ENU (m)
    sigma_m: np.ndarray             # (3,) E, N, U
    role: str                       # 'gcp' (used) or 'check' (never used)


@dataclass(frozen=True)
class BlockOptions:
    """The block's options (`Block`): which targets are GCPs in use, what a new point needs, and its freezing
    (`freeze`)."""
    min_triangulation_angle_deg: float = param(1.5, 'a new point needs rays at least this far apart, deg',
                                               min=0.0, max=90.0)
    max_reprojection_px: float = declared(ProblemOptions, 'max_reprojection_px')
    use_gcps: bool = param(True, 'surveyed GCPs enter the adjustment as point priors (off: every target is a '
                                 'check point)')
    spill_frozen: bool = param(True, 'long flights: tie points and keyframes that can no longer enter a window '
                                     'leave memory (compact arrays, keyframe observations on disk); same results')
    freeze: FreezeOptions = nested(FreezeOptions)

    def __post_init__(self):
        check(self)


class Block:
    """The block's keyframes, points, targets and ties (see the module's doc); `opt`: its options."""

    def __init__(self, camera: PinholeCamera, opt: BlockOptions, control: list[ControlPoint] | None = None, ties=()):
        self.opt = opt
        self.camera = camera
        # The camera as given: a stepwise self-calibration starts its candidates from these values.
        self.camera_given = camera
        self.kfs: list[Keyframe] = []
        self.registered: list[int] = []
        self.points = PointStore()                  # dict-like {track id: (3,) map ENU}
        self.track_kfs: dict[int, list[int]] = {}    # hot tracks: registered keyframes with an active observation
        self.freezer = Freezer(opt.freeze)
        self.georeferenced = False
        self.provisional = False
        self.control = {c.name: c for c in (control or [])}
        # Manual tie points by name: targets without coordinates that build geometry (not check points).
        self.ties: set[str] = set(ties)
        self.target_ids: dict[str, int] = {}

    def hold_given_focal(self) -> None:
        """The focal length (fx, fy) back at its given value; the caller's adjustments then hold it."""
        self.camera = replace(self.camera, fx=self.camera_given.fx, fy=self.camera_given.fy)

    # --- growing it ---------------------------------------------------------------------------------

    def add(self, kf: Keyframe) -> None:
        """A new keyframe (not oriented yet), its tracks seen again first brought back from the frozen ones."""
        self.thaw_seen_again(kf.track_ids)
        self.kfs.append(kf)
        self.freezer.seen(kf.kid, kf.track_ids)

    def enrol(self, kf: Keyframe) -> None:
        """Keyframe kf, oriented, joins the registered ones with its active observations."""
        kf.reg_seq = len(self.registered)
        self.registered.append(kf.kid)
        for t in kf.track_ids[kf.active].tolist():
            self.track_kfs.setdefault(t, []).append(kf.kid)

    def give_up_oriented(self) -> int:
        """Every oriented keyframe back to not oriented, every point and hot track dropped (a block before a break
        that its GNSS could not place); returns how many keyframes were oriented."""
        n = len(self.registered)
        for k in self.registered:
            self.kfs[k].map_T_cam = None
        self.registered, self.points, self.track_kfs = [], PointStore(), {}
        self.freezer = Freezer(self.opt.freeze)
        return n

    def add_ties(self, names) -> None:
        """Make targets `names` manual tie points."""
        self.ties |= set(names)

    # --- queries (what readers outside core/ use) -----------------------------------------------------

    @property
    def n_keyframes(self) -> int:
        """Keyframes received, oriented or not."""
        return len(self.kfs)

    @property
    def n_oriented(self) -> int:
        return len(self.registered)

    @property
    def n_points(self) -> int:
        return len(self.points)

    def keyframe(self, kid: int) -> Keyframe:
        """Keyframe `kid` (its id is its index in arrival order; negative counts from the newest)."""
        return self.kfs[kid]

    def keyframes(self, last: int | None = None) -> list[Keyframe]:
        """Every keyframe in arrival order (`kfs[-last:]` when `last` is given)."""
        return list(self.kfs if last is None else self.kfs[-last:])

    def oriented(self, last: int | None = None) -> list[int]:
        """Ids of the oriented keyframes in order of registration (`[-last:]` of them when `last` is given)."""
        return list(self.registered if last is None else self.registered[-last:])

    def last_oriented(self) -> Keyframe | None:
        """The keyframe oriented last, None before the first."""
        return self.kfs[self.registered[-1]] if self.registered else None

    def oriented_names(self) -> list[str]:
        return [self.kfs[k].name for k in self.registered]

    def oriented_poses(self) -> list[np.ndarray]:
        """(4, 4) map_T_cam of the oriented keyframes, in order of registration."""
        return [self.kfs[k].map_T_cam for k in self.registered]

    def poses_by_name(self) -> dict:
        """Photo name -> (4, 4) map_T_cam of every oriented keyframe."""
        return {self.kfs[k].name: self.kfs[k].map_T_cam for k in self.registered}

    def has_point(self, tid: int) -> bool:
        return tid in self.points

    def point(self, tid: int) -> np.ndarray:
        """(3,) map ENU (m) of track `tid`'s point (KeyError without one)."""
        return self.points[tid]

    def point_ids(self) -> list[int]:
        """Track ids of every point, in the order they were made."""
        return list(self.points)

    def point_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """((M,) track ids, (M, 3) map ENU m) of every point."""
        return self.points.arrays()

    def has_points(self, ids) -> np.ndarray:
        """(n,) bool: which of the track ids have a point."""
        return self.points.contains_many(ids)

    def points_of(self, ids) -> np.ndarray:
        """(n, 3) map ENU (m) of the points of track ids that have one."""
        return self.points.get_many(ids)

    def tie_point_cloud(self) -> np.ndarray:
        """(M, 3) map ENU (m) of the tracker's tie points (no targets)."""
        return np.array([self.points[t] for t in self.points if t >= 0]).reshape(-1, 3)

    def tie_point_ids(self, hot: bool = False) -> np.ndarray:
        """(M,) int64 tracker track ids (>= 0) with a point, in the order they were made; `hot`: only the hot
        tracks (those the window and its margin still observe: a bounded set on a long flight), in the order
        they became hot."""
        ids = np.fromiter((t for t in (self.track_kfs if hot else self.points) if t >= 0), np.int64)
        return ids[self.points.contains_many(ids)] if len(ids) else ids

    def tie_names(self) -> list[str]:
        return sorted(self.ties)

    def control_points(self) -> dict:
        """Target name -> ControlPoint of the surveyed control (a copy)."""
        return dict(self.control)

    # --- the block's own work --------------------------------------------------------------------------

    def new_target_track(self, name: str) -> int:
        if name not in self.target_ids:
            self.target_ids[name] = -(len(self.target_ids) + 1)   # tracker ids are >= 0
        return self.target_ids[name]

    def target_track(self, name: str) -> int | None:
        """Track id (negative) of a target by name, None while no keyframe has observed it."""
        return self.target_ids.get(name)

    def target_name(self, tid: int) -> str:
        for n, t in self.target_ids.items():
            if t == tid:
                return n
        return ''

    def is_check(self, tid: int) -> bool:
        """A target track that never enters the adjustment: a check point, a target the control does
        not name, or any target with use_gcps off. Tracker tracks (tid >= 0) and manual tie points are not."""
        if tid >= 0:
            return False
        name = self.target_name(tid)
        if name in self.ties:
            return False
        c = self.control.get(name)
        return c is None or c.role != 'gcp' or not self.opt.use_gcps

    def is_tie(self, tid: int) -> bool:
        """A manual tie point's track."""
        return tid < 0 and self.target_name(tid) in self.ties

    def tie_mask(self, tids: np.ndarray) -> np.ndarray:
        """(n,) bool: which of the track ids are manual tie points."""
        tids = np.asarray(tids, np.int64)
        out = np.zeros(len(tids), bool)
        if self.ties:
            neg = np.flatnonzero(tids < 0)
            out[neg] = [self.is_tie(int(t)) for t in tids[neg]]
        return out

    def hand_measured(self, tid: int) -> bool:
        """A target observation kept through outlier removal: a GCP's (its prior holds it) or an MTP's."""
        return tid < 0 and not self.is_check(tid)

    def usable(self, kf: Keyframe) -> np.ndarray:
        """Observations that may build geometry: active and not a check point."""
        m = kf.active.copy()
        neg = kf.track_ids < 0
        if neg.any():
            m[neg] &= ~np.array([self.is_check(int(t)) for t in kf.track_ids[neg]])
        return m

    def kf_tracks(self, k: int) -> np.ndarray:
        kf = self.kfs[k]
        t = kf.track_ids[kf.active]
        return t[self.points.contains_many(t)].astype(np.int64)

    def gcp_names(self) -> frozenset:
        """The GCPs the adjustment uses: targets triangulated in the block that are not check points."""
        return frozenset(n for n, t in self.target_ids.items() if t in self.points and not self.is_check(t))

    def n_gcps(self) -> int:
        return len(self.gcp_names())

    def gcp_pairs(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(triangulated point, surveyed map position) of every GCP with a point in the block (not check
        points, not manual tie points)."""
        return [(self.points[t], self.control[n].map_xyz) for n, t in self.target_ids.items()
                if t in self.points and not self.is_check(t) and not self.is_tie(t)]

    def gcps_in_block(self) -> int:
        """How many GCPs have a point in the block (the datum it has besides its GNSS)."""
        return len(self.gcp_pairs())

    def gcps_in_height(self) -> list[str]:
        """The GCPs used whose heights the adjustment uses (not those used horizontally only: their vertical
        sigma is HORIZONTAL_ONLY_SIGMA_V_M)."""
        return sorted(n for n in self.gcp_names() if self.control[n].sigma_m[2] < 1.0)

    def xn(self, kf: Keyframe, idx) -> np.ndarray:
        """Undistorted normalised coordinates of kf's observations `idx` with the current camera: those
        stored with the keyframe (made with the camera as given) until a self-calibration changes it."""
        if self.camera == self.camera_given:
            return kf.xn[idx]
        return self.camera.pixel_to_normalized(kf.uv[idx])

    def reprojection_px(self, map_T_cam: np.ndarray, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(n,) pixel distance between the points X (n, 3, map) seen from map_T_cam and uv (n, 2
        distorted pixels); inf behind the camera."""
        T = map_T_cam
        pc = (X - T[:3, 3]) @ T[:3, :3]
        z = np.where(pc[:, 2] > 1e-9, pc[:, 2], np.nan)
        proj = self.camera.normalized_to_pixel(pc[:, :2] / z[:, None])
        e = np.linalg.norm(proj - uv, axis=1)
        return np.where(np.isfinite(e), e, np.inf)

    def gather(self, tracks, kids=None):
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

    def poses_of(self, kid: np.ndarray) -> np.ndarray:
        uk, inv = np.unique(kid, return_inverse=True)
        return np.array([self.kfs[k].map_T_cam for k in uk]).reshape(-1, 4, 4)[inv]

    def triangulate_tracks(self, tracks: list[int]) -> None:
        if not tracks:
            return
        for _ in range(2):   # second pass after dropping the observations that disagree
            slot, kid, oi = self.gather(tracks)
            if len(slot) == 0:
                return
            counts = np.bincount(slot, minlength=len(tracks))
            ks = list(dict.fromkeys(kid.tolist()))     # _gather groups by keyframe, in this order
            Ts = self.poses_of(kid)
            xn = np.concatenate([self.xn(self.kfs[k], oi[kid == k]) for k in ks])
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
            drop &= np.array([not self.is_tie(int(t)) for t in np.asarray(tracks)[slot]])
            if not drop.any():
                break
            for k, i, t in zip(kid[drop], oi[drop], np.asarray(tracks)[slot[drop]]):
                self.deactivate(int(k), int(i), int(t))
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

    def triangulate_new(self, kf: Keyframe) -> None:
        use = self.usable(kf)
        cand = kf.track_ids[use]
        tracks = [int(t) for t in cand[~self.points.contains_many(cand)]
                  if len(self.track_kfs.get(int(t), ())) >= 2]
        self.triangulate_tracks(tracks)
        # Existing points seen again: drop the observations that disagree with them.
        act = np.flatnonzero(use & kf.active)
        idx = act[self.points.contains_many(kf.track_ids[act])].tolist()
        if idx:
            X = self.points.get_many(kf.track_ids[idx])
            e = self.reprojection_px(kf.map_T_cam, X, kf.uv[idx])
            for i in np.asarray(idx)[e > 2 * self.opt.max_reprojection_px]:
                if not self.is_tie(int(kf.track_ids[i])):
                    self.deactivate(kf.kid, int(i), int(kf.track_ids[i]))

    def deactivate(self, kid: int, i: int, t: int) -> None:
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

    def retriangulate_ties(self) -> list[str]:
        """Each manual tie point intersected afresh from every observation in the oriented keyframes (rays
        refined on their reprojection, core `intersect_point`), its observations active again: a point made
        from the photos of one part before another joined, or from a pose that later moved, is stale.
        Returns the names with a point."""
        out = []
        for name in sorted(self.ties):
            tid = self.target_ids.get(name)
            if tid is None:
                continue
            kids = [k for k in self.registered if not self.kfs[k].frozen and self.kfs[k].index(tid) is not None]
            if len(kids) < 2:
                continue
            Ts = np.array([self.kfs[k].map_T_cam for k in kids])
            uv = np.array([self.kfs[k].uv[self.kfs[k].index(tid)] for k in kids], float)
            hit = intersect_point(self.camera, Ts, uv)
            if hit is None or not np.all(np.isfinite(hit[0])):
                continue
            depth = np.einsum('ni,ni->n', hit[0][None] - Ts[:, :3, 3], Ts[:, :3, 2])
            if np.any(depth <= 0):
                continue
            frozen = self.points.is_frozen(tid)   # a frozen track keeps only its count: its point moves alone
            self.points[tid] = hit[0]
            out.append(name)
            if frozen:
                continue
            lst = self.track_kfs.setdefault(tid, [])
            for k in kids:
                self.kfs[k].active[self.kfs[k].index(tid)] = True
                if k not in lst:
                    lst.append(k)
        return out

    def triangulate_targets(self, names) -> list[str]:
        """Points for the GCPs among `names` from their active observations in the registered keyframes:
        a target held as a check point builds no geometry, so a GCP admitted later (in flight, once its
        survey agrees with the block) gets its point, and its prior, here. Returns the names with a point."""
        tids = [self.target_ids[n] for n in names if n in self.target_ids]
        self.triangulate_tracks([t for t in tids if not self.is_check(t) and t not in self.points])
        return [n for n in names if self.target_ids.get(n) in self.points]

    def drop_target_observation(self, kid: int, name: str) -> bool:
        """Take keyframe `kid`'s observation of target `name` out of the adjustment (a detection the
        control vetting rejected); False when the keyframe has none."""
        tid = self.target_ids.get(name)
        i = self.kfs[kid].index(tid) if tid is not None and 0 <= kid < len(self.kfs) else None
        if i is None:
            return False
        self.deactivate(kid, i, tid)
        return True

    def set_control(self, control: list[ControlPoint]) -> None:
        """Surveyed targets in this block's map frame; may come after the first keyframes (a flight
        knows its origin only from the first fix): roles are looked up at every adjustment."""
        self.control = {c.name: c for c in control}

    def control_summary(self) -> dict:
        """GCPs and check points: how many were observed, how many GCPs constrain the block (triangulated,
        with their prior: georeferenced), and the RMS of the adjusted GCPs minus their survey (m)."""
        seen = [n for n in self.target_ids if n in self.control]
        gcps = [n for n in seen if not self.is_check(self.target_ids[n])]
        used = [n for n in gcps if self.target_ids[n] in self.points] if self.georeferenced else []
        r = np.array([self.points[self.target_ids[n]] - self.control[n].map_xyz for n in used]).reshape(-1, 3)
        n_gcps = sum(c.role == 'gcp' for c in self.control.values()) if self.opt.use_gcps else 0
        out = {'gcps': n_gcps, 'gcps_seen': len(gcps), 'gcps_used': len(used), 'checks_seen': len(seen) - len(gcps),
               'gcp_residual_rms_h_m': float('nan'), 'gcp_residual_rms_v_m': float('nan')}
        if len(r):
            out['gcp_residual_rms_h_m'] = float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1))))
            out['gcp_residual_rms_v_m'] = float(np.sqrt(np.mean(r[:, 2] ** 2)))
        return out

    def fix_sigma_enu_m(self) -> np.ndarray:
        """(3,) E, N, U sigma (m) of the oriented keyframes' fixes, the median: how well the GNSS alone
        places the block (10 m each without a fix)."""
        cov = [self.kfs[k].fix_cov for k in self.registered if self.kfs[k].fix_cov is not None]
        if not cov:
            return np.full(3, 10.0)
        return np.sqrt(np.median([np.diag(c) for c in cov], axis=0))

    def poses(self) -> dict[int, np.ndarray]:
        return {k: self.kfs[k].map_T_cam for k in self.registered}

    def keyframe_points(self, kid: int) -> np.ndarray:
        """(N, 3) map ENU (m) of the tie points keyframe `kid` observes (active observations)."""
        return self.points.get_many(self.kf_tracks(kid)).reshape(-1, 3)

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
        tid = self.target_ids.get(name)
        if tid is None:
            return None
        Ts, uv = self.observations_of(tid)
        if len(Ts) < 2:
            return None
        return intersect_point(self.camera, np.array(Ts), uv)

    @property
    def freezing_stopped(self) -> str:
        """Why this block is no longer frozen ('' while it is)."""
        return self.freezer.stopped

    def freeze(self) -> None:
        """Freeze the tracks and keyframes that can no longer enter a window; called every
        `freeze_every` keyframes (and after a full adjustment) when `spill_frozen`."""
        self.freezer.freeze(self.kfs, self.registered, self.track_kfs, self.points)

    def thaw_seen_again(self, ids: np.ndarray) -> None:
        self.freezer.thaw_seen_again(ids, self.kfs, self.registered, self.track_kfs, self.points)

    def memory_stats(self) -> dict:
        """What the triangulation holds: keyframes/points in memory and frozen, bytes spilled."""
        return {'keyframes': len(self.kfs), 'keyframes_in_memory': sum(not kf.frozen for kf in self.kfs),
                'points': len(self.points), 'points_in_memory': self.points.n_hot,
                'hot_tracks': len(self.track_kfs), 'frozen_points_mb': round(self.points.frozen_bytes / 1e6, 2),
                'spilled_mb': round(self.freezer.spilled_bytes / 1e6, 2),
                'freezing_stopped': self.freezing_stopped}

    def seed(self, origin, records: list, map_T_cam: dict, point_ids, points_map_m, target_uv: dict,
                        gate_px: float | None = None) -> dict:
        """Make this empty adjuster hold the merged block, ready for its `full_adjustment`.

        records: core/incremental.py KeyframeRecord of every photo of the block (in order); map_T_cam: photo name
        -> (4, 4) merged pose (map ENU, camera to map; a photo without one is a keyframe not oriented);
        point_ids / points_map_m: (M,) track ids and (M, 3) map ENU m of the merged tie points; target_uv: photo
        name -> {target name: (u, v) px} of the GCP (and manual tie point) observations the adjustment takes
        (the records' own target_uv are not read). A merged point's observation in an oriented photo that
        reprojects further than `gate_px` (None: self.opt.max_reprojection_px x 2, as a new keyframe's check of the
        points it sees again) is left inactive; a point with fewer than 2 active observations left is not
        kept. The GCPs the observations name are intersected from the merged cameras (`triangulate_targets`).
        The block is georeferenced for good (the merged block is in the map frame of its sub-blocks' GNSS and
        GCPs). Returns {'keyframes', 'oriented', 'points', 'observations', 'observations_left_out', 'gcps'}.
        Keyframes come in as `add_keyframe` and the resection (core/at_register.py) would make them, with poses and points already known."""
        if self.kfs:
            raise DataError(f'seed needs an empty adjuster; it holds {len(self.kfs)} keyframes')
        if origin is None:
            raise DataError('seed needs an adjuster with its map origin (the block\'s)')
        if self.opt.spill_frozen:
            raise ConfigError('seed needs an adjuster with spill_frozen off: its keyframes do not come '
                              'through add_keyframe, which the freezing follows')
        ids_m = np.asarray(point_ids, np.int64).reshape(-1)
        P = np.asarray(points_map_m, float).reshape(-1, 3)
        if len(ids_m) != len(P):
            raise DataError(f'seed: {len(ids_m)} point ids but {len(P)} points')
        order = np.argsort(ids_m)
        ids_sorted, P_sorted = ids_m[order], P[order]
        gate_px = 2.0 * self.opt.max_reprojection_px if gate_px is None else float(gate_px)
        n_obs = n_out = 0
        for rec in records:
            ids = np.asarray(rec.track_ids, np.int64).ravel()
            uv = np.asarray(rec.uv, float).reshape(-1, 2)
            if len(ids) != len(uv):
                raise DataError(f'photo {rec.name}: {len(ids)} track ids but {len(uv)} pixel positions')
            tuv = target_uv.get(rec.name, {})
            if tuv:
                ids = np.concatenate([ids, [self.new_target_track(n) for n in tuv]])
                uv = np.vstack([uv, np.asarray(list(tuv.values()), float).reshape(-1, 2)])
            ids, first = np.unique(ids, return_index=True)
            uv = uv[first]
            fix_enu = fix_cov = None
            if rec.fix is not None:
                fix_enu = np.asarray(origin.geodetic_to_enu(rec.fix.lat_deg, rec.fix.lon_deg, rec.fix.h_m), float)
                fix_cov = np.asarray(rec.fix.cov_enu_m2, float).reshape(3, 3)
            active = np.ones(len(ids), bool)
            kf = Keyframe(len(self.kfs), int(rec.stamp_ns), rec.name or str(rec.stamp_ns), ids, uv,
                          self.camera.pixel_to_normalized(uv), active, fix_enu, fix_cov)
            if rec.antenna_offset_map_m is not None:
                kf.antenna_offset = np.asarray(rec.antenna_offset_map_m, float).reshape(3)
            self.kfs.append(kf)
            T = map_T_cam.get(kf.name)
            if T is None:
                continue
            kf.map_T_cam = np.array(T, float)
            kf.reg_seq = len(self.registered)
            self.registered.append(kf.kid)
            pos = np.clip(np.searchsorted(ids_sorted, ids), 0, max(len(ids_sorted) - 1, 0))
            has = (ids_sorted[pos] == ids) if len(ids_sorted) else np.zeros(len(ids), bool)
            if has.any():
                e = self.reprojection_px(kf.map_T_cam, P_sorted[pos[has]], uv[has])
                far = ~(e <= gate_px)
                active[np.flatnonzero(has)[far]] = False
                n_obs += int(has.sum())
                n_out += int(far.sum())
            for t in ids[active].tolist():
                self.track_kfs.setdefault(t, []).append(kf.kid)
        keep = np.array([len(self.track_kfs.get(int(t), ())) >= 2 for t in ids_m], bool)
        if keep.any():
            self.points.set_many(ids_m[keep], P[keep])
        self.georeferenced = True
        self.provisional = False
        gcps = self.triangulate_targets(sorted({n for o in target_uv.values() for n in o}))
        return {'keyframes': len(self.kfs), 'oriented': len(self.registered), 'points': int(keep.sum()),
                'observations': n_obs, 'observations_left_out': n_out, 'gcps': gcps}

