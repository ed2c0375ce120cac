"""Sliding-window selection: which keyframes and points an incremental adjustment touches.

The newest `size` registered keyframes are free; every point they observe is free; every other
keyframe observing one of those points enters the problem held fixed, so the window stays
anchored to the part of the block already adjusted. The size of this set depends on the image
overlap, not on the length of the flight, which keeps the cost per keyframe bounded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class WindowSelection:
    free_kfs: list[int]          # keyframe ids adjusted
    fixed_kfs: list[int]         # keyframe ids that observe window points, held fixed
    track_ids: np.ndarray        # points adjusted (tracks with a point)

    @property
    def kfs(self) -> list[int]:
        return self.free_kfs + self.fixed_kfs


def select_window(registered: list[int], size: int, kf_tracks: dict, track_kfs: dict,
                  max_fixed: int | None = None) -> WindowSelection:
    """`registered`: keyframe ids in order of registration; `kf_tracks[k]`: track ids with a point
    that keyframe k observes (active observations only); `track_kfs[t]`: keyframes observing t.

    `max_fixed` caps the fixed keyframes (the ones sharing most points are kept): along a long
    line with many repeats the cap keeps the worst case bounded too.
    """
    free = list(registered[-size:]) if size > 0 else list(registered)
    tracks = np.unique(np.concatenate([np.asarray(kf_tracks[k], dtype=np.int64) for k in free]
                                      or [np.zeros(0, np.int64)]))
    return WindowSelection(free, sorted(neighbour_keyframes(free, tracks, track_kfs, max_fixed)), tracks)


def neighbour_keyframes(free: list[int], tracks, track_kfs: dict, max_fixed: int | None = None) -> list[int]:
    """Keyframes outside `free` observing `tracks` (`track_kfs[t]`: keyframes observing t), most
    shared tracks first (ties in the order met), at most `max_fixed` of them."""
    free_set = set(free)
    shared: dict[int, int] = {}
    for t in np.asarray(tracks).tolist():
        for k in track_kfs.get(t, ()):
            if k not in free_set:
                shared[k] = shared.get(k, 0) + 1
    fixed = sorted(shared, key=lambda k: -shared[k])
    return fixed if max_fixed is None else fixed[:max_fixed]
