"""How a frame links to the chain's keyframes (core/tracker.py's descriptor matching): which track id each of its
features takes from the entries it verified, and when to stop trying entries.

- `TrackViews`: per track id, how many keyframes published it (capped at 254), so that a feature whose matches
  carry different ids takes the one seen most (the likeliest to be known to the adjuster).
- `assign_track_ids`: the frame's features without an id take one from the verified matches.
- `enough_links`: the stop rule of chain_enough_verified / chain_stop_after_failures.
"""

from __future__ import annotations

import numpy as np


class TrackViews:
    """Per track id, the keyframes that published it (uint8, capped at 254)."""

    def __init__(self):
        self._views = np.zeros(0, np.uint8)

    def of(self, ids: np.ndarray) -> np.ndarray:
        ids = np.asarray(ids, np.int64)
        v = np.zeros(len(ids), np.int64)
        ok = ids < len(self._views)
        v[ok] = self._views[ids[ok]]
        return v

    def add(self, ids: np.ndarray) -> None:
        """One more keyframe published `ids`."""
        ids = np.asarray(ids, np.int64)
        if not len(ids):
            return
        top = int(ids.max()) + 1
        if top > len(self._views):
            self._views = np.concatenate([self._views, np.zeros(max(top - len(self._views), 4096), np.uint8)])
        np.add.at(self._views, ids, 1)
        np.minimum(self._views, 254, out=self._views)


def assign_track_ids(got: np.ndarray, dsts: list[np.ndarray], tids: list[np.ndarray], views: TrackViews) -> None:
    """`got` (the frame's track id per feature, -1: none) takes, for each feature without one, the id its verified
    matches carry (`dsts`: the frame's feature rows, `tids`: their entries' ids, one array per entry): where they
    differ, the id seen by the most keyframes, then the oldest."""
    if not dsts:
        return
    dst, tid = np.concatenate(dsts), np.concatenate(tids)
    open_ = got[dst] < 0
    dst, tid = dst[open_], tid[open_]
    order = np.lexsort((tid, -views.of(tid), dst))
    dst, tid = dst[order], tid[order]
    first = np.concatenate([[True], dst[1:] != dst[:-1]]) if len(dst) else np.zeros(0, bool)
    got[dst[first]] = tid[first]


def enough_links(verified: int, failed_run: int, p) -> bool:
    """Whether a frame has matched enough chain entries (p.chain_enough_verified; 0: no bound), or, having verified
    one, the last p.chain_stop_after_failures (farther, nearest first) failed: the rest would cost time, not links.
    `p`: the tracker's parameters (core/tracker.TrackerParams)."""
    if p.chain_enough_verified and verified >= p.chain_enough_verified:
        return True
    return bool(p.chain_stop_after_failures and verified and failed_run >= p.chain_stop_after_failures)
