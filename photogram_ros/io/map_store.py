"""Crash-safe, append-only storage of the fused map and of the keyframes the orthomosaic needs.

Layout of a map directory:
    map.json                      grid geometry and the geodetic origin (written atomically)
    tiles/<ti>_<tj>.pgt           one append-only file per tile
    keyframes/<stamp_ns>.jpg      keyframe image
    keyframes/<stamp_ns>.json     its latest map_T_cam (rewritten atomically when the pose improves)
    camera.json                   the keyframes' camera calibration: once the bundle adjuster has sent it, the
                                  camera the final poses were adjusted with (camera_name final_adjustment)
    control_points.json           the bundle adjuster's latest check points and GCPs with their detections
    flight_end.json               how the flight ended: was the final adjustment made (written last)

    tiles/index.json              each tile's size at its last sync (written after the tiles' fsync)

A tile file is a 32-byte header followed by blocks. A block is a 16-byte header (magic, record
count, CRC-32 of the payload) and fixed-size records (cell index + the cell's full state). A flush
appends the cells that changed since the last flush; reading replays the blocks and the last record
of a cell wins. A block cut short or garbled by a crash fails its length or CRC check: reading
stops there and the next append truncates the torn tail first, so a kill -9 loses only what was
not yet flushed. Files that have grown much larger than their content are rewritten compactly
(temporary file, fsync, rename).

`check_tiles` compares the tiles with the index: a tile deleted, cut short, or whose blocks before its
synced size fail their check (overwritten), or whose header is not a tile's, is a `TileDamage` naming
the file and what was lost; a header that is not a tile's leaves the tile out of `tile_keys` so the
rest of the map still reads. A map without an index (written before it existed) can only tell the
blocks that fail their check.
"""

from __future__ import annotations

import errno
import json
import os
import struct
import threading
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from photogram_ros.core.fusion import CELL_DTYPE
from photogram_ros.errors import DataError, StorageError

FORMAT = 'photogram_ros.map'
# camera.json's camera_name: the calibration the flight started with, or the one of the final adjustment's poses.
CAMERA_INPUT = 'camera'
CAMERA_FINAL = 'final_adjustment'
CONTROL_POINTS_FILE = 'control_points.json'
VERSION = 1
RECORD_DTYPE = np.dtype([('cell', '<u4')] + [(n, CELL_DTYPE.fields[n][0]) for n in CELL_DTYPE.names])
_FILE_HEADER = struct.Struct('<8sIiiIdI')          # magic, version, ti, tj, tile_cells, cell_m, record size
_FILE_MAGIC = b'PGRTILE1'
_BLOCK_HEADER = struct.Struct('<IIII')             # magic, n records, crc32, reserved
_BLOCK_MAGIC = 0x4B4C4250                          # 'PBLK'
_FILE_HEADER_SIZE = 40


TILE_INDEX = 'index.json'   # in tiles/


@dataclass(frozen=True)
class TileDamage:
    """A map tile that lost cells: `what` says how (missing, cut short, overwritten, not a tile)."""

    key: tuple
    path: Path
    what: str

    def __str__(self) -> str:
        return f'{self.path.name}: {self.what}'


def _atomic_write(path: Path, data: bytes) -> None:
    """Write `path` whole or not at all; a failure (a full disk) leaves no temporary file behind and
    raises a StorageError (an OSError too) naming the folder."""
    tmp = path.with_name(path.name + '.tmp')
    try:
        with open(tmp, 'wb') as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise StorageError(f'cannot write {path.name} in {path.parent} ({exc.strerror or exc}): '
                           f'{"the disk is full: free space" if exc.errno == errno.ENOSPC else "check the folder"} '
                           'and run again', exc.errno) from exc


class MapStore:
    """The map directory. Implements the store protocol that core.fusion.Fusion uses."""

    def __init__(self, root: str | Path, cell_m: float | None = None, tile_cells: int | None = None,
                 compact_factor: float = 4.0):
        self.root = Path(root)
        self.tiles_dir = self.root / 'tiles'
        self.keyframes_dir = self.root / 'keyframes'
        self.compact_factor = compact_factor
        meta_path = self.root / 'map.json'
        if meta_path.exists():
            try:
                self.meta = json.loads(meta_path.read_text())
            except (OSError, ValueError) as exc:
                raise DataError(f'{meta_path} is unreadable ({exc}): is this a photogram_ros map folder?') from exc
            if self.meta.get('format') != FORMAT:
                raise DataError(f'{meta_path} is not a photogram_ros map (format {self.meta.get("format")!r})')
            for name, want in (('cell_m', cell_m), ('tile_cells', tile_cells)):
                if want is not None and abs(float(self.meta[name]) - float(want)) > 1e-12:
                    raise DataError(f'the map in {self.root} has {name} = {self.meta[name]}, not {want}: '
                                    'use the same value or a new map_dir')
        else:
            if cell_m is None or tile_cells is None:
                raise DataError(f'{self.root} holds no map (no map.json)')
            self.root.mkdir(parents=True, exist_ok=True)
            self.meta = {'format': FORMAT, 'version': VERSION, 'cell_m': float(cell_m),
                         'tile_cells': int(tile_cells), 'origin': None}
            _atomic_write(meta_path, json.dumps(self.meta, indent=1).encode())
        self.tiles_dir.mkdir(parents=True, exist_ok=True)
        self.keyframes_dir.mkdir(parents=True, exist_ok=True)
        self.cell_m = float(self.meta['cell_m'])
        self.tile_cells = int(self.meta['tile_cells'])
        self._good_size: dict[tuple[int, int], int] = {}
        self._unsynced: set[Path] = set()
        # One sync at a time, and the index written under it: the map stage syncs outside its own lock while
        # its fusion appends (stages/map.py flush).
        self._sync_lock = threading.Lock()
        self._index = self._read_index()   # (ti, tj) -> the tile's size at its last sync; None: no index
        self._unreadable: set[tuple[int, int]] = set()   # tiles check_tiles found are not tiles of this map
        self.bytes_written = 0
        self.write_failures = 0          # writes that failed (a full disk, a folder gone): map_node's diagnostics
        self.last_write_error: StorageError | None = None

    def _write(self, path: Path, data: bytes) -> None:
        """_atomic_write, counting a failure in write_failures."""
        try:
            _atomic_write(path, data)
        except StorageError as exc:
            self.write_failures += 1
            self.last_write_error = exc
            raise

    def set_cell_m(self, cell_m: float) -> None:
        """Change the cell size of a map that holds no tiles yet (a cell derived from the GSD once the
        first pair cloud tells the flying height); a map with tiles keeps its cell."""
        if self.tile_keys():
            raise DataError(f'the map in {self.root} holds tiles of {self.cell_m} m cells: its cell size cannot '
                            'change; use a new map_dir')
        if not cell_m > 0:
            raise DataError(f'cell size {cell_m} m must be positive')
        self.meta['cell_m'] = float(cell_m)
        self.cell_m = float(cell_m)
        self._write(self.root / 'map.json', json.dumps(self.meta, indent=1).encode())

    # --- metadata --------------------------------------------------------------------------------

    @property
    def origin(self):
        from photogram_ros.core.geodesy import LocalFrame
        o = self.meta.get('origin')
        return LocalFrame.from_dict(o) if o else None

    def set_origin(self, frame) -> None:
        self.meta['origin'] = frame.to_dict()
        self._write(self.root / 'map.json', json.dumps(self.meta, indent=1).encode())

    def save_flight_end(self, end: dict) -> None:
        """How the flight ended ({'final_adjustment': 'done' | 'failed' | 'none', 'reason', ...}): the
        products then say whether their poses are the final adjustment's."""
        self._write(self.root / 'flight_end.json', json.dumps(end, indent=1).encode())

    def flight_end(self) -> dict | None:
        """What save_flight_end wrote, or None (a map from before it existed, or a flight cut short)."""
        p = self.root / 'flight_end.json'
        try:
            return json.loads(p.read_text()) if p.exists() else None
        except (OSError, ValueError):
            return None

    # --- tiles -----------------------------------------------------------------------------------

    def tile_path(self, key) -> Path:
        """The file of tile `key` (i, j), whether or not it exists."""
        return self.tiles_dir / f'{int(key[0])}_{int(key[1])}.pgt'

    def tile_keys(self) -> list[tuple[int, int]]:
        """The tiles on disk (but those check_tiles found unreadable)."""
        keys = []
        for p in self.tiles_dir.glob('*.pgt'):
            try:
                a, b = p.stem.split('_')
                keys.append((int(a), int(b)))
            except ValueError:
                continue
        return sorted(k for k in keys if k not in self._unreadable)

    def _read_index(self) -> dict | None:
        p = self.tiles_dir / TILE_INDEX
        try:
            body = json.loads(p.read_text())
            return {tuple(int(v) for v in k.split('_')): int(n) for k, n in body['sizes'].items()}
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            return {}   # a damaged index: tiles are still checked block by block

    def _write_index(self) -> None:
        body = {'sizes': {f'{k[0]}_{k[1]}': n for k, n in sorted(self._index.items())}}
        self._write(self.tiles_dir / TILE_INDEX, json.dumps(body).encode())

    def check_tiles(self) -> list[TileDamage]:
        """Every tile that lost cells, named with how: missing (in the index, not on disk), cut short or
        overwritten (its whole blocks end before its size at the last sync), not a tile of this map (its
        header). Without an index, a tile whose blocks fail their check after some byte (a crash's torn
        tail, or damage) is named too. Unreadable tiles are left out of tile_keys from here on."""
        out = []
        index = self._index or {}
        on_disk = {}
        for p in self.tiles_dir.glob('*.pgt'):
            try:
                a, b = p.stem.split('_')
                on_disk[(int(a), int(b))] = p
            except ValueError:
                continue
        for key in sorted(set(index) - set(on_disk)):
            out.append(TileDamage(key, self.tile_path(key), f'missing (deleted?): it held {index[key]} bytes of '
                                                             'cells at the last sync'))
        for key, path in sorted(on_disk.items()):
            try:
                size = path.stat().st_size
                _, good = self._read_records(path, key)
            except (OSError, DataError) as exc:
                self._unreadable.add(key)
                out.append(TileDamage(key, path, f'unreadable, left out: {exc}'))
                continue
            known = index.get(key)
            if known is not None and good < known:
                what = (f'cut short: {size} bytes of the {known} it held' if size < known else
                        f'damaged (overwritten?): its blocks fail their check from byte {good} of {known}')
                out.append(TileDamage(key, path, what + f': the cells of {known - good} bytes lost'))
            elif self._index is None and good < size:
                out.append(TileDamage(key, path, f'its blocks fail their check from byte {good} of {size} (a crash '
                                                 'cut its last write, or the file was damaged)'))
        return out

    def _read_records(self, path: Path, key) -> tuple[np.ndarray, int]:
        data = path.read_bytes()
        if len(data) < _FILE_HEADER_SIZE:
            return np.zeros(0, RECORD_DTYPE), 0
        magic, version, ti, tj, tcells, cell_m, rsize = _FILE_HEADER.unpack_from(data, 0)
        if magic != _FILE_MAGIC or rsize != RECORD_DTYPE.itemsize or tcells != self.tile_cells:
            raise DataError(f'{path} is not a tile of this map (magic {magic!r}, record size {rsize}, '
                            f'tile_cells {tcells})')
        pos, parts = _FILE_HEADER_SIZE, []
        while pos + _BLOCK_HEADER.size <= len(data):
            bmagic, n, crc, _ = _BLOCK_HEADER.unpack_from(data, pos)
            end = pos + _BLOCK_HEADER.size + n * rsize
            if bmagic != _BLOCK_MAGIC or end > len(data):
                break
            payload = data[pos + _BLOCK_HEADER.size:end]
            if zlib.crc32(payload) != crc:
                break
            parts.append(np.frombuffer(payload, dtype=RECORD_DTYPE))
            pos = end
        recs = np.concatenate(parts) if parts else np.zeros(0, RECORD_DTYPE)
        return recs, pos

    def load_tile(self, key) -> np.ndarray | None:
        """The tile's cells (dense, CELL_DTYPE) or None if the tile was never written."""
        key = (int(key[0]), int(key[1]))
        path = self.tile_path(key)
        if not path.exists():
            return None
        recs, good = self._read_records(path, key)
        self._good_size[key] = good
        cells = np.zeros(self.tile_cells * self.tile_cells, dtype=CELL_DTYPE)
        if recs.size:
            # Last record of each cell wins: unique over the reversed order keeps the newest.
            rev = recs[::-1]
            _, first = np.unique(rev['cell'], return_index=True)
            last = rev[first]
            if int(last['cell'].max()) >= cells.size:
                raise DataError(f'{path} holds a cell index beyond its tile: the file is corrupt')
            for name in CELL_DTYPE.names:
                cells[name][last['cell']] = last[name]
        return cells

    def append_cells(self, key, cell_idx: np.ndarray, cells: np.ndarray) -> None:
        key = (int(key[0]), int(key[1]))
        path = self.tile_path(key)
        recs = np.empty(cell_idx.size, dtype=RECORD_DTYPE)
        recs['cell'] = cell_idx
        for name in CELL_DTYPE.names:
            recs[name] = cells[name]
        payload = recs.tobytes()
        block = _BLOCK_HEADER.pack(_BLOCK_MAGIC, recs.size, zlib.crc32(payload), 0) + payload
        new = not path.exists()
        try:
            if not new:
                good = self._good_size.get(key)
                if good is None:
                    _, good = self._read_records(path, key)
                if os.path.getsize(path) != good:   # torn tail of an earlier crash: cut it off
                    os.truncate(path, good)
            with open(path, 'ab') as f:
                if new:
                    f.write(_FILE_HEADER.pack(_FILE_MAGIC, VERSION, key[0], key[1], self.tile_cells, self.cell_m,
                                              RECORD_DTYPE.itemsize).ljust(_FILE_HEADER_SIZE, b'\0'))
                f.write(block)
                size = f.tell()
        except OSError as exc:
            # The block that did not fit is a torn tail: the next append (or read) cuts it off.
            self._good_size.pop(key, None)
            self.write_failures += 1
            self.last_write_error = StorageError(
                f'cannot append to {path.name} in {path.parent} ({exc.strerror or exc}): '
                f'{"the disk is full: free space" if exc.errno == errno.ENOSPC else "check the folder"}', exc.errno)
            raise self.last_write_error from exc
        self._good_size[key] = size
        self._unsynced.add(path)
        self.bytes_written += len(block)
        # Amortised: a file is rewritten only after it has grown by several full tiles of records.
        if size > self.compact_factor * self.tile_cells * self.tile_cells * RECORD_DTYPE.itemsize:
            self.compact(key)

    def compact(self, key) -> None:
        """Rewrite a tile file with one block of its current cells (atomic)."""
        key = (int(key[0]), int(key[1]))
        cells = self.load_tile(key)
        idx = np.flatnonzero(cells['n']).astype(np.uint32)
        recs = np.empty(idx.size, dtype=RECORD_DTYPE)
        recs['cell'] = idx
        for name in CELL_DTYPE.names:
            recs[name] = cells[name][idx]
        payload = recs.tobytes()
        data = (_FILE_HEADER.pack(_FILE_MAGIC, VERSION, key[0], key[1], self.tile_cells, self.cell_m,
                                  RECORD_DTYPE.itemsize).ljust(_FILE_HEADER_SIZE, b'\0')
                + _BLOCK_HEADER.pack(_BLOCK_MAGIC, recs.size, zlib.crc32(payload), 0) + payload)
        path = self.tile_path(key)
        self._write(path, data)
        self._good_size[key] = len(data)
        self._unsynced.discard(path)
        with self._sync_lock:
            if self._index is not None and key in self._index:   # smaller now: the index must not claim more
                self._index[key] = len(data)
                self._write_index()

    def sync(self) -> None:
        """fsync every tile file appended since the last sync (and the folder, for new files), and record their
        sizes in the index. Appends may go on in another thread meanwhile: a tile appended after the snapshot
        below is left to the next sync, and the index never claims more than was synced."""
        with self._sync_lock:
            paths = list(self._unsynced)
            self._unsynced.difference_update(paths)   # appended again from here on: in the next sync
            sizes = {}
            for path in paths:
                try:
                    key = tuple(int(v) for v in path.stem.split('_'))
                except ValueError:
                    key = None
                if key in self._good_size:
                    sizes[key] = self._good_size[key]   # taken before the fsync: at most what it makes durable
            try:
                for path in paths:
                    try:
                        fd = os.open(path, os.O_RDONLY)
                        try:
                            os.fsync(fd)
                        finally:
                            os.close(fd)
                    except FileNotFoundError:
                        pass
                if paths:
                    fd = os.open(self.tiles_dir, os.O_RDONLY)
                    try:
                        os.fsync(fd)
                    finally:
                        os.close(fd)
            except OSError:
                self._unsynced.update(paths)   # not durable: the next sync tries them again
                raise
            if paths:
                # The sizes synced: what check_tiles expects at least (a map from before the index gets one now).
                self._index = {**(self._index or {}), **sizes}
                self._write_index()

    def disk_bytes(self) -> int:
        return sum(p.stat().st_size for p in self.tiles_dir.glob('*.pgt'))

    # --- keyframes -------------------------------------------------------------------------------

    def save_camera(self, camera, name: str = 'camera') -> None:
        """The keyframes' camera (ROS calibration YAML layout as JSON); `name` (its camera_name) says which:
        CAMERA_INPUT, the calibration the flight started with, or CAMERA_FINAL, the one the final
        adjustment's poses were adjusted with (its self-calibration)."""
        self._write(self.root / 'camera.json', json.dumps(camera.to_ros_yaml_dict(name)).encode())

    def load_camera(self):
        from photogram_ros.core.camera import PinholeCamera
        p = self.root / 'camera.json'
        return PinholeCamera.from_ros_yaml_dict(json.loads(p.read_text())) if p.exists() else None

    def camera_name(self) -> str | None:
        """camera.json's camera_name (CAMERA_INPUT, CAMERA_FINAL or a calibration's own), None without one."""
        p = self.root / 'camera.json'
        return json.loads(p.read_text()).get('camera_name') if p.exists() else None

    def save_control_points(self, doc: dict) -> None:
        """The bundle adjuster's latest live accuracy document (map/control_points): the check points and GCPs
        with the detections each was intersected from, which the flight report intersects again."""
        self._write(self.root / CONTROL_POINTS_FILE, json.dumps(doc).encode())

    def control_points(self) -> dict | None:
        """What save_control_points wrote, or None (no control file in flight, or unreadable)."""
        p = self.root / CONTROL_POINTS_FILE
        try:
            return json.loads(p.read_text()) if p.exists() else None
        except (OSError, ValueError):
            return None

    def keyframe_image_path(self, stamp_ns: int) -> Path:
        """Where the image of the keyframe stamped `stamp_ns` is saved."""
        return self.keyframes_dir / f'{int(stamp_ns)}.jpg'

    def save_keyframe_image(self, stamp_ns: int, jpeg: bytes) -> None:
        self._write(self.keyframe_image_path(stamp_ns), jpeg)

    def save_keyframe_pose(self, stamp_ns: int, map_T_cam: np.ndarray) -> None:
        body = {'stamp_ns': int(stamp_ns), 'map_T_cam': np.asarray(map_T_cam, float).tolist()}
        self._write(self.keyframes_dir / f'{int(stamp_ns)}.json', json.dumps(body).encode())

    def unposed_keyframe_images(self) -> list[Path]:
        """Keyframe images saved without a pose: taken before the flight was cut short (a crash) and never
        oriented by the bundle adjuster; keyframes() leaves them out."""
        return [p for p in sorted(self.keyframes_dir.glob('*.jpg')) if not p.with_suffix('.json').exists()]

    def keyframes(self) -> list[dict]:
        """[{'stamp_ns', 'image_path', 'map_T_cam'}] for keyframes that have both image and pose."""
        out = []
        for p in sorted(self.keyframes_dir.glob('*.json')):
            img = p.with_suffix('.jpg')
            if not img.exists():
                continue
            try:
                body = json.loads(p.read_text())
                T = np.asarray(body['map_T_cam'], float).reshape(4, 4)
            except (OSError, ValueError, KeyError):
                continue
            out.append({'stamp_ns': int(body['stamp_ns']), 'image_path': img, 'map_T_cam': T})
        return out


def as_map_store(map_dir: str | Path | MapStore) -> MapStore:
    """An open MapStore as it is, a folder opened as one: for functions that take either."""
    return map_dir if isinstance(map_dir, MapStore) else MapStore(map_dir)
