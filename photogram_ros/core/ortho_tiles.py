"""Live orthomosaic tiles: the fused map's cell colours as XYZ / Web Mercator tiles at a reduced GSD.

The fused map (core/fusion.py) keeps, per cell, the mean colour of the stereo points that fell in it:
seen from above, that is a true orthophoto of what stereo measured (no relief displacement; holes
where stereo found nothing). `OrthoTiler` renders it into the standard XYZ tile scheme (Web Mercator,
EPSG:3857, 256-pixel tiles, tile x from the west and y from the north; the grid comes from
morecantile's WebMercatorQuad) at the zoom level whose ground pixel is the finest not finer than
`gsd_m`, so a map viewer can draw it over any other map:
- `tiles_of_map_tile(key)`: the XYZ tiles a changed fusion tile touches;
- `render(tile, records_of)`: a (256, 256, 4) BGRA image of one XYZ tile, each pixel the mean colour
  of the fused cells in the block of cells under it (alpha 0 where the map has none), from the fusion
  tiles `records_of(key)` returns (CELL_DTYPE arrays, or None).
Pixel positions go from Web Mercator to map ENU through the geodetic coordinates of each tile's
corners (an affine map over the tile: its error is far below a millimetre over a few hundred metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import morecantile
import numpy as np

from photogram_ros.core.geodesy import LocalFrame

TILE_PX = 256


@dataclass(frozen=True)
class XYZ:
    z: int
    x: int
    y: int

    def path(self) -> str:
        return f'{self.z}/{self.x}/{self.y}'


class OrthoTiler:
    def __init__(self, origin: LocalFrame, cell_m: float, tile_cells: int, gsd_m: float):
        self.tms = morecantile.tms.get('WebMercatorQuad')
        self.origin = origin
        self.cell_m = float(cell_m)
        self.tile_cells = int(tile_cells)
        # Web Mercator pixels are 1 / cos(lat) times larger than the ground they show.
        scale = 1.0 / np.cos(np.radians(origin.lat_deg))
        self.zoom = int(self.tms.zoom_for_res(gsd_m * scale, zoom_level_strategy='lower'))
        self.pixel_m = self.tms.matrix(self.zoom).cellSize / scale   # ground size of one pixel
        self.block = max(1, int(2 ** np.floor(np.log2(max(self.pixel_m / self.cell_m, 1.0)))))

    # --- geometry --------------------------------------------------------------------------------

    def _enu_of_lnglat(self, lng, lat) -> np.ndarray:
        return np.atleast_2d(self.origin.geodetic_to_enu(np.asarray(lat, float), np.asarray(lng, float),
                                                         np.full(np.shape(lat), self.origin.h_m)))[:, :2]

    def tile_corners_enu(self, t: XYZ) -> np.ndarray:
        """Map ENU (x, y) of the tile's north-west, north-east and south-west corners: (3, 2)."""
        b = self.tms.bounds(morecantile.Tile(t.x, t.y, t.z))
        return self._enu_of_lnglat([b.left, b.right, b.left], [b.top, b.top, b.bottom])

    def tiles_of_map_tile(self, key) -> list[XYZ]:
        T = self.cell_m * self.tile_cells
        x0, y0 = key[0] * T, key[1] * T
        corners = np.array([[x0, y0], [x0 + T, y0], [x0, y0 + T], [x0 + T, y0 + T]])
        lat, lon, _ = self.origin.enu_to_geodetic(np.column_stack([corners, np.zeros(4)]))
        tiles = self.tms.tiles(float(np.min(lon)), float(np.min(lat)), float(np.max(lon)), float(np.max(lat)),
                               [self.zoom])
        return [XYZ(t.z, t.x, t.y) for t in tiles]

    def tile_of_enu(self, x_m: float, y_m: float) -> XYZ:
        lat, lon, _ = self.origin.enu_to_geodetic(np.array([x_m, y_m, 0.0]))
        t = self.tms.tile(float(lon), float(lat), self.zoom)
        return XYZ(t.z, t.x, t.y)

    def lnglat_bounds(self, t: XYZ) -> tuple[float, float, float, float]:
        b = self.tms.bounds(morecantile.Tile(t.x, t.y, t.z))
        return b.left, b.bottom, b.right, b.top

    # --- rendering -------------------------------------------------------------------------------

    def _block_colours(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean colour (rows, cols, 3) of each block x block group of cells of one fusion tile, and its
        count of occupied cells; rows and columns follow the cell index (y then x)."""
        T, f = self.tile_cells, self.block
        occ = (cells['n'] > 0).reshape(T, T).astype(np.float32)
        nb = -(-T // f)
        pad = nb * f - T
        def blocks(a):
            a = np.pad(a, ((0, pad), (0, pad)))
            return a.reshape(nb, f, nb, f).sum(axis=(1, 3))
        cnt = blocks(occ)
        rgb = np.stack([blocks(cells[ch].reshape(T, T).astype(np.float32) * occ) for ch in ('r', 'g', 'b')], -1)
        return rgb / np.maximum(cnt, 1)[..., None], cnt

    def render(self, t: XYZ, records_of, colours: dict | None = None) -> np.ndarray:
        """BGRA uint8 (256, 256, 4) of tile t from the fusion tiles records_of(key) returns. `colours`: a dict kept
        over the tiles of one batch, holding each fusion tile's block colours once (XYZ tiles share them)."""
        nw, ne, sw = self.tile_corners_enu(t)
        f = (np.arange(TILE_PX) + 0.5) / TILE_PX
        P = nw + f[None, :, None] * (ne - nw) + f[:, None, None] * (sw - nw)   # (row, col, 2)
        gx = np.floor(P[..., 0] / self.cell_m).astype(np.int64)
        gy = np.floor(P[..., 1] / self.cell_m).astype(np.int64)
        T = self.tile_cells
        kx, ky = gx // T, gy // T
        out = np.zeros((TILE_PX, TILE_PX, 4), np.uint8)
        # The fusion tiles under the tile's pixels (a few of 65536 pixels' keys: packed, then unique).
        x0, y0 = int(kx.min()), int(ky.min())
        span = int(ky.max()) - y0 + 1
        packed = np.unique((kx - x0) * span + (ky - y0))
        colours = {} if colours is None else colours
        for key in [(x0 + int(k) // span, y0 + int(k) % span) for k in packed]:
            if key not in colours:
                cells = records_of(key)
                colours[key] = None if cells is None else self._block_colours(cells)
            if colours[key] is None:
                continue
            rgb, cnt = colours[key]
            sel = (kx == key[0]) & (ky == key[1])
            bi = (gy[sel] - key[1] * T) // self.block
            bj = (gx[sel] - key[0] * T) // self.block
            have = cnt[bi, bj] > 0
            px = np.clip(np.rint(rgb[bi, bj]), 0, 255).astype(np.uint8)
            vals = np.zeros((int(sel.sum()), 4), np.uint8)
            vals[:, 0], vals[:, 1], vals[:, 2] = px[:, 2], px[:, 1], px[:, 0]   # BGR
            vals[:, 3] = np.where(have, 255, 0)
            out[sel] = vals
        return out
