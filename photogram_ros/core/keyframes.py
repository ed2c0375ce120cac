"""Keyframe helpers: GNSS fixes (core.gnss_fix.GnssFix) interpolated to an image time, and front-overlap estimates.

Overlap is the fraction of the last keyframe's footprint that is still inside the current image.
From images it is measured with a homography fitted to the tracks both frames share (exact for
flat ground, a good approximation at survey heights); from GPS it is one minus the distance
flown over the along-track footprint length, usable only when the fix is good.
"""

from __future__ import annotations

import bisect

import cv2
import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.gnss_fix import GnssFix


class FixBuffer:
    """Time-ordered GNSS fixes; interpolates one to any stamp between two fixes not too far apart."""

    def __init__(self, max_gap_s: float = 1.0, keep: int = 600):
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.keep = keep
        self._stamps: list[int] = []
        self._fixes: list[GnssFix] = []

    def add(self, fix: GnssFix) -> None:
        if fix.status < 0 or not (np.isfinite(fix.lat_deg) and np.isfinite(fix.lon_deg)):
            return   # NavSatStatus.STATUS_NO_FIX: nothing to interpolate from
        i = bisect.bisect_left(self._stamps, fix.stamp_ns)
        if i < len(self._stamps) and self._stamps[i] == fix.stamp_ns:
            self._fixes[i] = fix
            return
        self._stamps.insert(i, fix.stamp_ns)
        self._fixes.insert(i, fix)
        if len(self._stamps) > self.keep:
            del self._stamps[0], self._fixes[0]

    def __len__(self) -> int:
        return len(self._stamps)

    def latest_ns(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    def near(self, stamp_ns: int, max_s: float) -> GnssFix | None:
        """The fix at `stamp_ns` (interpolated), else the fix nearest in time within `max_s`, else None."""
        got = self.at(stamp_ns)
        if got is not None or not self._stamps:
            return got
        i = bisect.bisect_left(self._stamps, stamp_ns)
        near = [k for k in (i - 1, i) if 0 <= k < len(self._stamps)]
        k = min(near, key=lambda k: abs(self._stamps[k] - stamp_ns))
        return self._fixes[k] if abs(self._stamps[k] - stamp_ns) <= max_s * 1e9 else None

    def at(self, stamp_ns: int) -> GnssFix | None:
        """The fix at `stamp_ns` interpolated linearly, or None outside the data or across an outage."""
        i = bisect.bisect_left(self._stamps, stamp_ns)
        if i < len(self._stamps) and self._stamps[i] == stamp_ns:
            return self._fixes[i]
        if i == 0 or i == len(self._stamps):
            return None
        a, b = self._fixes[i - 1], self._fixes[i]
        if b.stamp_ns - a.stamp_ns > self.max_gap_ns:
            return None
        w = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        return GnssFix(a.lat_deg + w * (b.lat_deg - a.lat_deg), a.lon_deg + w * (b.lon_deg - a.lon_deg),
                       a.h_m + w * (b.h_m - a.h_m),
                       # The worse fix bounds the uncertainty of a point between them.
                       np.maximum(a.cov_enu_m2, b.cov_enu_m2), int(stamp_ns), min(a.status, b.status),
                       min(a.cov_type, b.cov_type), True)


def gps_distance_m(a: GnssFix, b: GnssFix) -> float:
    """Horizontal distance between two nearby fixes (local spherical approximation, < 1 mm at 100 m)."""
    r_m = 6371008.8
    lat = np.radians(0.5 * (a.lat_deg + b.lat_deg))
    dn = np.radians(b.lat_deg - a.lat_deg) * r_m
    de = np.radians(b.lon_deg - a.lon_deg) * r_m * np.cos(lat)
    return float(np.hypot(de, dn))


class OverlapGrid:
    """A grid of sample pixels of one image with their undistorted normalized coordinates."""

    def __init__(self, camera: PinholeCamera, nx: int = 64, ny: int = 48):
        u = (np.arange(nx) + 0.5) * camera.width / nx - 0.5
        v = (np.arange(ny) + 0.5) * camera.height / ny - 0.5
        self.uv = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
        self.xn = camera.pixel_to_normalized(self.uv)
        self.camera = camera

    def overlap(self, H_norm: np.ndarray) -> float:
        """Fraction of the grid that the normalized homography maps inside the image."""
        p = np.column_stack([self.xn, np.ones(len(self.xn))]) @ H_norm.T
        ok = p[:, 2] > 1e-9
        q = p[:, :2] / np.where(ok, p[:, 2], 1.0)[:, None]
        # Far outside the calibrated field the distortion polynomial folds back: cut there first.
        lim = np.abs(self.xn).max(axis=0) * 1.5
        ok &= (np.abs(q[:, 0]) < lim[0]) & (np.abs(q[:, 1]) < lim[1])
        uv = self.camera.normalized_to_pixel(q)
        return float(np.mean(ok & self.camera.in_image(uv)))


def homography_overlap(grid: OverlapGrid, xn_kf: np.ndarray, xn_cur: np.ndarray,
                       thresh_norm: float) -> tuple[float | None, int]:
    """Overlap of the keyframe (points xn_kf) with the current frame (xn_cur); None when unknown."""
    if len(xn_kf) < 8:
        return None, 0
    H, inl = cv2.findHomography(xn_kf.astype(np.float64), xn_cur.astype(np.float64), cv2.RANSAC,
                                thresh_norm, maxIters=200)
    if H is None:
        return None, 0
    return grid.overlap(H), int(inl.sum())



class ChainStore:
    """What cross-keyframe matching keeps of each keyframe: its stamp, its position (local metres, once its
    GNSS fix is known), and the SIFT features it published as tracks: reduced-image pixels (float32),
    RootSIFT descriptors quantised to uint8 (value x 255: RootSIFT components lie in [0, 1]) and their track
    ids (uint32), and every track id the keyframe published (uint32). 140 bytes per feature, 4 per track and ~100
    per keyframe: 1500 features of a photo-rate keyframe publishing 4000 tracks ~ 226 kB, a 300-keyframe
    flight ~ 68 MB. Beyond `max_keyframes` the oldest keyframe's features are dropped (counted in `dropped`):
    a longer flight keeps matching its newest `max_keyframes`."""

    def __init__(self, max_keyframes: int):
        self.max_keyframes = int(max_keyframes)
        self.stamps: list[int] = []
        self.keys: list[int] = []              # the keyframe index of each entry
        self.positions: list = []              # (3,) local metres, or None until the fix is known
        self.sigma_h_m: list[float] = []
        self.uv: list[np.ndarray] = []
        self.desc: list[np.ndarray] = []
        self.ids: list[np.ndarray] = []
        self.seen: list[np.ndarray] = []
        self.dropped = 0

    def __len__(self) -> int:
        return len(self.keys)

    def add(self, key: int, stamp_ns: int, uv: np.ndarray, desc: np.ndarray, ids: np.ndarray,
            seen: np.ndarray | None = None) -> None:
        """A keyframe's published SIFT tracks (desc float RootSIFT in [0, 1], quantised here); `seen`: every
        track id the keyframe published (KLT ones too: whether a new keyframe is linked to it already)."""
        self.seen.append(np.asarray(ids if seen is None else seen, np.uint32).ravel())
        self.keys.append(int(key))
        self.stamps.append(int(stamp_ns))
        self.positions.append(None)
        self.sigma_h_m.append(0.0)
        self.uv.append(np.asarray(uv, np.float32).reshape(-1, 2))
        self.desc.append(np.clip(np.rint(np.asarray(desc, np.float32) * 255.0), 0, 255).astype(np.uint8))
        self.ids.append(np.asarray(ids, np.uint32).ravel())
        while len(self.keys) > self.max_keyframes:
            for lst in (self.keys, self.stamps, self.positions, self.sigma_h_m, self.uv, self.desc, self.ids,
                        self.seen):
                del lst[0]
            self.dropped += 1

    def locate(self, position_of) -> None:
        """Give the entries still without a position one: `position_of(stamp_ns)` -> ((3,) m, sigma_h_m) or None."""
        for i, p in enumerate(self.positions):
            if p is None:
                got = position_of(self.stamps[i])
                if got is not None:
                    self.positions[i], self.sigma_h_m[i] = np.asarray(got[0], float), float(got[1])

    def overlapping(self, here, neighbours: int) -> list[int]:
        """Entries whose footprints a frame at `here` ((3,) m, sigma_h_m: what `locate` takes; or None) overlaps by
        GNSS, nearest first: photo_matching.earlier_candidates' first `neighbours` candidates (at most twice that)."""
        from photogram_ros.core.photo_matching import earlier_candidates
        placed = [i for i in range(len(self.keys)) if self.positions[i] is not None]
        if here is None or not placed or neighbours == 0:
            return []
        sigma = max(here[1], float(np.median([self.sigma_h_m[i] for i in placed])))
        order, first = earlier_candidates(np.array([self.positions[i] for i in placed]), here[0], neighbours, sigma)
        return [placed[int(k)] for k in order[:min(first, 2 * neighbours)]]

    def nearest_first(self, entries: list[int], here) -> list[int]:
        """`entries` by horizontal distance from `here` (as in `overlapping`; None: as they are), those without a
        position last."""
        if here is None:
            return list(entries)

        def dist(i):
            q = self.positions[i]
            return float(np.linalg.norm((q - here[0])[:2])) if q is not None else float('inf')
        return sorted(entries, key=dist)

    def descriptors(self, i: int) -> np.ndarray:
        """Entry i's descriptors as float32 RootSIFT (what FLANN matches)."""
        return self.desc[i].astype(np.float32) * np.float32(1.0 / 255.0)

    def nbytes(self) -> int:
        return int(sum(u.nbytes + d.nbytes + t.nbytes + s.nbytes
                       for u, d, t, s in zip(self.uv, self.desc, self.ids, self.seen)) + 100 * len(self.keys))
