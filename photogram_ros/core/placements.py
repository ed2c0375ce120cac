"""Where each keyframe's fused clouds were placed, so that a keyframe whose pose moves is placed again.

A pair cloud's depth is measured in its keyframe's camera frame: it depends on the pair's relative pose, not on
the georeference. Stereo places it in `map` with the keyframe's pose of the moment (a provisional one before the
first turn included: core/pose_status.py) and says that pose (the placement) with the cloud. The map keeps, per
keyframe, each fused cloud's placement and what it merged into the cells (core/fusion.py Contribution, at the
map's cell resolution); when the keyframe's latest pose is off a placement by `move_m` or more (centre shift plus
its height above the cloud times the rotation angle), or the placement was provisional and the pose is now
final, that cloud is due to be placed again (`due`): taken out of its cells and fused again moved (Fusion.move).
With `keep_final` false only clouds placed with a provisional pose keep their contribution, until they are placed
again at the final pose (once, `move_m` 0: a final placement never moves them), then it is dropped: the records
cover the keyframes before the first turn, not the flight.

Memory is bounded by `budget_bytes`: past it the oldest contributions placed with a final pose are dropped
first (then the oldest at all); their placement stays known, so a later move of such a keyframe is counted
(`moved_not_replaced`) and said, not silently kept.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np

from photogram_ros.core.rotations import angle_between_R


def pose_move_m(before: np.ndarray, after: np.ndarray, ground_z_m: float) -> float:
    """How far a pose change moves what a keyframe sees: the camera centre's shift plus its height above the
    ground (`ground_z_m`, map z) times the rotation angle (the shift of the ground under it), m."""
    shift = float(np.linalg.norm(after[:3, 3] - before[:3, 3]))
    height = max(float(after[2, 3] - ground_z_m), 0.0)
    return shift + height * angle_between_R(before[:3, :3], after[:3, :3])


@dataclass
class Part:
    """One fused cloud of a keyframe: the pose it is placed with (None until its placement came) and its
    contribution (None: not kept, or dropped for memory)."""
    map_T_cam: np.ndarray | None
    provisional: bool
    contribution: object | None
    said_moved: bool = False   # a move that could not be followed was counted


@dataclass
class _Entry:
    waiting: deque = field(default_factory=deque)    # placements that came before their cloud: (T, provisional)
    parts: list = field(default_factory=list)
    pose: tuple | None = None                        # the keyframe's latest (map_T_cam, provisional)


class Placements:
    def __init__(self, move_m: float, budget_bytes: int, keep_final: bool = True):
        self.move_m = float(move_m)
        self.budget_bytes = int(budget_bytes)
        self.keep_final = bool(keep_final)
        self._kf: OrderedDict[int, _Entry] = OrderedDict()
        self._check: set[int] = set()      # keyframes whose placements may be off their pose
        self.nbytes = 0
        self.dropped = 0                   # contributions dropped for memory
        self.moved_not_replaced = 0        # fused clouds whose keyframe moved after their contribution was dropped

    def _entry(self, stamp: int) -> _Entry:
        e = self._kf.get(stamp)
        if e is None:
            e = self._kf[stamp] = _Entry()
        return e

    def placed_with(self, stamp: int, map_T_cam: np.ndarray, provisional: bool) -> None:
        """Stereo's placement of its next cloud of `stamp` (it comes before that cloud; a cloud that came first
        takes it)."""
        e = self._entry(stamp)
        part = next((p for p in e.parts if p.map_T_cam is None), None)
        if part is None:
            e.waiting.append((np.array(map_T_cam, float), bool(provisional)))
        else:
            part.map_T_cam, part.provisional = np.array(map_T_cam, float), bool(provisional)
            if not self._keeps(part):
                self._release(part)
            self._check.add(stamp)

    def wants_record(self, stamp: int) -> bool:
        """Whether the next cloud of `stamp` should be fused with its contribution recorded: always with
        keep_final, else when its placement is provisional or has not come yet."""
        if self.keep_final:
            return True
        e = self._kf.get(stamp)
        return not (e is not None and e.waiting and not e.waiting[0][1])

    def _keeps(self, part: Part) -> bool:
        """Whether `part`'s contribution is kept: with keep_final, or while it is (or may be) provisional."""
        return self.keep_final or part.map_T_cam is None or part.provisional

    def _release(self, part: Part) -> None:
        if part.contribution is not None:
            self.nbytes -= part.contribution.nbytes
            part.contribution = None

    def fused(self, stamp: int, contribution) -> None:
        """A cloud of `stamp` was fused with `contribution` (core/fusion.py; None: not kept)."""
        e = self._entry(stamp)
        T, prov = e.waiting.popleft() if e.waiting else (None, False)
        part = Part(T, prov, contribution)
        e.parts.append(part)
        if contribution is not None:
            self.nbytes += contribution.nbytes
            if not self._keeps(part):
                self._release(part)
        self._check.add(stamp)
        self._bound()

    def pose(self, stamp: int, map_T_cam: np.ndarray, provisional: bool) -> None:
        """The keyframe's latest pose (map/keyframe_pose, provisional or final)."""
        e = self._kf.get(stamp)
        if e is None:
            return
        e.pose = (np.array(map_T_cam, float), bool(provisional))
        self._check.add(stamp)

    def _off(self, part: Part, pose: tuple) -> bool:
        T, prov = pose
        if part.provisional and not prov:
            return True
        if self.move_m <= 0:
            return False
        ground = part.contribution.median_z_m if part.contribution is not None else T[2, 3]
        return pose_move_m(part.map_T_cam, T, ground) >= self.move_m

    def due(self) -> list[tuple[int, int]]:
        """(stamp, part index) of the fused clouds to place again, oldest keyframe first; moves that cannot be
        followed (contribution dropped) are counted in moved_not_replaced."""
        out = []
        for stamp in sorted(self._check):
            e = self._kf.get(stamp)
            if e is None or e.pose is None:
                continue
            for i, part in enumerate(e.parts):
                if part.map_T_cam is None or not self._off(part, e.pose):
                    continue
                if part.contribution is not None:
                    out.append((stamp, i))
                elif not part.said_moved:
                    part.said_moved = True
                    self.moved_not_replaced += 1
        self._check = {s for s, _ in out}
        return out

    def part(self, stamp: int, index: int) -> Part:
        return self._kf[stamp].parts[index]

    def pose_of(self, stamp: int) -> tuple:
        return self._kf[stamp].pose

    def replaced(self, stamp: int, index: int, contribution) -> None:
        """The part was placed again at its keyframe's latest pose, with the new `contribution`."""
        e = self._kf[stamp]
        part = e.parts[index]
        old = part.contribution
        self.nbytes += (contribution.nbytes if contribution is not None else 0) - (old.nbytes if old is not None else 0)
        part.map_T_cam, part.provisional = e.pose[0].copy(), e.pose[1]
        part.contribution = contribution
        if not self._keeps(part):
            self._release(part)
        self._check.discard(stamp)
        self._bound()

    def cannot_follow(self, stamp: int, index: int) -> None:
        """The part's move cannot be followed (its contribution does not fit the map any more): counted."""
        part = self._kf[stamp].parts[index]
        if part.contribution is not None:
            self.nbytes -= part.contribution.nbytes
            part.contribution = None
        part.said_moved = True
        self.moved_not_replaced += 1
        self._check.discard(stamp)

    def provisional_keyframes(self) -> int:
        """Keyframes with a fused cloud placed with a provisional pose now."""
        return sum(any(p.provisional and p.map_T_cam is not None for p in e.parts) for e in self._kf.values())

    def _bound(self) -> None:
        if self.nbytes <= self.budget_bytes:
            return
        for final_only in (True, False):
            for e in self._kf.values():
                if self.nbytes <= self.budget_bytes:
                    return
                if final_only and any(p.provisional for p in e.parts):
                    continue
                for p in e.parts:
                    if p.contribution is not None:
                        self.nbytes -= p.contribution.nbytes
                        p.contribution = None
                        self.dropped += 1
