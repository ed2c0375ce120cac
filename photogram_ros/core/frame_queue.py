"""The frames waiting for the tracker, and which one goes when the camera outpaces it.

Beyond `size` frames waiting, one frame is dropped only when the chain can spare it: the waiting frame
whose removal leaves the smallest GNSS gap between the frames on either side of it (the frame taken
before it, or the waiting one before it, and the waiting one after it), and only when that gap is no
larger than the spacing at which the tracker takes keyframes (`spacing_m`: the median GNSS distance
between its recent keyframes; a frame closer than that to both neighbours is overlap the keyframe rule
would skip anyway). A frame whose removal would leave a wider gap is needed: it is kept and the queue
grows past `size` (the tracker falls behind instead of losing the chain) up to `max_bytes` of frames;
beyond that the most redundant frame goes anyway and the drop says so. Without GNSS positions (no fix
near the stamps, or no keyframe spacing known yet for a queue over `max_bytes`) the oldest waiting frame
is dropped, as a plain bounded queue does. The newest frame is never the one dropped: it is the frame a
gap is measured to. Each drop comes back as a `Dropped` with its reason, for /diagnostics.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Callable

from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.core.keyframes import gps_distance_m


@dataclass
class Dropped:
    item: object
    stamp_ns: int
    reason: str        # 'redundant', 'no_position', 'over_memory'
    gap_m: float       # the GNSS gap its removal left (nan: unknown)
    message: str


@dataclass
class _Entry:
    item: object
    stamp_ns: int
    nbytes: int
    fix: GnssFix | None = None


class FrameQueue:
    """Frames (any object, with its stamp and size in bytes) in arrival order; `push` applies the drop rule."""

    def __init__(self, size: int, max_bytes: int):
        self.size = size
        self.max_bytes = max_bytes
        self._q: deque[_Entry] = deque()
        self._taken: _Entry | None = None     # the last frame handed to the tracker
        self.nbytes = 0
        self.kept_over_size = 0               # pushes that left the queue over `size` (frames the chain needs)

    def __len__(self) -> int:
        return len(self._q)

    def __iter__(self):
        return (e.item for e in self._q)

    def stamps(self) -> list[int]:
        return [e.stamp_ns for e in self._q]

    def extend(self, items) -> None:
        """Queue items without the drop rule (stamp 0, size 0)."""
        for it in items:
            self._q.append(_Entry(it, 0, 0))

    def popleft(self):
        e = self._q.popleft()
        self.nbytes -= e.nbytes
        self._taken = e
        return e.item

    def push(self, item, stamp_ns: int, nbytes: int, fix_of: Callable[[int], GnssFix | None],
             spacing_m: float | None) -> list[Dropped]:
        """Queue a frame; returns what was dropped to keep the queue within `size` (and `max_bytes`).
        `fix_of(stamp_ns)`: the GNSS fix at a stamp or None; `spacing_m`: the tracker's keyframe spacing or None."""
        self._q.append(_Entry(item, int(stamp_ns), int(nbytes)))
        self.nbytes += int(nbytes)
        out = []
        while len(self._q) > self.size:
            d = self._drop_one(fix_of, spacing_m, self.nbytes > self.max_bytes)
            if d is None:
                self.kept_over_size += 1
                break
            out.append(d)
        return out

    def _fix(self, e: _Entry | None, fix_of) -> GnssFix | None:
        if e is not None and e.fix is None:
            e.fix = fix_of(e.stamp_ns)
        return None if e is None else e.fix

    def _remove(self, k: int, reason: str, gap_m: float, message: str) -> Dropped:
        e = self._q[k]
        del self._q[k]
        self.nbytes -= e.nbytes
        return Dropped(e.item, e.stamp_ns, reason, gap_m, message)

    def _drop_one(self, fix_of, spacing_m, over_memory: bool) -> Dropped | None:
        q = list(self._q)
        fixes = [self._fix(e, fix_of) for e in q]
        before = self._fix(self._taken, fix_of) if self._taken is not None else None
        gaps = []            # (gap left, k) of the waiting frames but the newest, all three fixes known
        unknown = []
        for k in range(len(q) - 1):
            prev = fixes[k - 1] if k else before
            if k == 0 and self._taken is None:
                prev = fixes[0]    # the first frame of the stream: its gap is the one to the next
            if prev is None or fixes[k] is None or fixes[k + 1] is None:
                unknown.append(k)
            else:
                gaps.append((gps_distance_m(prev, fixes[k + 1]), k))
        if gaps:
            gap, k = min(gaps)
            if spacing_m is not None and gap <= spacing_m:
                return self._remove(k, 'redundant', gap, (
                    f'frame stamped {q[k].stamp_ns * 1e-9:.3f} s dropped as redundant: frames come faster than the '
                    f'tracker takes them ({len(q)} waiting) and the frames either side of it are {gap:.1f} m apart '
                    f'by GNSS, within the keyframe spacing ({spacing_m:.1f} m)'))
        if unknown and (not gaps or over_memory):
            k = unknown[0]
            return self._remove(k, 'no_position', float('nan'), (
                f'frame stamped {q[k].stamp_ns * 1e-9:.3f} s dropped: frames come faster than the tracker takes '
                f'them ({len(q)} waiting) and without a GNSS position the oldest waiting one goes'))
        if over_memory and gaps:
            gap, k = min(gaps)
            return self._remove(k, 'over_memory', gap, (
                f'frame stamped {q[k].stamp_ns * 1e-9:.3f} s dropped though the chain may need it (a gap of '
                f'{gap:.1f} m by GNSS, keyframe spacing {"unknown" if spacing_m is None else f"{spacing_m:.1f} m"}): '
                f'{len(q)} frames waiting hold {self.nbytes / 1e6:.0f} MB, over the queue\'s '
                f'{self.max_bytes / 1e6:.0f} MB'))
        return None
