"""The tracker's second look at a break: SIFT features of the image descriptor matching does not use
(`TrackerParams.features_fallback`; core/tracker.py calls it).

The tracker detects its matching features on one image of a frame (`features_on`: the reduced grey after its
photometric normalisation, or as decoded). CLAHE makes KLT precise but can cost a weak pair its verified matches
(brighton_beach every other photo: DJI_0018-DJI_0020 give 20 inliers on the raw grey, 9 after CLAHE), and raw
alone loses near-infrared keyframes elsewhere (seneca). So the other image is looked at only where a break
needs it:

- a keyframe made at or after a break (photo-rate input) also publishes the features of its other image as
  tracks (`publish`), matched first with those of the weak keyframes it overlaps by GNSS (the first keyframe, or
  one whose break only the other image bridged, until a later frame verifies it with its usual features; the
  newest `hold_weak`): a match takes their track id; then one within 1 px of a track the keyframe already
  publishes takes its id, the others new ids; they are held for the last `match_keyframes` keyframes and the
  weak ones (`keep`);
- a frame at a break that verified no keyframe with its usual features is matched once more on its other
  image against what those keyframes published so (`recover`), nearest by GNSS first: a matched feature takes
  the keyframe's track id; the first keyframe that verifies at least `min_inliers` linked features wins.

The cost: one more SIFT extraction per keyframe after a break.

Nothing here reads ROS or files; the caller gives images, positions and the track-id counter.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.photo_matching import MatchingOptions, PhotoFeatures, extract, match_pair

def first_per_id(ids: np.ndarray) -> None:
    """One entry per track id in the (K,) int64 ids (-1: none), in place: the first keeps it, the others -1."""
    _, first = np.unique(np.where(ids >= 0, ids, -1 - np.arange(len(ids))), return_index=True)
    dup = np.ones(len(ids), bool)
    dup[first] = False
    ids[dup] = -1


class OtherImageFallback:
    """Features of a frame's other image (see the module doc). `inside(uv)` says which reduced-image pixels are
    far enough inside the image to be tracks; `new_ids(n)` hands out fresh track ids (int64); `position(stamp_ns)`
    the (3,) local metres of the GNSS fix at a stamp, or None; `params` the tracker's (its `features_on` and
    `features_fallback`: off, every method does nothing); `hold_weak`: how many weak keyframes' features are
    held beyond the last ones (the newest)."""

    def __init__(self, camera: PinholeCamera, options: MatchingOptions, inside: Callable[[np.ndarray], np.ndarray],
                 new_ids: Callable[[int], np.ndarray], position: Callable[[int], np.ndarray | None], params,
                 hold_weak: int = 8):
        self.camera = camera
        self.options = options
        self.hold_weak = hold_weak
        self._inside = inside
        self._new_ids = new_ids
        self._position = position
        self._on = bool(params.features_fallback)
        self._raw_is_usual = params.features_on == 'raw'
        self._features: dict[int, tuple[PhotoFeatures, np.ndarray]] = {}   # frame index -> features, track ids
        self._published: dict[int, tuple[PhotoFeatures, np.ndarray]] = {}  # keyframe index -> the same
        self._weak: list[int] = []           # keyframes no later frame linked by its usual features, oldest first
        self._bridged_frames: set[int] = set()   # frames whose break only the other image bridged
        self.bridged = 0     # breaks bridged by the other image only
        self.pairs = 0       # keyframes matched on the other image
        self.verified = 0    # ... of them verified

    def image_of(self, gray: np.ndarray, raw: np.ndarray | None) -> np.ndarray | None:
        """A frame's image that descriptor matching does not use: of its normalised grey `gray` and its reduced grey
        as decoded `raw` (None: no other, the same image), the one `features_on` does not name; None when off."""
        if not self._on or raw is None:
            return None
        return gray if self._raw_is_usual else raw

    def _distance_m(self, a_ns: int, b_ns: int) -> float:
        a, b = self._position(a_ns), self._position(b_ns)
        return float(np.linalg.norm((a - b)[:2])) if a is not None and b is not None else 0.0

    def features(self, index: int, image: np.ndarray) -> tuple[PhotoFeatures, np.ndarray]:
        """SIFT of frame `index`'s other image (reduced-image pixels) and its track ids (-1: none yet), computed
        once per frame; of features at one position (SIFT's orientations) only the first."""
        got = self._features.get(index)
        if got is None:
            f = extract(str(index), image, (1.0, 1.0), self.options)
            _, first = np.unique(np.round(f.uv, 1), axis=0, return_index=True)
            first.sort()
            f = PhotoFeatures(f.name, f.uv[first], f.desc[first],
                              f.response[first] if f.response is not None else None)
            got = self._features[index] = (f, np.full(len(f.uv), -1, np.int64))
        return got

    def _match(self, key: int, f: PhotoFeatures, ids: np.ndarray, inside: np.ndarray) -> int:
        """Frame features `f` matched with keyframe `key`'s published ones; open ones (id -1) that match take its
        track ids. How many took one (0: not verified)."""
        kf, kids = self._published[key]
        self.pairs += 1
        m = match_pair(kf, f, self.camera, self.options)
        if not m.verified:
            return 0
        self.verified += 1
        rows, dst = m.matches[:, 0], m.matches[:, 1]
        keep = (kids[rows] >= 0) & inside[dst] & (ids[dst] < 0) & ~np.isin(kids[rows], ids)
        ids[dst[keep]] = kids[rows[keep]]
        first_per_id(ids)
        return int(keep.sum())

    def recover(self, index: int, gray: np.ndarray, raw: np.ndarray | None, stamp_ns: int,
                keyframes: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray] | None:
        """Frame `index` (stamp_ns) at a break that verified no keyframe: its other image (`image_of(gray, raw)`)
        matched against what the `keyframes` (keyframe index, stamp ns) published of theirs, nearest by GNSS
        first. Returns (pts, ids) of the first keyframe's linked tracks that verifies `min_inliers` of them
        (reduced-image pixels, uint32 ids), or None."""
        opt = self.options
        image = self.image_of(gray, raw)
        if image is None:
            return None
        f, ids = self.features(index, image)
        if len(f.uv) < opt.min_inliers:
            return None
        inside = self._inside(f.uv)
        for k, _ in sorted(keyframes, key=lambda ks: self._distance_m(ks[1], stamp_ns)):
            if k not in self._published:
                continue
            ids[:] = -1
            if self._match(k, f, ids, inside) >= opt.min_inliers:
                self.bridged += 1
                self._bridged_frames.add(index)
                take = ids >= 0
                return f.uv[take].astype(np.float32), ids[take].astype(np.uint32)
        ids[:] = -1
        return None

    def linked(self, key: int) -> None:
        """A later frame verified keyframe `key` with its usual features: not weak any more."""
        if key in self._weak:
            self._weak.remove(key)

    def publish(self, index: int, key: int, gray: np.ndarray, raw: np.ndarray | None, klt: tuple, extra: tuple,
                overlapping: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Frame `index`, made keyframe `key` at or after a break, publishes its other image's features
        (`image_of(gray, raw)`; none: nothing). First they are matched with those of the weak keyframes held among
        `overlapping` (keyframe indices whose footprints it overlaps by GNSS; a weak keyframe: the first, or one
        whose break only the other image bridged, that no later frame verified with its usual features): a match
        takes their track id. Then one within 1 px of a track the keyframe shows (`klt` and `extra`: (pts, ids)
        each, reduced-image pixels and uint32 ids) takes its id, the others get new ids. Returns `extra` with those
        whose id the keyframe does not show yet added (float32, uint32); all are held for later frames."""
        from scipy.spatial import cKDTree
        image = self.image_of(gray, raw)
        if image is None:
            return extra
        shown_pts, shown_ids = (np.concatenate([a, b]) for a, b in zip(klt, extra))
        f, ids = self.features(index, image)
        ok = self._inside(f.uv)
        for k in overlapping:
            if k in self._weak and k in self._published:
                self._match(k, f, ids, ok)
        ids[~ok] = -1
        shown = np.asarray(shown_ids, np.int64)
        lone = np.flatnonzero(ok & (ids < 0))
        if len(shown) and len(lone):
            d, near = cKDTree(np.asarray(shown_pts, np.float64)).query(f.uv[lone], distance_upper_bound=1.0)
            hit = np.isfinite(d) & ~np.isin(shown[np.minimum(near, len(shown) - 1)], ids)
            ids[lone[hit]] = shown[near[hit]]
            first_per_id(ids)
            lone = np.flatnonzero(ok & (ids < 0))
        ids[lone] = self._new_ids(len(lone))
        self._published[key] = (f, ids)
        if not self._published.keys() - {key} or index in self._bridged_frames:
            self._weak = (self._weak + [key])[-self.hold_weak:]
        add = np.flatnonzero(ok & ~np.isin(ids, shown))
        return (np.concatenate([extra[0], f.uv[add].astype(np.float32)]),
                np.concatenate([extra[1], ids[add].astype(np.uint32)]))

    def keep(self, recent) -> None:
        """Hold what the keyframes `recent` (keyframe indices) and the weak ones published; drop the features of
        frames that were not published."""
        keep = set(int(i) for i in recent) | set(self._weak)
        self._published = {i: v for i, v in self._published.items() if i in keep}
        self._features = {}
        self._bridged_frames = set()

    def nbytes(self) -> int:
        """Bytes of the features held."""
        return sum(f.uv.nbytes + f.desc.nbytes + ids.nbytes for f, ids in self._published.values())
