"""Memory on long flights: freezing what can no longer enter an adjustment window.

A tracker track that has not been seen for the window plus a margin can never enter a window
again, so it is frozen: its point moves to compact arrays with only a count of its observations
(`PointStore`, core/at_store.py), and a keyframe whose tracks are all frozen moves its observations
to disk (`KeyframeSpill`). The final full adjustment reads them back (its peak is the solver's);
results are bit-identical to keeping everything (tests/test_incremental.py).

`Freezer` holds what only freezing needs (the newest keyframe of every hot track, the spill
folder) and runs the passes over the triangulation's state, which the caller hands in: its
keyframes (`Keyframe`, by id), the registered keyframe ids in order of registration, the
keyframes observing each hot track (`track_kfs`) and the points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photogram_ros.core.at_problem import ProblemOptions
from photogram_ros.core.at_store import Keyframe, KeyframeSpill, PointStore
from photogram_ros.core.part_options import check, declared
from photogram_ros.params import param


@dataclass(frozen=True)
class FreezeOptions:
    """The options of freezing (`Freezer`): how far behind the window a track freezes, when thawing stops, where
    frozen keyframes spill."""
    window_size: int = declared(ProblemOptions, 'window_size')
    spill_dir: str = param('', 'folder for the frozen keyframes\' observations ("" = a private temporary folder, '
                               'removed afterwards)')
    freeze_margin_keyframes: int = param(5, 'a track freezes this many registrations before the window',
                                         min=0, max=10000)
    max_thaws: int = param(3, 'keyframes bringing back (or looking up) ended tracks before freezing stops',
                           min=1, max=10000)

    def __post_init__(self):
        check(self)


class Freezer:
    """Freeze and thaw passes of one triangulation, for the options `opt`."""

    def __init__(self, opt: FreezeOptions):
        self.opt = opt
        # Hot tracker tracks (id >= 0) -> newest keyframe observing them; a track whose newest
        # observation is older than the window (and its margin) is frozen.
        self.last_seen: dict[int, int] = {}
        self.max_seen_id = -1
        self.spill: KeyframeSpill | None = None
        # Records whose track ids come back after a gap (ground-point ids, a loop-closing matcher)
        # make every thaw a scan of the block: after a few, freezing stops for this block.
        self.thaw_keyframes = 0
        self.stopped = ''          # why freezing stopped ('' while it goes on)

    def seen(self, kid: int, ids: np.ndarray) -> None:
        """Keyframe `kid` observes the (sorted) track ids `ids`."""
        for t in ids[ids >= 0].tolist():
            self.last_seen[t] = kid
        if len(ids) and ids[-1] >= 0:
            self.max_seen_id = max(self.max_seen_id, int(ids[-1]))

    @property
    def spilled_bytes(self) -> int:
        return self.spill.bytes_on_disk if self.spill else 0

    def freeze(self, kfs: list[Keyframe], registered: list[int], track_kfs: dict, points: PointStore) -> None:
        """Freeze the tracks whose newest observation is older than the window (plus a margin) and
        the keyframes that only observe frozen tracks.

        No future window can hold them: the free keyframes are the newest ones, and a fixed keyframe
        enters only through a point that a free keyframe observes. A tracker never reuses an id
        after its track ended; if a record does anyway, `thaw_seen_again` undoes this.
        Keyframes with target (GCP) observations stay in memory: targets are seen again anywhere.
        """
        n_keep = self.opt.window_size + max(self.opt.freeze_margin_keyframes, 0)
        if len(registered) <= n_keep or self.stopped:
            return
        horizon = min(registered[-n_keep:])
        dead = [t for t, k in self.last_seen.items() if k < horizon]
        counts = []
        for t in dead:
            del self.last_seen[t]
            counts.append(len(track_kfs.pop(t, ())))
        points.freeze(dead, counts)
        if self.spill is None:
            self.spill = KeyframeSpill(self.opt.spill_dir or None)
        for kf in kfs[:horizon]:
            if not kf.frozen and not kf.has_targets and not any(t in self.last_seen for t in kf.track_ids.tolist()):
                kf.freeze(self.spill)

    def thaw_seen_again(self, ids: np.ndarray, kfs: list[Keyframe], registered: list[int], track_kfs: dict,
                        points: PointStore) -> None:
        """Tracks of a new record that were frozen: restore their keyframe lists (in registration
        order, as they were built), points and keyframes, so the result is what it would have been."""
        if self.spill is None or self.stopped:
            return   # nothing was ever frozen / everything is back in memory
        ids = np.asarray(ids, np.int64)
        cand = ids[(ids >= 0) & (ids <= self.max_seen_id)]
        if not len(cand):
            return
        cand = np.array([t for t in cand.tolist() if t not in self.last_seen], np.int64)
        if not len(cand):
            return
        # A tracker's new ids are above every id seen so far: a lower unknown id costs a scan of
        # the block, and a source doing that repeatedly is not frozen any more (see below).
        self.thaw_keyframes += 1
        lists: dict[int, list] = {}
        for kf in kfs:
            if kf.id_hi < cand[0] or kf.id_lo > cand[-1]:
                continue
            tids, _, _, active = kf.peek()
            hit = np.isin(tids, cand)
            if not hit.any():
                continue
            if kf.frozen:
                kf.thaw()
            for t, a in zip(tids[hit].tolist(), active[hit].tolist()):
                self.last_seen[t] = max(self.last_seen.get(t, -1), kf.kid)
                if a and kf.reg_seq >= 0:
                    lists.setdefault(t, []).append(kf)
        for t, lst in lists.items():
            track_kfs[t] = [kf.kid for kf in sorted(lst, key=lambda kf: kf.reg_seq)]
            points.thaw(t)
        if self.thaw_keyframes >= self.opt.max_thaws:
            self._stop(f'track ids below the newest ones not in memory (ended tracks seen again?) '
                       f'in {self.thaw_keyframes} keyframes', kfs, registered, track_kfs, points)

    def _stop(self, why: str, kfs: list[Keyframe], registered: list[int], track_kfs: dict,
              points: PointStore) -> None:
        """Everything back in memory (same values, same order): from now on this block is not frozen."""
        self.stopped = why
        for kf in kfs:
            if kf.frozen:
                kf.thaw()
        for t in [t for t in points.ids().tolist() if points.is_frozen(t)]:
            points.thaw(t)
        # Rebuild the keyframe lists of every track (frozen ones kept only their count).
        lists: dict[int, list] = {}
        for k in registered:
            kf = kfs[k]
            for t in kf.track_ids[kf.active].tolist():
                if t not in track_kfs:
                    lists.setdefault(t, []).append(kf)
        for t, lst in lists.items():
            track_kfs[t] = [kf.kid for kf in sorted(lst, key=lambda kf: kf.reg_seq)]
            self.last_seen.setdefault(t, max(kf.kid for kf in lst))
