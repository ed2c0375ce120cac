"""2.5D fusion of dense pair clouds into a tiled height grid with bounded memory.

The map is a grid of square cells (`cell_m`) in the `map` ENU frame, cut into square tiles of
`tile_cells` x `tile_cells` cells keyed by integer tile indices (ti, tj) = floor(cell index / tile_cells).
Each cell keeps a running mean of position and colour, the number of points and of pairs that
contributed, and the running variance of z (Chan's parallel update, so one pair's points merge in
one step).

Outliers are rejected in three steps, all vectorised over the pair's points:
1. speckle inside the pair: a point farther than max(2.5 sigma, min_tolerance_m) from the mean of
   its 4x4-cell block (two passes, the second without the first's rejects) is dropped;
2. consistency between pairs: a point must agree with its cell's fused height (built by the
   earlier pairs) within max(k_sigma * sigma_z, min_tolerance_m);
3. a cell where the whole new pair disagrees counts a rejection; once rejections outnumber the
   pairs that built the cell, the cell is rebuilt from the newest pair, so a bad first pair
   cannot lock a cell forever.

A fused pair cloud can be moved (`add(..., record=True)` returns its `Contribution`: what it merged into each
cell, at the cell's resolution; `move` takes it out of its cells exactly, the reverse of the running-mean update,
and fuses it again transformed, as a keyframe's cloud follows its pose; `remove` only takes it out). A cell
rebuilt by step 3 after the contribution was fused no longer holds it: taking it out there empties at most
what the cell holds.

Memory is bounded by evicting the least recently touched tiles to a store (see io/map_store.py)
once more than `max_tiles_in_memory` are held; an evicted tile reloads on demand. Without a store
nothing is evicted (there would be nowhere to put it).
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from photogram_ros.core import gsd, offheap
from photogram_ros.errors import ConfigError, DataError
from photogram_ros.params import param

# One fused cell. x, y are offsets from the tile's south-west corner so float32 keeps 0.1 mm.
CELL_DTYPE = np.dtype([
    ('n', '<u4'),            # points fused
    ('n_pairs', '<u2'),      # pair clouds fused
    ('n_rejected', '<u2'),   # pair clouds rejected since the cell was (re)built
    ('x', '<f4'), ('y', '<f4'), ('z', '<f4'),   # mean position (x, y tile-relative; z map ENU), m
    ('m2_z', '<f4'),         # sum of squared z deviations, m^2
    ('r', '<f4'), ('g', '<f4'), ('b', '<f4'),    # mean colour, 0..255
    ('confidence', '<f4'),   # mean stereo confidence
])


# What one fused cloud merged into one cell (Fusion.add(record=True)), compact: cell indices relative to the
# contribution's base cell, the point mean's position inside its cell in 1/256 of the cell, colour and
# confidence quantised to a byte (what taking it out again leaves is within those steps).
CONTRIB_DTYPE = np.dtype([
    ('di', '<i2'), ('dj', '<i2'),   # cell index - the contribution's base cell
    ('n', '<u2'),                   # points merged
    ('fx', 'u1'), ('fy', 'u1'),     # mean position inside the cell, 1/256 of cell_m
    ('z', '<f4'),                   # mean z, m
    ('m2_z', '<f2'),                # the points' sum of squared z deviations, m^2
    ('r', 'u1'), ('g', 'u1'), ('b', 'u1'),
    ('confidence', 'u1'),           # mean stereo confidence x 255
])


@dataclass
class Contribution:
    """What one fused cloud merged into the map, cell by cell (CONTRIB_DTYPE), at the map's cell resolution."""
    base: tuple[int, int]     # global cell index (ix, iy) the records' di, dj are relative to
    cell_m: float
    cells: np.ndarray         # CONTRIB_DTYPE

    @property
    def nbytes(self) -> int:
        return int(self.cells.nbytes)

    def ij(self) -> tuple[np.ndarray, np.ndarray]:
        return (self.base[0] + self.cells['di'].astype(np.int64), self.base[1] + self.cells['dj'].astype(np.int64))

    def points(self, map_T_map: np.ndarray | None = None) -> np.ndarray:
        """The contribution as one weighted point per cell (x, y, z, rgb, confidence, n, m2_z), map ENU, moved
        by `map_T_map` (4x4, the new placement times the old one's inverse) when given."""
        c = self.cells
        ix, iy = self.ij()
        xyz = np.column_stack([(ix + (c['fx'] + 0.5) / 256.0) * self.cell_m,
                               (iy + (c['fy'] + 0.5) / 256.0) * self.cell_m, c['z'].astype(np.float64)])
        if map_T_map is not None:
            xyz = xyz @ map_T_map[:3, :3].T + map_T_map[:3, 3]
        out = np.empty(len(c), dtype=[('x', '<f8'), ('y', '<f8'), ('z', '<f8'), ('rgb', '<u4'),
                                      ('confidence', '<f4'), ('n', '<u4'), ('m2_z', '<f4')])
        out['x'], out['y'], out['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        out['rgb'] = pack_rgb(c['r'], c['g'], c['b'])
        out['confidence'] = c['confidence'] / 255.0
        out['n'] = c['n']
        out['m2_z'] = c['m2_z']
        return out

    @property
    def median_z_m(self) -> float:
        return float(np.median(self.cells['z'])) if len(self.cells) else 0.0


@dataclass
class FusionConfig:
    """The fusion's parameters (the map node's cell and tile geometry, memory bound and rejection rules)."""
    cell_m: float = param(gsd.AUTO, 'Fusion cell size, m; -1: from the GSD (core/gsd.py: 0.12 m for the '
                                    'simulator\'s 640x480 at 40 m), set by the map node or densify before fusing',
                          min=gsd.AUTO, max=10.0)
    tile_cells: int = param(256, 'Cells per tile side (tile = cell_m * tile_cells metres)', min=8, max=4096)
    max_tiles_in_memory: int = param(64, 'Tiles held in memory; least recently touched ones go to disk',
                                     min=1, max=100000)
    k_sigma: float = param(3.0, 'A pair disagreeing with a cell by more than k sigma (and min_tolerance_m) '
                                'is rejected there', min=0.5, max=100.0)
    min_tolerance_m: float = param(gsd.AUTO, 'Smallest height disagreement that rejects a pair, m; -1: scaled with '
                                             'the cell (0.3 m at 0.12 m cells)', min=gsd.AUTO, max=1e3)
    min_confidence: float = param(0.3, 'Points with a lower stereo confidence are not fused (0 keeps all)',
                                  min=0.0, max=1.0)

    def check(self) -> None:
        gsd.check_auto_or_at_least(self, {'cell_m': 0.005, 'min_tolerance_m': 0.0})
        if self.cell_m != gsd.AUTO and not (self.cell_m > 0 and np.isfinite(self.cell_m)):
            raise ConfigError(f'fusion cell size {self.cell_m} m must be positive')
        if not 8 <= self.tile_cells <= 4096:
            raise ConfigError(f'tile_cells {self.tile_cells} must be within [8, 4096]')
        if self.max_tiles_in_memory < 1:
            raise ConfigError('max_tiles_in_memory must be at least 1')

    @property
    def tile_m(self) -> float:
        return self.cell_m * self.tile_cells


class Tile:
    """Dense cells of one tile plus what changed since the last flush and the last stream.

    Held as one array per field (fancy indexing of a structured array copies whole records, which
    was most of the fusion time); `records()` gives the CELL_DTYPE layout for storage.
    """

    def __init__(self, key: tuple[int, int], tile_cells: int, cells: np.ndarray | None = None):
        self.key = key
        n = tile_cells * tile_cells
        # Off the heap: a tile lives for minutes among each cloud's temporaries (see core/offheap.py),
        # and an evicted one gives its memory back at once.
        self.f = {name: (offheap.copy(cells[name]) if cells is not None
                         else offheap.zeros(n, CELL_DTYPE.fields[name][0]))
                  for name in CELL_DTYPE.names}
        self.dirty = np.zeros(n, dtype=bool)     # not yet handed to the store

    def records(self, idx=None) -> np.ndarray:
        n = self.f['n'].size if idx is None else len(idx)
        out = np.empty(n, dtype=CELL_DTYPE)
        for name, arr in self.f.items():
            out[name] = arr if idx is None else arr[idx]
        return out

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.f.values()) + self.dirty.nbytes


@dataclass
class FusionStats:
    clouds: int = 0
    points_in: int = 0
    points_fused: int = 0
    points_rejected: int = 0
    points_invalid: int = 0          # non-finite or below min_confidence
    cells_replaced: int = 0
    tiles_evicted: int = 0
    tiles_loaded: int = 0
    extra: dict = field(default_factory=dict)


def _int32(v: int) -> int:
    return v - (1 << 32) if v >= (1 << 31) else v


class Fusion:
    """Fuses pair clouds (structured arrays with x, y, z and optionally rgb, confidence)."""

    def __init__(self, config: FusionConfig | None = None, store=None):
        config = config or FusionConfig()
        config.check()
        if config.cell_m == gsd.AUTO:
            raise ConfigError('the fusion cell_m is left to the GSD: resolve it first (core/gsd.resolve), or set it')
        if config.min_tolerance_m == gsd.AUTO:
            config = dataclasses.replace(config, min_tolerance_m=gsd.tolerance_for_cell(config.cell_m))
        self.config = config
        self.store = store
        self.tiles: OrderedDict[tuple[int, int], Tile] = OrderedDict()
        self.stats = FusionStats()
        self.changed_tiles: set[tuple[int, int]] = set()   # since the caller last cleared it

    # --- tiles -----------------------------------------------------------------------------------

    def tile_origin_m(self, key) -> tuple[float, float]:
        t = self.config.tile_m
        return key[0] * t, key[1] * t

    def _tile(self, key: tuple[int, int]) -> Tile:
        tile = self.tiles.get(key)
        if tile is not None:
            self.tiles.move_to_end(key)
            return tile
        cells = self.store.load_tile(key) if self.store is not None else None
        if cells is not None:
            self.stats.tiles_loaded += 1
        tile = Tile(key, self.config.tile_cells, cells)
        self.tiles[key] = tile
        return tile

    def _evict(self, keep: set) -> None:
        if self.store is None:
            return
        while len(self.tiles) > self.config.max_tiles_in_memory:
            key = next((k for k in self.tiles if k not in keep), None)
            if key is None:
                return
            self._flush_tile(self.tiles[key])
            del self.tiles[key]
            self.stats.tiles_evicted += 1

    def _flush_tile(self, tile: Tile) -> int:
        idx = np.flatnonzero(tile.dirty)
        if idx.size == 0:
            return 0
        self.store.append_cells(tile.key, idx.astype(np.uint32), tile.records(idx))
        tile.dirty[:] = False
        return idx.size

    def flush(self, sync: bool = True) -> int:
        """Hand every changed cell to the store and (`sync`) make it durable; returns cells written. Without
        `sync` the caller syncs the store itself (io/map_store.MapStore.sync), e.g. outside its own lock."""
        if self.store is None:
            return 0
        n = sum(self._flush_tile(t) for t in self.tiles.values())
        if sync:
            self.store.sync()
        return n

    # --- fusing ----------------------------------------------------------------------------------

    def add(self, points: np.ndarray, record: bool = False):
        """Fuse one pair cloud; returns the number of points accepted, and with `record` also its Contribution
        (None when nothing was fused or the cloud spans more than an int16 of cells). Optional fields `n` (points
        a point stands for) and `m2_z` (their sum of squared z deviations) fuse a Contribution's points again."""
        accepted, contrib = self._add(points, record)
        return (accepted, contrib) if record else accepted

    def _add(self, points: np.ndarray, record: bool):
        names = points.dtype.names or ()
        if not {'x', 'y', 'z'} <= set(names):
            raise DataError(f'a cloud to fuse needs x, y, z fields; got {names}')
        cfg = self.config
        x = np.asarray(points['x'], dtype=np.float64)
        y = np.asarray(points['y'], dtype=np.float64)
        z = np.asarray(points['z'], dtype=np.float64)
        rgb = np.asarray(points['rgb']) if 'rgb' in names else None
        conf = np.asarray(points['confidence']) if 'confidence' in names else None
        wt = np.asarray(points['n'], dtype=np.float64) if 'n' in names else None
        m2w = np.asarray(points['m2_z'], dtype=np.float64) if 'm2_z' in names else None
        ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
        if conf is not None and self.config.min_confidence > 0:
            ok &= conf >= self.config.min_confidence
        self.stats.clouds += 1
        self.stats.points_in += x.size
        self.stats.points_invalid += int(x.size - ok.sum())
        if not ok.all():   # field by field: indexing the structured array would copy whole records
            x, y, z = x[ok], y[ok], z[ok]
            rgb = rgb[ok] if rgb is not None else None
            conf = conf[ok] if conf is not None else None
            wt = wt[ok] if wt is not None else None
            m2w = m2w[ok] if m2w is not None else None
        if x.size == 0:
            return 0, None
        T = cfg.tile_cells
        TT = T * T
        ix = np.floor(x / cfg.cell_m).astype(np.int64)
        iy = np.floor(y / cfg.cell_m).astype(np.int64)
        ti = ix // T
        tj = iy // T
        lx, ly = ix - ti * T, iy - tj * T
        local = ly * T + lx
        ti0, tj0 = int(ti.min()), int(tj.min())
        span_i, span_j = int(ti.max()) - ti0 + 1, int(tj.max()) - tj0 + 1
        if span_i * span_j <= 64:
            tid = (tj - tj0) * span_i + (ti - ti0)
            tile_keys = [(ti0 + k % span_i, tj0 + k // span_i) for k in range(span_i * span_j)]
        else:  # stray far points: index only the tiles actually hit
            packed = (ti << 32) + (tj & 0xFFFFFFFF)
            uniq, tid = np.unique(packed, return_inverse=True)
            tile_keys = [(int(u) >> 32, _int32(int(u) & 0xFFFFFFFF)) for u in uniq]
        key = tid * TT + local
        # Compact bin numbers (occupied cells only) keep every later bincount small.
        present = np.bincount(key, minlength=len(tile_keys) * TT) > 0
        cell_of_bin = np.flatnonzero(present)
        ckey = (np.cumsum(present) - 1)[key]
        nbins = cell_of_bin.size

        # (1) Speckle inside the pair: a point far from the mean of its block of cells is dropped,
        # at two block sizes (4 and 16 cells) so small blobs of mismatches go as well as single
        # points. Two passes per size: the second takes block statistics without the first's
        # rejects, so large outliers cannot hide each other by inflating the spread. Across a
        # roof edge the spread is large and the gate lenient, so real steps survive.
        keep = np.ones(x.size, dtype=bool)
        for bs in (4, 16):
            TB = -(-T // bs)
            bkey = tid * (TB * TB) + (ly // bs) * TB + lx // bs
            nb = int(bkey.max()) + 1
            for _ in range(2):
                bc = np.bincount(bkey, keep, minlength=nb)
                bm = np.bincount(bkey, z * keep, minlength=nb) / np.maximum(bc, 1)
                bv = np.bincount(bkey, z * z * keep, minlength=nb) / np.maximum(bc, 1) - bm * bm
                bsd = np.sqrt(np.maximum(bv, 0.0))
                keep &= (np.abs(z - bm[bkey]) <= np.maximum(2.5 * bsd[bkey], cfg.min_tolerance_m)) | (bc[bkey] < 4)

        # (2) Consistency with the earlier pairs: gate each point against its fused cell.
        hit = np.flatnonzero(np.bincount(tid, minlength=len(tile_keys)))
        tiles = {int(h): self._tile(tile_keys[int(h)]) for h in hit}
        # Per-cell reference height and tolerance of the hit tiles, then one gather for all points.
        slot = np.zeros(len(tile_keys), dtype=np.int64)
        slot[hit] = np.arange(hit.size)
        z_ref = np.empty(hit.size * TT, dtype=np.float32)
        tol_ref = np.empty(hit.size * TT, dtype=np.float32)
        for k, h in enumerate(hit):
            c = tiles[int(h)].f
            n_old = c['n'].astype(np.float32)
            sigma = np.sqrt(c['m2_z'] / np.maximum(n_old - 1.0, 1.0))
            z_ref[k * TT:(k + 1) * TT] = c['z']
            tol_ref[k * TT:(k + 1) * TT] = np.where(n_old > 0, np.maximum(cfg.k_sigma * sigma, cfg.min_tolerance_m),
                                                    np.inf)
        ref = slot[tid] * TT + local
        zf, tolf = z_ref[ref], tol_ref[ref]
        consistent = np.abs(z - zf) <= tolf
        good = keep & consistent
        gated = keep & ~consistent

        # (3) Cells where this pair disagrees entirely count a rejection; when rejections outnumber
        # the pairs behind a cell, the cell is rebuilt from this pair.
        cnt_ok = np.bincount(ckey, good, minlength=nbins)
        cnt_g = np.bincount(ckey, gated, minlength=nbins)
        disputed_c = np.flatnonzero((cnt_g > 0) & (cnt_ok == 0))
        takeover = np.zeros(nbins, dtype=bool)
        if disputed_c.size:
            disputed = cell_of_bin[disputed_c]
            d_tile = disputed // TT
            for h in np.unique(d_tile):
                cells_idx = disputed[d_tile == h] - h * TT
                tile = tiles[int(h)]
                rej = tile.f['n_rejected'][cells_idx].astype(np.int64) + 1
                over = rej > tile.f['n_pairs'][cells_idx]
                tile.f['n_rejected'][cells_idx] = np.minimum(rej, 65535)
                for arr in tile.f.values():       # emptied: rebuilt below from this pair
                    arr[cells_idx[over]] = 0
                tile.dirty[cells_idx] = True
                takeover[disputed_c[d_tile == h][over]] = True
                self.stats.cells_replaced += int(over.sum())
        use = good | (gated & takeover[ckey])
        if not use.any():
            self.stats.points_rejected += len(use)
            return 0, None     # every point disagreed with what the map holds there
        if not use.all():
            x, y, z, ckey = x[use], y[use], z[use], ckey[use]
            rgb = rgb[use] if rgb is not None else None
            conf = conf[use] if conf is not None else None
            wt = wt[use] if wt is not None else None
            m2w = m2w[use] if m2w is not None else None
        w1 = np.ones(x.size) if wt is None else wt

        cnt = np.bincount(ckey, w1, minlength=nbins)
        occ_c = np.flatnonzero(cnt)
        n_p = cnt[occ_c].astype(np.float64)
        occ = cell_of_bin[occ_c]

        def mean_of(v):
            return np.bincount(ckey, w1 * v, minlength=nbins)[occ_c] / n_p

        mx, my, mz = mean_of(x), mean_of(y), mean_of(z)
        m2_p = np.maximum(np.bincount(ckey, w1 * z * z, minlength=nbins)[occ_c] - n_p * mz * mz, 0.0)
        if m2w is not None:
            m2_p = m2_p + np.bincount(ckey, m2w, minlength=nbins)[occ_c]
        if rgb is not None:
            bgra = np.ascontiguousarray(rgb, dtype='<u4').view(np.uint8).reshape(-1, 4)
            mr, mg, mb = mean_of(bgra[:, 2]), mean_of(bgra[:, 1]), mean_of(bgra[:, 0])
        else:
            mr = mg = mb = np.full(occ.size, 128.0)
        mc = mean_of(conf) if conf is not None else np.ones(occ.size)

        occ_tile = occ // TT
        occ_local = occ - occ_tile * TT
        bounds = np.flatnonzero(np.diff(occ_tile)) + 1
        starts = np.concatenate([[0], bounds]).astype(int)
        ends = np.concatenate([bounds, [occ.size]]).astype(int)
        for s, e in zip(starts, ends):
            h = int(occ_tile[s])
            ox, oy = self.tile_origin_m(tile_keys[h])
            sl = slice(s, e)
            self.changed_tiles.add(tile_keys[h])
            self._merge(tiles[h], occ_local[sl], n_p[sl], mx[sl] - ox, my[sl] - oy, mz[sl], m2_p[sl],
                        mr[sl], mg[sl], mb[sl], mc[sl])
        accepted = int(x.size)
        self.stats.points_fused += accepted
        self.stats.points_rejected += len(use) - accepted
        contrib = None
        if record:
            keys = np.asarray(tile_keys, dtype=np.int64)[occ_tile]
            ix = keys[:, 0] * T + occ_local % T
            iy = keys[:, 1] * T + occ_local // T
            contrib = self._contribution(ix, iy, n_p, mx, my, mz, m2_p, mr, mg, mb, mc)
        self._evict({tile_keys[int(h)] for h in hit})
        return accepted, contrib

    def _contribution(self, ix, iy, n_p, mx, my, mz, m2_p, mr, mg, mb, mc) -> Contribution | None:
        base = (int(ix.min()), int(iy.min()))
        if ix.max() - base[0] > 32767 or iy.max() - base[1] > 32767:
            return None
        cell = self.config.cell_m
        c = np.empty(ix.size, dtype=CONTRIB_DTYPE)
        c['di'], c['dj'] = ix - base[0], iy - base[1]
        c['n'] = np.minimum(n_p, 65535)
        c['fx'] = np.clip(np.floor((mx / cell - ix) * 256.0), 0, 255)
        c['fy'] = np.clip(np.floor((my / cell - iy) * 256.0), 0, 255)
        c['z'] = mz
        c['m2_z'] = np.minimum(m2_p, 65000.0)
        for name, v in (('r', mr), ('g', mg), ('b', mb)):
            c[name] = np.clip(np.rint(v), 0, 255)
        c['confidence'] = np.clip(np.rint(np.asarray(mc, np.float64) * 255.0), 0, 255)
        # Kept while its keyframe's pose may move (minutes): off the heap, like the tiles.
        return Contribution(base, cell, offheap.copy(c))

    def remove(self, contrib: Contribution) -> None:
        """Take a recorded contribution out of its cells: the reverse of the running-mean update (Chan's, undone);
        a cell left without points is emptied."""
        if contrib.cell_m != self.config.cell_m:
            raise DataError(f'a contribution at {contrib.cell_m} m cells cannot leave a map of {self.config.cell_m} m')
        pts = contrib.points()
        ix, iy = contrib.ij()
        T = self.config.tile_cells
        ti, tj = ix // T, iy // T
        local = (iy - tj * T) * T + (ix - ti * T)
        packed = (ti << 32) + (tj & 0xFFFFFFFF)
        for u in np.unique(packed):
            key = (int(u) >> 32, _int32(int(u) & 0xFFFFFFFF))
            sel = packed == u
            tile = self._tile(key)
            ox, oy = self.tile_origin_m(key)
            p = pts[sel]
            bgr = np.ascontiguousarray(p['rgb'], dtype='<u4').view(np.uint8).reshape(-1, 4)
            self._unmerge(tile, local[sel], p['n'].astype(np.float64), p['x'] - ox, p['y'] - oy,
                          p['z'].astype(np.float64), p['m2_z'].astype(np.float64), bgr[:, 2], bgr[:, 1], bgr[:, 0],
                          p['confidence'].astype(np.float64))
            self.changed_tiles.add(key)
            self._evict({key})

    def move(self, contrib: Contribution, map_T_map: np.ndarray) -> tuple[int, Contribution | None]:
        """Take `contrib` out and fuse it again moved by `map_T_map` (new placement x old placement^-1): a
        keyframe's cloud following its pose. Returns (points accepted, the new contribution)."""
        pts = contrib.points(map_T_map)
        self.remove(contrib)
        return self.add(pts, record=True)

    @staticmethod
    def _unmerge(tile: Tile, idx, n_p, mx, my, mz, m2_p, mr, mg, mb, mc) -> None:
        c = tile.f
        n = c['n'][idx].astype(np.float64)
        n_old = n - n_p
        gone = n_old <= 0.5
        keep = ~gone
        w = np.where(keep, n_p / np.maximum(n_old, 1.0), 0.0)   # mean_old = mean + (mean - v) n_p / n_old
        for name, v in (('x', mx), ('y', my), ('r', mr), ('g', mg), ('b', mb), ('confidence', mc)):
            cur = c[name][idx].astype(np.float64)
            c[name][idx] = cur + (cur - v) * w
        z_cur = c['z'][idx].astype(np.float64)
        z_old = z_cur + (z_cur - mz) * w
        delta = mz - z_old
        m2 = c['m2_z'][idx] - m2_p - delta * delta * np.maximum(n_old, 0.0) * n_p / np.maximum(n, 1.0)
        c['m2_z'][idx] = np.maximum(m2, 0.0)
        c['z'][idx] = z_old
        c['n'][idx] = np.maximum(np.rint(n_old), 0)
        c['n_pairs'][idx] = np.maximum(c['n_pairs'][idx].astype(np.int64) - 1, 0)
        if gone.any():
            for arr in c.values():
                arr[idx[gone]] = 0
        tile.dirty[idx] = True

    @staticmethod
    def _merge(tile: Tile, idx, n_p, mx, my, mz, m2_p, mr, mg, mb, mc) -> None:
        c = tile.f
        n_old = c['n'][idx].astype(np.float64)
        n_new = n_old + n_p
        w = n_p / n_new
        for name, v in (('x', mx), ('y', my), ('r', mr), ('g', mg), ('b', mb), ('confidence', mc)):
            old = c[name][idx]
            c[name][idx] = old + (v - old) * w
        z_old = c['z'][idx].astype(np.float64)
        delta = mz - z_old
        # Chan's parallel update; for an empty cell n_old = 0 and this reduces to the pair's own m2.
        c['m2_z'][idx] = c['m2_z'][idx] + m2_p + delta * delta * n_old * n_p / n_new
        c['z'][idx] = z_old + delta * w
        c['n'][idx] = np.minimum(n_new, 2**32 - 1)
        c['n_pairs'][idx] = np.minimum(c['n_pairs'][idx] + 1, 65535)
        tile.dirty[idx] = True

    # --- reading the map -------------------------------------------------------------------------

    def tile_points(self, key, cells: np.ndarray) -> dict:
        """Occupied cells of a tile as flat arrays in map ENU."""
        idx = np.flatnonzero(cells['n'])
        c = cells[idx]
        ox, oy = self.tile_origin_m(key)
        T = self.config.tile_cells
        return {'ix': key[0] * T + idx % T, 'iy': key[1] * T + idx // T,   # global cell indices
                'x': c['x'] + ox, 'y': c['y'] + oy, 'z': c['z'].astype(np.float64),
                'r': c['r'], 'g': c['g'], 'b': c['b'], 'confidence': c['confidence'],
                'n': c['n'], 'n_pairs': c['n_pairs'],
                'sigma_z': np.sqrt(c['m2_z'] / np.maximum(c['n'].astype(np.float32) - 1, 1))}

    def tile_records(self, key) -> np.ndarray | None:
        """CELL_DTYPE cells of one tile from memory or the store (None if never written)."""
        key = (int(key[0]), int(key[1]))
        if key in self.tiles:
            return self.tiles[key].records()
        return self.store.load_tile(key) if self.store is not None else None

    def iter_tiles(self):
        """(key, cells) for every tile, in memory or on disk, without disturbing the LRU order."""
        for key, tile in list(self.tiles.items()):
            yield key, tile.records()
        if self.store is not None:
            for key in self.store.tile_keys():
                if key not in self.tiles:
                    cells = self.store.load_tile(key)
                    if cells is not None:
                        yield key, cells

    def points(self) -> dict:
        """Every fused cell of the map as flat arrays (see tile_points)."""
        parts = [self.tile_points(k, c) for k, c in self.iter_tiles()]
        parts = [p for p in parts if p['x'].size]
        if not parts:
            return {k: np.zeros(0) for k in ('ix', 'iy', 'x', 'y', 'z', 'r', 'g', 'b', 'confidence', 'n', 'n_pairs',
                                             'sigma_z')}
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    @property
    def memory_bytes(self) -> int:
        return sum(t.nbytes for t in self.tiles.values())


def pack_rgb(r, g, b) -> np.ndarray:
    """Channels 0..255 -> uint32 0x00RRGGBB (the PointCloud2 / PCL layout)."""
    r = np.clip(np.rint(r), 0, 255).astype(np.uint32)
    g = np.clip(np.rint(g), 0, 255).astype(np.uint32)
    b = np.clip(np.rint(b), 0, 255).astype(np.uint32)
    return (r << 16) | (g << 8) | b


def downsample(pts: dict, factor: int, cell_m: float) -> dict:
    """Block means of `factor` x `factor` cells, for the ground-station stream."""
    if factor <= 1 or pts['x'].size == 0:
        return pts
    size = cell_m * factor
    ix = np.floor(pts['x'] / size).astype(np.int64)
    iy = np.floor(pts['y'] / size).astype(np.int64)
    packed = (ix << 32) + (iy & 0xFFFFFFFF)
    _, inv, cnt = np.unique(packed, return_inverse=True, return_counts=True)
    out = {}
    for k in ('x', 'y', 'z', 'r', 'g', 'b', 'confidence'):
        out[k] = np.bincount(inv, np.asarray(pts[k], np.float64)) / cnt
    out['n'] = np.bincount(inv, np.asarray(pts['n'], np.float64)).astype(np.uint32)
    return out
