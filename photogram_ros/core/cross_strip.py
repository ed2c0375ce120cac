"""Tie points across strips for keyframes that KLT carried (core/tracker.py).

A keyframe KLT carried (no break since the last keyframe: video-rate input, or photos close enough for KLT)
has no SIFT features unless `chain_klt_keyframes` gives them to every keyframe, which costs a feature
extraction and descriptor matches per keyframe. Without them a later strip flying past it cannot be matched
with it: the block falls into parts joined only through their GNSS. `CrossStrip` decides which of those
keyframes get SIFT features all the same:

- every `cross_strip_store_every`-th keyframe (by index) keeps features in the chain (core.keyframes.ChainStore)
  for a later strip to match: whether a footprint will be flown over again is not known when it is taken;
- a keyframe whose GNSS footprint overlaps a chain entry of another part of the flight (an earlier keyframe
  of the tracker's candidates, photo_matching.earlier_candidates, at least `cross_strip_min_back` keyframes
  older and not already sharing `chain_linked_ids` track ids with it: not the recent KLT chain) gets features
  and is matched with it: its matched features take that keyframe's track ids; at most every
  `cross_strip_revisit_every`-th keyframe (the cost of a SIFT extraction and its matches).

The features of such a keyframe that no match linked take the id of the KLT track they sit on
(`adopt_track_ids`, within `cross_strip_adopt_px`), so that what a later strip matches is a track the earlier
strip's keyframes already triangulate, not a point seen once.

Off by default (`cross_strip_store_every` 0, `cross_strip_min_back` 0); bench/chain_cross_strip.py measures it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from photogram_ros.params import param


@dataclass
class CrossStripParams:
    cross_strip_store_every: int = param(0, 'Every this many keyframes (by index), one that KLT carried also gets '
                                         'SIFT features and keeps chain_features of them in the chain, for a later '
                                         'strip overlapping its footprint to match (core/cross_strip.py); 0: off '
                                         '(the default: with 3 and cross_strip_min_back 6, seneca_part\'s replay DSM '
                                         'held 8-10 % measured cells against 10-11 % without, at 2.5x the tracker\'s '
                                         'CPU per keyframe on 20 MP; no accuracy gain measured yet)',
                                         min=0, max=1000)
    cross_strip_min_back: int = param(0, 'A keyframe KLT carried gets SIFT features and is matched with the chain\'s '
                                      'earlier keyframes whose GNSS footprints it overlaps (within cross_strip_reach) '
                                      'that are at least this many keyframes older and share fewer than '
                                      'chain_linked_ids track ids with it (another strip, not the recent KLT chain); '
                                      '0: off (the default; 6 with cross_strip_store_every 3)', min=0, max=100000)
    cross_strip_revisit_every: int = param(2, 'A keyframe KLT carried is matched with another strip\'s keyframes only '
                                           'when none of the last this many - 1 keyframes was (1: every one that '
                                           'overlaps another strip; 2: at most every other)', min=1, max=1000)
    cross_strip_reach: float = param(0.75, 'Another strip\'s keyframe overlaps a keyframe KLT carried when their GNSS '
                                     'positions are closer than this share of the footprint\'s along-track length '
                                     '(estimated from consecutive keyframes: GNSS distance / (1 - front overlap))',
                                     min=0.05, max=2.0)
    cross_strip_adopt_px: float = param(1.5, 'A SIFT feature of a keyframe KLT carried that no match linked takes '
                                        'the id of the KLT track within this distance, reduced-image px (0: a new '
                                        'id)', min=0.0, max=20.0)


# Footprints estimated from this many of the latest consecutive keyframe pairs (their median).
FOOTPRINT_SAMPLES = 21


class CrossStrip:
    """Which keyframes KLT carried get SIFT features, and which chain entries they are matched with (see the
    module's doc); counts what it decided."""

    def __init__(self, params: CrossStripParams):
        self.params = params
        self.stored = 0       # keyframes given features to keep (every cross_strip_store_every-th)
        self.revisits = 0     # keyframes given features because another strip's keyframe overlaps them
        self._last: tuple[int, np.ndarray] | None = None   # (key, (3,) m) of the last keyframe with a position
        self._footprints: list[float] = []
        self._last_revisit = -10**9

    @property
    def on(self) -> bool:
        return self.params.cross_strip_store_every > 0 or self.params.cross_strip_min_back > 0

    def footprint_m(self) -> float | None:
        """The footprint's along-track length, m: the median of GNSS distance / (1 - front overlap) over the
        latest consecutive keyframes; None before there is one."""
        return float(np.median(self._footprints)) if self._footprints else None

    def plan(self, key: int, here, overlap: float, wanted: bool, chain, candidates: Sequence[int]) -> list[int] | None:
        """Keyframe `key` (`here`: ((3,) local m, sigma_h_m) of its GNSS fix or None; `overlap`: its front
        overlap with the previous keyframe; `wanted`: it gets SIFT features anyway): None when it is to have
        none, else the entries of `chain` (core.keyframes.ChainStore, located) to match it with, of
        `candidates` (the tracker's chain candidates for it): those of another strip it overlaps."""
        p = self.params
        pos = None if here is None else np.asarray(here[0], float)
        if pos is not None:
            if (self._last is not None and self._last[0] == key - 1 and np.isfinite(overlap)
                    and 0.05 < overlap < 0.95):
                step = float(np.linalg.norm((pos - self._last[1])[:2]))
                if step > 0.0:
                    self._footprints = (self._footprints + [step / (1.0 - overlap)])[-FOOTPRINT_SAMPLES:]
            self._last = (key, pos)
        if wanted or not self.on:
            return None
        other = []
        foot = self.footprint_m()
        if (p.cross_strip_min_back > 0 and pos is not None and foot is not None
                and key - self._last_revisit >= p.cross_strip_revisit_every):
            reach = p.cross_strip_reach * foot
            old = [i for i in candidates if chain.keys[i] <= key - p.cross_strip_min_back]
            other = [i for i in old if chain.positions[i] is not None
                     and float(np.linalg.norm((chain.positions[i] - pos)[:2])) <= reach]
        if other:
            self.revisits += 1
            self._last_revisit = key
            return other
        if p.cross_strip_store_every > 0 and key % p.cross_strip_store_every == 0:
            self.stored += 1
            return []
        return None

    def adopt_klt_ids(self, feat_uv: np.ndarray, feat_ids: np.ndarray, pts: np.ndarray, ids: np.ndarray) -> int:
        """adopt_track_ids within cross_strip_adopt_px."""
        return adopt_track_ids(feat_uv, feat_ids, pts, ids, self.params.cross_strip_adopt_px)


def adopt_track_ids(feat_uv: np.ndarray, feat_ids: np.ndarray, pts: np.ndarray, ids: np.ndarray,
                    radius_px: float) -> int:
    """Give the features without a track id (-1 in `feat_ids`, changed in place) the id of the nearest KLT
    track (`pts` (N, 2) px, `ids` (N,)) within `radius_px`, one feature per track (the nearest). Returns how
    many took one."""
    open_ = np.flatnonzero(feat_ids < 0)
    if radius_px <= 0 or not len(open_) or not len(ids):
        return 0
    d, t = cKDTree(np.asarray(pts, float).reshape(-1, 2)).query(np.asarray(feat_uv, float)[open_],
                                                                distance_upper_bound=radius_px)
    q = np.flatnonzero(np.isfinite(d))
    t, d = t[q], d[q]
    order = np.lexsort((d, t))                      # per track, the nearest feature first
    q, t = q[order], t[order]
    first = np.concatenate([[True], t[1:] != t[:-1]]) if len(t) else np.zeros(0, bool)
    taken = ~np.isin(ids[t[first]].astype(np.int64), feat_ids[feat_ids >= 0])
    feat_ids[open_[q[first][taken]]] = ids[t[first][taken]].astype(np.int64)
    return int(taken.sum())
