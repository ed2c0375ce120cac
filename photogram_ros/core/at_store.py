"""Storage of the aerial triangulation for long flights: what left the window leaves the Python heap.

A Python dict entry and a 3-element ndarray cost ~200 bytes per tie point, and per-keyframe arrays
stay resident for the whole flight: memory grew by tens of MB per flight minute. Here:

- `PointStore`: the tie points, a dict-like {track id: (3,) map ENU} whose *frozen* points (tracks
  that can no longer be observed) live in sorted numpy arrays (~36 bytes a point) with the count of
  keyframes observing them, which replaces their per-track keyframe list.
- `KeyframeSpill`: the observation arrays of frozen keyframes, one .npy per keyframe in a spill
  folder, read back only when something needs them again (the final full adjustment, a report).
- `Keyframe`: one keyframe of the triangulation, its observation arrays in memory while it is hot
  and in a `KeyframeSpill` once frozen (when: core/at_freeze.py).

Iteration order of `PointStore` is the insertion order a plain dict would have (a sequence number
per point), so adjustments built from it are the same problems, bit for bit, as before.
"""

from __future__ import annotations

import shutil
import tempfile
import weakref
from pathlib import Path

import numpy as np

_OBS_DTYPE = np.dtype([('track_id', '<i8'), ('uv', '<f8', (2,)), ('xn', '<f8', (2,)), ('active', '?')])


class PointStore:
    """{track id: point} with hot points in a dict and frozen ones in compact sorted arrays."""

    def __init__(self):
        self._hot: dict[int, np.ndarray] = {}
        self._hot_seq: dict[int, int] = {}
        self._seq = 0
        self._f_ids = np.zeros(0, np.int64)      # sorted
        self._f_xyz = np.zeros((0, 3))
        self._f_seq = np.zeros(0, np.int64)
        self._f_count = np.zeros(0, np.int32)    # registered keyframes with an active observation
        self._f_alive = np.zeros(0, bool)
        self._n_alive = 0

    # --- frozen lookup ------------------------------------------------------------------------

    def _frozen_rows(self, ids: np.ndarray) -> np.ndarray:
        """Row of each id among the alive frozen points, -1 where it is not one."""
        ids = np.asarray(ids, np.int64)
        if not len(self._f_ids) or not len(ids):
            return np.full(len(ids), -1)
        pos = np.clip(np.searchsorted(self._f_ids, ids), 0, len(self._f_ids) - 1)
        ok = (self._f_ids[pos] == ids) & self._f_alive[pos]
        return np.where(ok, pos, -1)

    def _frozen_row(self, t: int) -> int:
        # Scalar path without temporary arrays: a per-point loop over the store (a node publishing
        # the cloud) must stay close to dict speed.
        f = self._f_ids
        if not len(f):
            return -1
        i = int(f.searchsorted(t))
        return i if i < len(f) and f[i] == t and self._f_alive[i] else -1

    # --- mapping API ----------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._hot) + self._n_alive

    def __contains__(self, t) -> bool:
        t = int(t)
        return t in self._hot or self._frozen_row(t) >= 0

    def __getitem__(self, t) -> np.ndarray:
        t = int(t)
        v = self._hot.get(t)
        if v is not None:
            return v
        r = self._frozen_row(t)
        if r < 0:
            raise KeyError(t)
        return self._f_xyz[r].copy()

    def get(self, t, default=None):
        try:
            return self[t]
        except KeyError:
            return default

    def __setitem__(self, t, xyz) -> None:
        t = int(t)
        # A copy: a view into a solver's output would keep that whole array alive.
        v = np.array(xyz, dtype=float).reshape(3)
        if t in self._hot:
            self._hot[t] = v
            return
        r = self._frozen_row(t)
        if r >= 0:
            self._f_xyz[r] = v
            return
        self._hot[t] = v
        self._hot_seq[t] = self._seq
        self._seq += 1

    def pop(self, t, *default):
        t = int(t)
        if t in self._hot:
            self._hot_seq.pop(t)
            return self._hot.pop(t)
        r = self._frozen_row(t)
        if r >= 0:
            self._f_alive[r] = False
            self._n_alive -= 1
            return self._f_xyz[r].copy()
        if default:
            return default[0]
        raise KeyError(t)

    def ids(self) -> np.ndarray:
        """Every point's track id, in insertion order (as a dict would iterate)."""
        hot_ids = np.fromiter(self._hot_seq.keys(), np.int64, len(self._hot_seq))
        hot_seq = np.fromiter(self._hot_seq.values(), np.int64, len(self._hot_seq))
        ids = np.concatenate([self._f_ids[self._f_alive], hot_ids])
        seq = np.concatenate([self._f_seq[self._f_alive], hot_seq])
        return ids[np.argsort(seq, kind='stable')]

    def __iter__(self):
        return iter(self.ids().tolist())

    def keys(self):
        return self.ids().tolist()

    def values(self):
        return list(self.get_many(self.ids()))

    def items(self):
        ids = self.ids()
        return list(zip(ids.tolist(), self.get_many(ids)))

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids, xyz (n, 3)) of every point, in insertion order: one call instead of n lookups."""
        ids = self.ids()
        return ids, self.get_many(ids)

    def contains_many(self, ids) -> np.ndarray:
        ids = np.asarray(ids, np.int64).ravel()
        # Dict lookups per queried id: the queries are a keyframe's tracks, the hot set can be the whole
        # block (freezing stops when track ids come back), so no array of the hot ids per call.
        hot_d = self._hot
        hot = np.fromiter((t in hot_d for t in ids.tolist()), bool, len(ids))
        return hot | (self._frozen_rows(ids) >= 0)

    def get_many(self, ids) -> np.ndarray:
        """(n, 3) points of `ids` (every id must be a point)."""
        ids = np.asarray(ids, np.int64).ravel()
        out = np.empty((len(ids), 3))
        rows = self._frozen_rows(ids)
        f = rows >= 0
        out[f] = self._f_xyz[rows[f]]
        if not f.all():
            out[~f] = np.array([self._hot[t] for t in ids[~f].tolist()]).reshape(-1, 3)
        return out

    def set_many(self, ids, xyz) -> None:
        ids = np.asarray(ids, np.int64).ravel()
        # One copy for the batch; its rows are the hot points (hot points are bounded by the window,
        # frozen ones are copied into the compact arrays).
        xyz = np.array(xyz, dtype=float).reshape(-1, 3)
        rows = self._frozen_rows(ids)
        f = rows >= 0
        self._f_xyz[rows[f]] = xyz[f]
        hot, seq = self._hot, self._hot_seq
        for i, t in zip(np.flatnonzero(~f).tolist(), ids[~f].tolist()):
            if t not in hot:
                seq[t] = self._seq
                self._seq += 1
            hot[t] = xyz[i]

    # --- freezing -------------------------------------------------------------------------------

    def is_frozen(self, t: int) -> bool:
        return int(t) not in self._hot and self._frozen_row(int(t)) >= 0

    def freeze(self, ids, counts) -> None:
        """Move hot points `ids` (with their observation counts) to the compact arrays."""
        cnt = dict(zip([int(t) for t in ids], counts))
        ids = [t for t in cnt if t in self._hot]
        if not ids:
            return
        new_ids = np.array(ids, np.int64)
        new_xyz = np.array([self._hot.pop(t) for t in ids]).reshape(-1, 3)
        new_seq = np.array([self._hot_seq.pop(t) for t in ids], np.int64)
        new_cnt = np.array([cnt[t] for t in ids], np.int32)
        keep = self._f_alive
        ids_all = np.concatenate([self._f_ids[keep], new_ids])
        order = np.argsort(ids_all, kind='stable')
        self._f_ids = ids_all[order]
        self._f_xyz = np.concatenate([self._f_xyz[keep], new_xyz])[order]
        self._f_seq = np.concatenate([self._f_seq[keep], new_seq])[order]
        self._f_count = np.concatenate([self._f_count[keep], new_cnt])[order]
        self._f_alive = np.ones(len(self._f_ids), bool)
        self._n_alive = len(self._f_ids)

    def thaw(self, t: int) -> int:
        """Move frozen point `t` back to the dict (same value, same place in the order); its count."""
        r = self._frozen_row(int(t))
        if r < 0:
            return 0
        self._hot[int(t)] = self._f_xyz[r].copy()
        self._hot_seq[int(t)] = int(self._f_seq[r])
        self._f_alive[r] = False
        self._n_alive -= 1
        return int(self._f_count[r])

    def frozen_count_decrement(self, t: int) -> int | None:
        """One observation of frozen point `t` dropped: its remaining count (None: not frozen)."""
        r = self._frozen_row(int(t))
        if r < 0:
            return None
        self._f_count[r] -= 1
        return int(self._f_count[r])

    @property
    def n_hot(self) -> int:
        return len(self._hot)

    @property
    def frozen_bytes(self) -> int:
        return sum(a.nbytes for a in (self._f_ids, self._f_xyz, self._f_seq, self._f_count, self._f_alive))


class KeyframeSpill:
    """Observation arrays of frozen keyframes on disk, one file per keyframe.

    `folder` None: a private temporary folder, removed when the store is garbage collected or the
    process exits.
    """

    def __init__(self, folder: str | None = None):
        if folder:
            self.folder = Path(folder)
            self.folder.mkdir(parents=True, exist_ok=True)
            self._cleanup = None
        else:
            self.folder = Path(tempfile.mkdtemp(prefix='photogram_at_spill_'))
            self._cleanup = weakref.finalize(self, shutil.rmtree, str(self.folder), True)
        self.bytes_on_disk = 0

    def path(self, kid: int) -> Path:
        return self.folder / f'kf_{kid:07d}.npy'

    def save(self, kid: int, track_ids, uv, xn, active) -> None:
        a = np.empty(len(track_ids), _OBS_DTYPE)
        a['track_id'], a['uv'], a['xn'], a['active'] = track_ids, uv, xn, active
        p = self.path(kid)
        old = p.stat().st_size if p.exists() else 0
        np.save(p, a, allow_pickle=False)
        self.bytes_on_disk += p.stat().st_size - old

    def load(self, kid: int):
        """(track_ids, uv, xn, active) as contiguous arrays."""
        a = np.load(self.path(kid), allow_pickle=False)
        return (np.ascontiguousarray(a['track_id']), np.ascontiguousarray(a['uv']),
                np.ascontiguousarray(a['xn']), np.ascontiguousarray(a['active']))


class Keyframe:
    """One keyframe: metadata always in memory, observation arrays in memory while it is *hot* and
    on disk (`KeyframeSpill`) once frozen. Reading an array of a frozen keyframe thaws it, so every
    caller stays correct; the freeze pass (core/at_freeze.py) spills it again when it may."""

    __slots__ = ('kid', 'stamp_ns', 'name', 'fix_enu', 'fix_cov', 'map_T_cam', 'antenna_offset', 'map_R_cam_prior',
                 'reg_seq', 'id_lo', 'id_hi', 'has_targets', '_arr', '_spill', '_disk_active')

    def __init__(self, kid, stamp_ns, name, track_ids, uv, xn, active, fix_enu, fix_cov, map_T_cam=None,
                 antenna_offset=None):
        self.kid, self.stamp_ns, self.name = kid, stamp_ns, name
        self.fix_enu, self.fix_cov, self.map_T_cam, self.antenna_offset = fix_enu, fix_cov, map_T_cam, antenna_offset
        self.map_R_cam_prior = None   # (3, 3) camera -> map from the autopilot's attitude and the mount, or None
        self.reg_seq = -1          # position in Block.registered (core/at_block.py), -1 while not registered
        nonneg = track_ids[track_ids >= 0]
        self.id_lo = int(nonneg.min()) if len(nonneg) else 0
        self.id_hi = int(nonneg.max()) if len(nonneg) else -1
        self.has_targets = bool(len(nonneg) < len(track_ids))
        self._arr = (track_ids, uv, xn, active)
        self._spill = None
        self._disk_active = None   # `active` as last written to disk (an unchanged keyframe is not rewritten)

    @property
    def frozen(self) -> bool:
        return self._arr is None

    def thaw(self):
        """Back in memory (a no-op when hot): (track_ids, uv, xn, active)."""
        if self._arr is None:
            self._arr = self._spill.load(self.kid)
            self._disk_active = self._arr[3].copy()
        return self._arr

    def peek(self):
        """(track_ids, uv, xn, active) without thawing (read-only use)."""
        return self._arr if self._arr is not None else self._spill.load(self.kid)

    def freeze(self, spill: KeyframeSpill) -> None:
        if self._arr is None:
            return
        if self._disk_active is None or not np.array_equal(self._disk_active, self._arr[3]):
            spill.save(self.kid, *self._arr)
        self._spill = spill
        self._arr = None
        self._disk_active = None

    track_ids = property(lambda self: self.thaw()[0])
    uv = property(lambda self: self.thaw()[1])
    xn = property(lambda self: self.thaw()[2])
    active = property(lambda self: self.thaw()[3])

    def index(self, tid: int) -> int | None:
        """Observation index of track `tid` (track ids are sorted), None if not observed."""
        ids = self.track_ids
        i = int(np.searchsorted(ids, tid))
        return i if i < len(ids) and ids[i] == tid else None

    @property
    def index_of(self) -> dict:
        return {int(t): i for i, t in enumerate(self.track_ids)}
