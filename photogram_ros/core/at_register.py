"""How a keyframe joins the block (core/at_block.py): the first pair from their relative pose, then each new one
by resection against the block's points (RANSAC, refined from the previous pose too: over flat ground a minimal
sample can land on the mirror-image pose), or else by its relative pose to the oriented keyframe it shares most
tracks with (scaled by the known points it sees or by GNSS), or with a georeferenced block and a fix, by the
homography's rotation and the fix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photogram_ros.core.at_problem import ProblemOptions, StepReport
from photogram_ros.core.at_store import Keyframe
from photogram_ros.core.at_two_view import TwoViewOptions, two_view_pose
from photogram_ros.core.part_options import check, declared, nested
from photogram_ros.core.rotations import invert_T, make_T
from photogram_ros.core.two_view import relative_pose, scene_facing
from photogram_ros.params import param


@dataclass(frozen=True)
class RegistrationOptions:
    """The options of orienting keyframes (`Registration`): the first pair, resection, the relative fallback and
    its two-view gates (`two_view`)."""
    window_size: int = declared(ProblemOptions, 'window_size')
    min_init_inliers: int = param(30, 'tie points (and relative-pose inliers) the first two keyframes need to start',
                                  min=8, max=100000)
    min_init_angle_deg: float = param(2.0, 'median ray angle of the first two keyframes, deg (a shorter baseline '
                                           'waits for a later keyframe)', min=0.0, max=60.0)
    pnp_threshold_px: float = declared(TwoViewOptions, 'pnp_threshold_px')
    min_pnp_inliers: int = param(12, 'a new keyframe registers with at least this many resection inliers',
                                 min=4, max=100000)
    relative_fallback: bool = param(True, 'a keyframe that resection cannot orient (too few known points: photo-rate '
                                          'input, a break) is oriented from its relative pose to the registered '
                                          'keyframe it shares most tracks with, scaled by the known points it sees '
                                          'or by GNSS', )
    min_relative_inliers: int = param(25, 'relative-pose inliers that fallback needs', min=8, max=100000)
    assume_nadir: bool = declared(TwoViewOptions, 'assume_nadir')
    min_facing: float = declared(TwoViewOptions, 'min_facing')
    two_view: TwoViewOptions = nested(TwoViewOptions)

    def __post_init__(self):
        check(self)


class Registration:
    """Orienting keyframes of `block` with its GNSS datum `datum` (the lever arm, the bias), for the options
    `opt`; what it orients joins the block (`Block.enrol`)."""

    def __init__(self, block, datum, opt: RegistrationOptions):
        self.block, self.datum, self.opt = block, datum, opt
        self.two_view_oriented: dict[int, str] = {}   # keyframes oriented from two views: {kid: how (`two_view`)}

    def faces_scene(self, res) -> bool:
        """A relative pose's tie points lie in front of camera 1 on a plane it looks at (|cos| of the plane's
        normal to the optical axis >= min_facing); always true without assume_nadir."""
        if not self.opt.assume_nadir:
            return True
        return scene_facing(res.points_cam1[res.inliers]) >= self.opt.min_facing

    def initialise(self) -> int | None:
        """The block's first two keyframes: of the keyframes so far, the one that pairs best with the newest (most
        relative-pose inliers at enough parallax, facing the scene) starts the block with it, and the keyframes
        waiting are registered against them. Returns the newest keyframe's id, None while no pair is found (the
        caller adjusts the block in full)."""
        new = self.block.kfs[-1]
        rows_new = np.flatnonzero(self.block.usable(new))
        cands = []
        for first in self.block.kfs[:-1]:
            rows_first = np.flatnonzero(self.block.usable(first))
            ids, i1, i2 = np.intersect1d(first.track_ids[rows_first], new.track_ids[rows_new], return_indices=True)
            i1, i2 = rows_first[i1], rows_new[i2]
            if len(ids) < self.opt.min_init_inliers:
                continue
            thr = self.opt.pnp_threshold_px / self.block.camera.fx
            res = relative_pose(self.block.xn(first, i1), self.block.xn(new, i2), thr, self.opt.min_init_inliers)
            if not res.ok or res.median_angle_deg < self.opt.min_init_angle_deg or not self.faces_scene(res):
                continue
            score = int(res.inliers.sum()) * min(1.0, res.median_angle_deg / (2 * self.opt.min_init_angle_deg))
            cands.append((score, first, res))
        if cands:
            # The pair with the most inliers at enough parallax (not merely the oldest that passes).
            _, first, res = max(cands, key=lambda c: c[0])
            first.map_T_cam = np.eye(4)
            new.map_T_cam = invert_T(res.cam2_T_cam1)
            self.block.registered = [first.kid, new.kid]
            first.reg_seq, new.reg_seq = 0, 1
            for kf in (first, new):
                for t in kf.track_ids[kf.active].tolist():
                    self.block.track_kfs.setdefault(t, []).append(kf.kid)
            self.block.triangulate_new(new)
            # Keyframes between (and before) the pair were waiting: register them now.
            self.register_waiting()
            return new.kid
        return None

    def register_waiting(self) -> int:
        """Every keyframe without a pose tried again (resection, then the relative fallback), in passes until a
        pass orients none: a keyframe that shares tracks only with another waiting one (a chain 0 -> 1 -> the
        block) is oriented once that one is. Returns how many were oriented."""
        n, progress = 0, True
        while progress:
            progress = False
            for kf in self.block.kfs:
                if kf.map_T_cam is None and (self.resect(kf).registered
                                             or (self.opt.relative_fallback and self.relative(kf).registered)):
                    self.block.triangulate_new(kf)
                    n, progress = n + 1, True
        return n

    def resect(self, kf: Keyframe) -> StepReport:
        import cv2
        use = self.block.usable(kf)
        self.block.thaw_seen_again(kf.track_ids)   # a second chance for an old keyframe (triangulate)
        have = self.block.points.contains_many(kf.track_ids) & use
        n = int(have.sum())
        if n < max(self.opt.min_pnp_inliers, 6):
            return StepReport(kf.kid, False, f'too_few_known_points ({n})')
        obj = self.block.points.get_many(kf.track_ids[have])
        img = self.block.xn(kf, have)
        prev = self.block.kfs[self.block.registered[-1]].map_T_cam
        cam_T_map = invert_T(prev)
        rvec0, _ = cv2.Rodrigues(cam_T_map[:3, :3])
        # No pose guess inside RANSAC: after a turn the previous pose is far off (and it is tried
        # separately below anyway).
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj, img, np.eye(3), None, iterationsCount=200, flags=cv2.SOLVEPNP_AP3P,
            reprojectionError=self.opt.pnp_threshold_px / self.block.camera.fx, confidence=0.999)
        if not ok or inl is None or len(inl) < self.opt.min_pnp_inliers:
            return StepReport(kf.kid, False, 'pnp_failed')
        inl = inl.ravel()
        # Over flat ground a minimal PnP sample can land on the mirror-image pose; refining from the
        # previous keyframe's pose as well and keeping the better-supported answer avoids it.
        thr = self.opt.pnp_threshold_px / self.block.camera.fx
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
        out = ~ok & ~self.block.tie_mask(kf.track_ids[have])
        kf.active[np.flatnonzero(have)[out]] = False
        self.block.enrol(kf)
        return StepReport(kf.kid, True, 'registered')

    def gnss_tolerance_m(self, kf: Keyframe) -> float | None:
        """How far kf's antenna may lie from its fix for a pose from fewer tracks than min_relative_inliers:
        3 x the GNSS residual RMS of the block's oriented keyframes (>= 3 of them, the block georeferenced), at
        least 0.1 m (core/at_two_view.py adds 2 % of the baseline); None when the fix cannot vouch for it (no fix, its
        fix not used, too few residuals)."""
        if not self.block.georeferenced or kf.fix_enu is None or kf.kid in self.datum.rejected:
            return None
        r = [v for k, v in self.datum.residuals().items() if k not in self.datum.rejected]
        if len(r) < 3:
            return None
        return max(3.0 * float(np.sqrt(np.mean(np.sum(np.array(r) ** 2, axis=1)))), 0.1)

    def relative(self, kf: Keyframe) -> StepReport:
        """Orientation from the relative pose to the registered keyframe sharing most usable tracks
        with `kf` (essential matrix, core/two_view.py); the baseline length from the known points
        both see (depth ratio, >= 5 of them) or else from the GNSS fixes (the block's scale from its
        registered keyframes' fixes while not georeferenced). With fewer than min_relative_inliers shared tracks:
        `two_view` (the gated two-view pose, scaled by GNSS) with any of the recent oriented keyframes."""
        use = self.block.usable(kf)
        ids = kf.track_ids[use]
        best = None
        for r in self.block.registered[-2 * self.opt.window_size:]:
            rk = self.block.kfs[r]
            if rk.frozen:
                continue
            common = np.intersect1d(rk.track_ids[self.block.usable(rk)], ids)
            if best is None or len(common) > len(best[1]):
                best = (r, common)
        n_shared = 0 if best is None else len(best[1])
        if n_shared < self.opt.min_relative_inliers:
            return self.two_view(kf, self.block.registered[-2 * self.opt.window_size:],
                                 f'relative: too_few_shared_tracks ({n_shared})')
        r, common = best
        rk = self.block.kfs[r]
        i1 = np.array([rk.index(int(t)) for t in common])
        i2 = np.array([kf.index(int(t)) for t in common])
        thr = self.opt.pnp_threshold_px / self.block.camera.fx
        res = relative_pose(self.block.xn(rk, i1), self.block.xn(kf, i2), thr, self.opt.min_relative_inliers)
        T_r = rk.map_T_cam
        if res.ok and not self.faces_scene(res):
            return StepReport(kf.kid, False, 'relative: sees its tie points edge-on (the planar twin)')
        if res.ok:
            R, t = res.cam2_T_cam1[:3, :3], res.cam2_T_cam1[:3, 3]
            map_R = T_r[:3, :3] @ R.T
            d_map = T_r[:3, :3] @ (-R.T @ t)             # unit baseline r -> kf, map frame (block units)
            scale = self.relative_scale(rk, kf, common[res.inliers], res, d_map)
            if scale is None:
                return StepReport(kf.kid, False, 'relative: no_scale (neither known points nor GNSS)')
            kf.map_T_cam = make_T(map_R, T_r[:3, 3] + scale * d_map)
            inl = res.inliers
            status = 'registered_relative'
        else:
            # Too short a baseline (or a turn on the spot) for the essential matrix: with a georeferenced
            # block and a fix, the rotation from the homography of the shared tracks (a rotation when
            # the baseline is short against the height), the position from GNSS; the adjustment refines.
            got = self.gnss_and_rotation(rk, kf, i1, i2, thr)
            if got is None:
                return StepReport(kf.kid, False, f'relative: {res.status}')
            kf.map_T_cam, inl = got
            status = 'registered_gnss_rotation'
        out = np.ones(len(kf.track_ids), bool)
        out[i2[inl]] = False
        known = self.block.points.contains_many(kf.track_ids) & ~self.block.tie_mask(kf.track_ids)
        kf.active[use & known & out] = False      # known points that disagree with the relative pose
        self.block.enrol(kf)
        return StepReport(kf.kid, True, status)

    def n_two_view(self) -> int:
        """How many keyframes were oriented from two views (`two_view`)."""
        return len(self.two_view_oriented)

    def two_view(self, kf: Keyframe, partners, refused: str) -> StepReport:
        """kf oriented from the few tracks it shares with one of the oriented keyframes `partners`, scaled by GNSS
        and gated (core/at_two_view.py), when its fix can vouch for the pose (`gnss_tolerance_m`); else a report
        `refused` and why. What it orients is in `two_view_oriented` ({kid: how})."""
        tol = self.gnss_tolerance_m(kf)
        if tol is None:
            return StepReport(kf.kid, False, refused)
        got = two_view_pose(self.block, self.datum, self.opt.two_view, kf, partners, tol)
        if isinstance(got, str):
            return StepReport(kf.kid, False, f'{refused}; {got}')
        use = self.block.usable(kf)
        kf.map_T_cam = got.map_T_cam
        out = np.ones(len(kf.track_ids), bool)
        out[got.rows] = False
        known = self.block.points.contains_many(kf.track_ids) & ~self.block.tie_mask(kf.track_ids)
        kf.active[use & known & out] = False      # known points that disagree with the two-view pose
        self.block.enrol(kf)
        self.two_view_oriented[kf.kid] = got.status
        return StepReport(kf.kid, True, got.status)

    def gnss_and_rotation(self, rk: Keyframe, kf: Keyframe, i1, i2, thr: float):
        """(map_T_cam, inlier mask over i1/i2) of `kf` from its fix and the homography rotation to `rk`;
        None without a georeference, a fix or enough homography inliers."""
        import cv2
        if not self.block.georeferenced or kf.fix_enu is None:
            return None
        H, mask = cv2.findHomography(self.block.xn(rk, i1), self.block.xn(kf, i2), cv2.RANSAC, 2 * thr)
        if H is None or int(mask.sum()) < self.opt.min_relative_inliers:
            return None
        U, _, Vt = np.linalg.svd(H)
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt     # nearest rotation: x_kf ~ R x_r
        map_R = rk.map_T_cam[:3, :3] @ R.T
        lever = self.datum.lever if kf.antenna_offset is None else map_R.T @ kf.antenna_offset
        C = kf.fix_enu - self.datum.bias_enu - map_R @ lever
        return make_T(map_R, C), mask.ravel().astype(bool)

    def relative_scale(self, rk: Keyframe, kf: Keyframe, inlier_ids, res, d_map) -> float | None:
        """Length of the baseline rk -> kf in block units (see _register_relative)."""
        known = inlier_ids[self.block.points.contains_many(inlier_ids)]
        if len(known) >= 5:
            X = self.block.points.get_many(known)
            depth_block = ((X - rk.map_T_cam[:3, 3]) @ rk.map_T_cam[:3, :3])[:, 2]
            rows = np.searchsorted(inlier_ids, known)
            depth_unit = res.points_cam1[np.flatnonzero(res.inliers)[rows], 2]
            ok = (depth_block > 0) & (depth_unit > 0)
            if ok.sum() >= 5:
                return float(np.median(depth_block[ok] / depth_unit[ok]))
        if rk.fix_enu is None or kf.fix_enu is None:
            return None
        gnss_m = float(np.linalg.norm(kf.fix_enu - rk.fix_enu))
        if self.block.georeferenced:
            return gnss_m
        ks = [k for k in self.block.registered if self.block.kfs[k].fix_enu is not None]
        if len(ks) < 2:
            return None
        C = np.array([self.block.kfs[k].map_T_cam[:3, 3] for k in ks])
        G = np.array([self.block.kfs[k].fix_enu for k in ks])
        block, world = np.linalg.norm(C - C[0], axis=1)[1:], np.linalg.norm(G - G[0], axis=1)[1:]
        if world.max() < 1e-6:
            return None
        return gnss_m * float(np.sum(block * world) / np.sum(world * world))

