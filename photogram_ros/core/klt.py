"""Frame-to-frame KLT on the tracker's working images: forward-backward checked, refined on the previous image
turned onto this one when the camera rotates, and checked by an essential matrix (core/tracker.py's steps)."""

from __future__ import annotations

import cv2
import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.two_view import essential_ransac


class KltStep:
    """KLT of (N, 2) float32 points between two grey images of the working camera `cam`, with the tracker's
    parameters `params` (TrackerParams: klt_window_px, klt_levels, fb_max_px, klt_err_factor, derotate_deg,
    klt_min_share, ransac_px)."""

    def __init__(self, params, cam: PinholeCamera):
        self.params, self.cam = params, cam
        self._win = (params.klt_window_px | 1, params.klt_window_px | 1)
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)

    def pair(self, img0, img1, p0, guess, levels):
        """Forward KLT from `guess` and backward check; (p1, ok, residual) for (N, 2) float32 points."""
        p = self.params
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        q0 = p0.reshape(-1, 1, 2).astype(np.float32)
        p1, st, err = cv2.calcOpticalFlowPyrLK(img0, img1, q0, guess.reshape(-1, 1, 2).astype(np.float32),
                                               winSize=self._win, maxLevel=levels, criteria=self._criteria,
                                               flags=flags)
        pb, st2, _ = cv2.calcOpticalFlowPyrLK(img1, img0, p1, q0.copy(), winSize=self._win, maxLevel=levels,
                                              criteria=self._criteria, flags=flags)
        p1, pb, err = p1.reshape(-1, 2), pb.reshape(-1, 2), err.ravel()
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(pb - p0.reshape(-1, 2), axis=1) < p.fb_max_px)
        ok &= self.cam.in_image(p1, margin_px=2.0)
        if ok.sum() > 10 and p.klt_err_factor > 0:
            # A window whose content changes (an occluding edge sliding over the background) keeps a
            # large residual: it is not the image of one ground point.
            ok &= err <= p.klt_err_factor * np.median(err[ok])
        return p1, ok

    def track(self, img0, img1, p0, ids, guess_shift):
        """KLT img0 -> img1 (de-rotated when the camera turns), FB and essential-matrix checks."""
        if len(p0) == 0:
            return p0, ids, None
        p = self.params
        p0 = p0.reshape(-1, 2).astype(np.float32)
        p1, ok = self.pair(img0, img1, p0, p0 + np.asarray(guess_shift, np.float32), p.klt_levels)
        if ok.sum() >= 10 and p.derotate_deg > 0:
            A, _ = cv2.estimateAffinePartial2D(p0[ok], p1[ok], method=cv2.RANSAC, ransacReprojThreshold=3.0)
            if A is not None and (abs(np.degrees(np.arctan2(A[1, 0], A[0, 0]))) > p.derotate_deg
                                  or abs(np.hypot(A[0, 0], A[1, 0]) - 1.0) > 0.02):
                # KLT fits translations only: under rotation its estimate drifts coherently, frame
                # after frame. Tracking from the previous image turned onto this one removes that.
                h, w = img1.shape[:2]
                warped = cv2.warpAffine(img0, A, (w, h), flags=cv2.INTER_LINEAR)
                q0 = p0 @ A[:, :2].T.astype(np.float32) + A[:, 2].astype(np.float32)
                p1, ok2 = self.pair(warped, img1, q0, np.where(ok[:, None], p1, q0), 1)
                ok = ok2
        if ok.sum() < p.klt_min_share * len(ok):
            # Most windows lost their point: far beyond KLT's reach (photo-rate input). The few
            # survivors are mostly coincidences; RANSAC on them would only cost time.
            return p0[:0], ids[:0], None
        p0, p1, ids = p0[ok], p1[ok], ids[ok]
        keep = self.epipolar_inliers(p0, p1)
        p0, p1, ids = p0[keep], p1[keep], ids[keep]
        flow = np.median(p1 - p0, axis=0) if len(p1) else None
        return p1.astype(np.float32), ids, flow

    def epipolar_inliers(self, p0, p1, xn0=None, method: str = 'ransac') -> np.ndarray:
        n = len(p1)
        if n < 8:
            return np.zeros(n, bool)
        xn0 = self.cam.pixel_to_normalized(p0) if xn0 is None else xn0
        xn1 = self.cam.pixel_to_normalized(p1)
        if np.median(np.linalg.norm(xn1 - xn0, axis=1)) * self.cam.fx < 1.0:
            return np.ones(n, bool)   # no baseline to speak of: E is undetermined, FB check must do
        E, mask = essential_ransac(xn0, xn1, self.params.ransac_px / self.cam.fx, method=method)
        if E is None:
            return np.zeros(n, bool)
        return mask

    def through_homography(self, img_kf, pts_kf, ids_kf, uv_kf, uv_cur, img_cur):
        """A keyframe's KLT tracks (`pts_kf`, `ids_kf` on `img_kf`) onto the frame `img_cur`: the keyframe's image
        warped by the homography of the descriptor matches `uv_kf` -> `uv_cur`, KLT from the warped positions (the
        parallax residual left), epipolar check. Returns ((M, 2) float32 pixels, (M,) ids)."""
        none = (np.empty((0, 2), np.float32), np.empty(0, np.uint32))
        if len(pts_kf) < 8:
            return none
        H, inl = cv2.findHomography(uv_kf.astype(np.float32), uv_cur.astype(np.float32), cv2.RANSAC, 8.0)
        if H is None or int(inl.sum()) < 15:
            return none
        h, w = img_cur.shape
        warped = cv2.warpPerspective(img_kf, H, (w, h), flags=cv2.INTER_LINEAR)
        guess = cv2.perspectiveTransform(pts_kf.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
        inside = self.cam.in_image(guess, margin_px=self._win[0] / 2)
        if inside.sum() < 8:
            return none
        guess = guess[inside].astype(np.float32)
        ids, xn_kf = ids_kf[inside], self.cam.pixel_to_normalized(pts_kf[inside].astype(np.float64))
        pts, ok = self.pair(warped, img_cur, guess, guess, 2)
        if ok.sum() < 8:
            return none
        keep = self.epipolar_inliers(None, pts[ok], xn_kf[ok], 'usac')
        return pts[ok][keep].astype(np.float32), ids[ok][keep]
