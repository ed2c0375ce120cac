"""Tie points for a folder of survey photos: SIFT features, matching of GNSS neighbours, tracks.

Photos are unordered in principle; their geotags say which ones can overlap, so each photo is
matched only with its nearest neighbours (by position), every match is verified by an essential
matrix (RANSAC, normalized coordinates), and the verified matches are chained into tracks with a
union-find. A track that would hold two features of one photo is dropped (an ambiguous chain).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.two_view import essential_ransac


@dataclass
class PhotoFeatures:
    name: str
    uv: np.ndarray          # (K, 2) pixels
    desc: np.ndarray        # (K, 128) float32


def extract(name: str, image_bgr: np.ndarray, max_features: int = 3000) -> PhotoFeatures:
    gray = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr
    sift = cv2.SIFT_create(nfeatures=max_features)
    kps, desc = sift.detectAndCompute(gray, None)
    uv = np.array([k.pt for k in kps], float).reshape(-1, 2)
    return PhotoFeatures(name, uv, desc if desc is not None else np.zeros((0, 128), np.float32))


def match_pair(a: PhotoFeatures, b: PhotoFeatures, camera: PinholeCamera, ratio: float = 0.8,
               threshold_px: float = 2.0, min_matches: int = 20) -> np.ndarray:
    """Verified matches (M, 2) of feature indices a -> b."""
    if len(a.uv) < 5 or len(b.uv) < 5:
        return np.zeros((0, 2), int)
    m = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.desc, b.desc, k=2)
    pairs = np.array([(x[0].queryIdx, x[0].trainIdx) for x in m if len(x) == 2 and x[0].distance < ratio * x[1].distance],
                     int).reshape(-1, 2)
    if len(pairs) < min_matches:
        return np.zeros((0, 2), int)
    _, uniq = np.unique(pairs[:, 1], return_index=True)   # one-to-one
    pairs = pairs[np.sort(uniq)]
    E, inl = essential_ransac(camera.pixel_to_normalized(a.uv[pairs[:, 0]]),
                              camera.pixel_to_normalized(b.uv[pairs[:, 1]]), threshold_px / camera.fx)
    if E is None or inl.sum() < min_matches:
        return np.zeros((0, 2), int)
    return pairs[inl]


def neighbours(positions: np.ndarray, k: int) -> list[tuple[int, int]]:
    """Pairs (i < j) of each photo with its k nearest photos by position."""
    d = np.linalg.norm(positions[:, None, :2] - positions[None, :, :2], axis=2)
    out = set()
    for i in range(len(positions)):
        for j in np.argsort(d[i])[1:k + 1]:
            out.add((min(i, int(j)), max(i, int(j))))
    return sorted(out)


def build_tracks(n_features: list[int], matches: dict) -> list[np.ndarray]:
    """Union-find over (photo, feature) nodes -> per photo an array of track ids (-1 = none)."""
    offsets = np.concatenate([[0], np.cumsum(n_features)])
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
    roots = np.array([find(x) for x in range(offsets[-1])], int)
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
