"""Segments: the flight after every track was lost.

Keyframes that share no tie point with the block (a long gap in the frames) start a block of their own, a segment
(an adjuster of its own in the same map frame, core/incremental.py), which joins the block as soon as it can:
through the tracker's tie points both have triangulated (the tracker's chain gives a keyframe after a break the
ids of the earlier keyframes it overlaps: a RANSAC similarity fitted to those shared points, whether or not
either is georeferenced), through the manual tie points both have (a similarity fitted to three or more, a shift
to one or two), or else through its GNSS once that georeferences it. `Segments` holds the segment being grown,
the block's ids of its keyframes, and the joins made.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photogram_ros.core.at_store import Keyframe
from photogram_ros.core.part_options import check
from photogram_ros.core.similarity import Similarity, similarity_ransac, spread
from photogram_ros.params import param

# A shared tie point fits the similarity segment -> block within this fraction of the distance the block's
# cameras see it from (triangulation noise of short baselines; a wrong track is off by a footprint's share).
TIE_FIT_DEPTH_FRACTION = 0.02
# The shared points the similarity keeps must span an area: their second spread at least this of their first.
TIE_MIN_SPREAD_RATIO = 0.2


@dataclass(frozen=True)
class SegmentOptions:
    """The options of segments after a break (`Segments`)."""
    segments: bool = param(True, 'keyframes that share no tie point with the block (every track lost: a long gap '
                                 'in the frames) start a segment of their own, which joins the block through the '
                                 'tracker\'s tie points both have triangulated as soon as they are '
                                 '`segment_min_tie_points`, else through its GNSS once that georeferences it (or at '
                                 'the end of the flight)')

    def __post_init__(self):
        check(self)


class Segments:
    """The segments of `block` (core/at_block.py), for the options `opt`."""

    def __init__(self, block, opt: SegmentOptions):
        self.block, self.opt = block, opt
        # The segment's adjuster (an IncrementalAT) and the block's ids of its keyframes (in order).
        self.current = None
        self.kids: list[int] = []
        self.joined = 0
        # Each segment that joined: its keyframes and how ('ties', 'mtp' or 'gnss', with the points used).
        self.joins: list[dict] = []
        # Keyframes of a block before a break that its GNSS could not place, given up for the segment after it.
        self.unplaced = 0
        # The last try to join the current segment through the tracker's tie points (`tracks_fit`): the ids its
        # keyframes share with the block's ('observed': seen by an oriented keyframe of both; 'points':
        # triangulated in both), the similarity's inliers, and why it did not join ('' when it did).
        self.last_fit = self._fit_note(0, 0, 0, 'no segment')

    def last_join_try(self) -> dict:
        """The waiting segment's last try to join through the tracker's tie points: the tracker ids it shares
        with the block (seen / triangulated in both / fitting) and why it did not join (a copy)."""
        return dict(self.last_fit)

    def joins_made(self) -> list[dict]:
        """Each segment that joined: {'keyframes', 'through' ('ties': the tracker's tie points, 'mtp': manual
        tie points, 'gnss'), 'mtps', 'ties' (the tracker's tie points the similarity kept), 'shared_observed',
        'shared_points' (tracker ids its keyframes shared with the block, seen / triangulated in both, at its
        last try through the tie points), 'why' (why that try did not join it; '' when it did)} (copies)."""
        return [dict(j) for j in self.joins]

    @staticmethod
    def _fit_note(observed: int, points: int, inliers: int, why: str) -> dict:
        return {'shared_observed': int(observed), 'shared_points': int(points), 'inliers': int(inliers), 'why': why}

    def shared_observed(self) -> int:
        """Tracker ids the current segment's oriented keyframes observe that an oriented keyframe of the block
        observes too (what the tracker handed on across the break, triangulated or not)."""
        seg = self.current
        if seg is None:
            return 0
        ids = [seg.block.kfs[k].track_ids for k in seg.block.registered]
        ids = np.concatenate(ids) if ids else np.zeros(0, np.int64)
        return len(set(ids[ids >= 0].tolist()) & self.block.track_kfs.keys())

    def start(self, adjuster) -> None:
        """Grow the keyframes that follow in `adjuster`, a new segment."""
        self.current, self.kids = adjuster, []

    def wanted(self, kf: Keyframe) -> bool:
        """A keyframe with a fix that shares no track with the block (no point, no observation in an oriented
        keyframe): the tracker lost every track. One that shares tracks waits for them to become points."""
        if not self.opt.segments or not self.block.registered or kf.fix_enu is None:
            return False
        if self.current is not None:
            return True
        ids = kf.track_ids[kf.track_ids >= 0]
        return not (self.block.points.contains_many(ids).any() or any(int(t) in self.block.track_kfs for t in ids))

    def shared_ties(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(segment point, block point) of the manual tie points both have triangulated (map frame)."""
        seg = self.current
        if seg is None or not self.block.ties:
            return []
        out = []
        for name in sorted(self.block.ties):
            a, b = seg.block.target_ids.get(name), self.block.target_ids.get(name)
            if a is not None and b is not None and a in seg.block.points and b in self.block.points:
                out.append((np.asarray(seg.block.points[a], float), np.asarray(self.block.points[b], float)))
        return out

    def ties_fit(self):
        """(similarity segment -> block, manual tie points used, whether it is a full similarity): a
        similarity from three or more shared MTPs that span an area (not on a line), else a shift from
        their offsets (the segment's own georeference then gives the rotation and scale); None without."""
        from photogram_ros.core.similarity import Similarity, umeyama
        pairs = self.shared_ties()
        if not pairs:
            return None, 0, False
        src = np.array([p for p, _ in pairs])
        dst = np.array([q for _, q in pairs])
        sv = spread(src)
        if len(pairs) >= 3 and sv[1] >= 0.2 * sv[0] > 0:
            return umeyama(src, dst), len(pairs), True
        return Similarity(1.0, np.eye(3), np.median(dst - src, axis=0)), len(pairs), False

    def can_join(self) -> bool:
        """The block is georeferenced and the segment is too (by its GNSS), or shares manual tie points that
        place it alone (three or more spanning an area)."""
        seg = self.current
        if seg is None or not seg.block.registered or not self.block.georeferenced:
            return False
        return seg.block.georeferenced or self.ties_fit()[2]

    def tracks_fit(self, min_points: int, rng: np.random.Generator | None = None):
        """(similarity segment -> block, the shared ids it fits, the shared ids it does not) from the tracker's
        tie points both have triangulated: RANSAC (a wrong track, a feature matched to the wrong one, is left
        out), at least `min_points` inliers spanning an area and at least half of the shared points; (None, ids,
        ids) without. Neither needs to be georeferenced: the similarity carries the scale between them."""
        seg = self.current
        none = np.zeros(0, np.int64)
        if seg is None or not seg.block.registered or not self.block.registered:
            self.last_fit = self._fit_note(0, 0, 0, 'the segment has no oriented keyframe yet')
            return None, none, none
        observed = self.shared_observed()
        ids, P = seg.block.points.arrays()
        both = ((ids >= 0) & self.block.points.contains_many(ids)) if len(ids) else np.zeros(0, bool)
        ids, src = ids[both], P[both]
        if len(ids) < max(min_points, 3):
            self.last_fit = self._fit_note(observed, len(ids), 0, f'{len(ids)} shared tie points triangulated in '
                                           f'both (of {observed} ids seen in both), under {max(min_points, 3)}')
            return None, none, none
        dst = self.block.points.get_many(ids)
        C = np.array([self.block.kfs[k].map_T_cam[:3, 3] for k in self.block.registered])
        depth = np.median(np.min(np.linalg.norm(dst[:, None, :] - C[None, :, :], axis=2), axis=1))
        res = similarity_ransac(src, dst, TIE_FIT_DEPTH_FRACTION * depth, rng or np.random.default_rng(0),
                                min_spread_ratio=TIE_MIN_SPREAD_RATIO)
        if not res.ok:
            self.last_fit = self._fit_note(observed, len(ids), 0, f'no similarity fits {len(ids)} shared tie points '
                                           f'(RANSAC: {res.status})')
            return None, none, none
        n = int(res.inliers.sum())
        sv = spread(dst[res.inliers])
        why = (f'{n} of {len(ids)} shared tie points fit, under {min_points}' if n < min_points else
               f'{n} of {len(ids)} shared tie points fit, under half' if 2 * n < len(ids) else
               f'the {n} fitting shared tie points lie on a line' if sv[1] < TIE_MIN_SPREAD_RATIO * sv[0] else '')
        self.last_fit = self._fit_note(observed, len(ids), n, why)
        if why:
            return None, none, none
        return res.sim, ids[res.inliers], ids[~res.inliers]

    def move_onto(self, s: Similarity) -> None:
        """Move the segment (poses and points) by the similarity `s`."""
        seg = self.current
        for k in seg.block.registered:
            seg.block.kfs[k].map_T_cam = s.apply_pose(seg.block.kfs[k].map_T_cam)
        ids, P = seg.block.points.arrays()
        if len(ids):
            seg.block.points.set_many(ids, s.apply(P))

    def move_onto_ties(self) -> int:
        """Move the segment (poses and points) onto the block through the manual tie points both have
        (`ties_fit`). Returns how many were used."""
        s, n, full = self.ties_fit()
        seg = self.current
        if s is None or not (full or seg.block.georeferenced):
            return 0
        self.move_onto(s)
        seg.block.georeferenced = True
        return n

    def join_by_tracks(self, min_points: int) -> int:
        """Join the segment through the tracker's tie points both have triangulated (`tracks_fit`), moving it
        onto the block first; its keyframes' observations of the shared points the similarity does not fit are
        not used. Returns how many keyframes joined (0: no fit)."""
        s, fit, bad = self.tracks_fit(min_points)
        if s is None:
            return 0
        self.move_onto(s)
        return self.join(through='ties', n_ties=len(fit), drop_ids=bad)

    def join(self, through: str | None = None, n_ties: int = 0, drop_ids=None) -> int:
        """Move the segment's oriented keyframes and points into the block (through the manual tie points
        both share, when there are any, else through its GNSS; `through` 'ties': the caller moved it onto the
        block by the tracker's tie points, `n_ties` of them, `drop_ids` the shared ids that disagree); returns
        how many joined."""
        n_mtps = 0 if through == 'ties' else self.move_onto_ties()
        seg, kids = self.current, self.kids
        self.current, self.kids = None, []
        drop = np.zeros(0, np.int64) if drop_ids is None else np.asarray(drop_ids, np.int64)
        for s_kid in seg.block.registered:
            kf, skf = self.block.kfs[kids[s_kid]], seg.block.kfs[s_kid]
            kf.map_T_cam = np.asarray(skf.map_T_cam, float).copy()
            # The segment's outliers, by tracker id (its target ids are numbered on their own).
            dropped = skf.track_ids[~skf.active]
            kf.active[np.isin(kf.track_ids, np.concatenate([dropped[dropped >= 0], drop]))] = False
            self.block.enrol(kf)
        ids, P = seg.block.points.arrays()
        # Tracker ids only: the segment numbers its targets on its own; the block triangulates them below.
        new = (~self.block.points.contains_many(ids) & (ids >= 0)) if len(ids) else np.zeros(0, bool)
        if new.any():
            self.block.points.set_many(ids[new], P[new])
        self.block.retriangulate_ties()
        self.joined += 1
        how = through or ('mtp' if n_mtps else 'gnss')
        self.joins.append({'keyframes': len(seg.block.registered), 'through': how, 'mtps': n_mtps,
                           'ties': n_ties, **self.last_fit})
        self.last_fit = self._fit_note(0, 0, 0, 'no segment')
        return len(seg.block.registered)
