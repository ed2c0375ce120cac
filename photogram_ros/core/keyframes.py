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

