"""An offline base map for the ground station's page: an XYZ tile folder or an MBTiles file.

- folder: `DIR/Z/X/Y.png` (or .jpg / .jpeg / .webp), the XYZ / Web Mercator scheme (y down from the north),
  as tile downloaders and `gdal2tiles.py --xyz` write them;
- MBTiles (https://github.com/mapbox/mbtiles-spec 1.3): an SQLite file with `tiles(zoom_level,
  tile_column, tile_row, tile_data)` in the TMS scheme (row up from the south: row = 2^z - 1 - y) and a
  `metadata(name, value)` table (format, minzoom, maxzoom, bounds, attribution).
`open_basemap(path)` -> BaseMap: `.tile(z, x, y)` -> (bytes, content type) or None, `.info()` -> what
the page needs (zoom range, bounds, attribution). Opened read-only; a missing or unreadable file raises
ConfigError at the start, not when the first tile is asked for.
"""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path

from photogram_ros.errors import ConfigError

CTYPES = {'png': 'image/png', 'jpg': 'image/jpeg', 'jpeg': 'image/jpeg', 'webp': 'image/webp'}
MAX_ZOOM = 24


def _ctype_of(data: bytes, default: str) -> str:
    if data[:8] == b'\x89PNG\r\n\x1a\n':
        return 'image/png'
    if data[:3] == b'\xff\xd8\xff':
        return 'image/jpeg'
    if data[:4] == b'RIFF' and data[8:12] == b'WEBP':
        return 'image/webp'
    return default


class BaseMap:
    kind = ''

    def __init__(self, path: Path):
        self.path = path
        self.minzoom, self.maxzoom = 0, MAX_ZOOM
        self.bounds = None            # [west, south, east, north], degrees
        self.attribution = ''

    def tile(self, z: int, x: int, y: int):
        raise NotImplementedError

    def info(self) -> dict:
        return {'kind': self.kind, 'name': self.path.name, 'minzoom': self.minzoom, 'maxzoom': self.maxzoom,
                'bounds': self.bounds, 'attribution': self.attribution}

    @staticmethod
    def _valid(z: int, x: int, y: int) -> bool:
        return 0 <= z <= MAX_ZOOM and 0 <= x < 2 ** z and 0 <= y < 2 ** z


class FolderBaseMap(BaseMap):
    kind = 'xyz'

    def __init__(self, path: Path):
        super().__init__(path)
        zooms = sorted(int(p.name) for p in path.iterdir() if p.is_dir() and p.name.isdigit())
        if not zooms:
            raise ConfigError(f'base map {path}: no zoom folders (an XYZ tile folder holds Z/X/Y.png)')
        self.minzoom, self.maxzoom = zooms[0], zooms[-1]

    def tile(self, z: int, x: int, y: int):
        if not self._valid(z, x, y):
            return None
        for ext, ctype in CTYPES.items():
            p = self.path / str(z) / str(x) / f'{y}.{ext}'
            if p.is_file():
                data = p.read_bytes()
                return data, _ctype_of(data, ctype)
        return None


class MBTilesBaseMap(BaseMap):
    kind = 'mbtiles'

    def __init__(self, path: Path):
        super().__init__(path)
        try:
            self.db = sqlite3.connect(f'file:{path}?mode=ro', uri=True, check_same_thread=False)
            meta = dict(self.db.execute('SELECT name, value FROM metadata').fetchall())
            zr = self.db.execute('SELECT MIN(zoom_level), MAX(zoom_level) FROM tiles').fetchone()
        except sqlite3.Error as exc:
            raise ConfigError(f'base map {path}: not a readable MBTiles file ({exc})') from exc
        if zr[0] is None:
            raise ConfigError(f'base map {path}: its tiles table is empty')
        self._lock = threading.Lock()
        self.format = CTYPES.get(str(meta.get('format', 'png')).lower(), 'image/png')
        self.minzoom = _int(meta.get('minzoom'), zr[0])
        self.maxzoom = _int(meta.get('maxzoom'), zr[1])
        try:
            b = [float(v) for v in str(meta.get('bounds', '')).split(',')]
            self.bounds = b if len(b) == 4 else None
        except ValueError:
            self.bounds = None
        self.attribution = str(meta.get('attribution', ''))

    def tile(self, z: int, x: int, y: int):
        if not self._valid(z, x, y):
            return None
        with self._lock:
            row = self.db.execute('SELECT tile_data FROM tiles WHERE zoom_level=? AND tile_column=? AND tile_row=?',
                                  (z, x, 2 ** z - 1 - y)).fetchone()
        if row is None or row[0] is None:
            return None
        data = bytes(row[0])
        return data, _ctype_of(data, self.format)


def _int(v, default: int) -> int:
    try:
        return int(v)
    except (TypeError, ValueError):
        return int(default)


def open_basemap(path: str | Path) -> BaseMap:
    """An XYZ folder or an .mbtiles file -> BaseMap; ConfigError when it cannot serve tiles."""
    p = Path(path).expanduser()
    if p.is_dir():
        return FolderBaseMap(p)
    if p.is_file():
        return MBTilesBaseMap(p)
    raise ConfigError(f'base map {p}: no such file or folder (give an XYZ tile folder Z/X/Y.png or an .mbtiles file)')
