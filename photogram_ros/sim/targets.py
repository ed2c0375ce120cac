"""Ground targets: ArUco markers as GCPs and check points, with surveyed coordinates.

Real GCP targets are laid on flat ground, so the DEM is levelled under each one; the target's
surveyed point is the marker centre. Markers are drawn into the texture with an exact affine map,
so their corners sit at known map coordinates to a small fraction of a texel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from photogram_ros.sim.terrain import Grid

ARUCO_DICT = cv2.aruco.DICT_4X4_50
MARKER_CELLS = 6          # 4x4 bits plus a one-cell black border
QUIET_CELLS = 1           # white margin around the marker


@dataclass
class Target:
    name: str                 # 'GCP01' or 'CHK01' (OpenDroneMap's check-point convention)
    marker_id: int
    role: str                 # 'gcp' or 'check'
    center_enu: np.ndarray    # (3,) m
    corners_enu: np.ndarray   # (4, 3) m, in ArUco's corner order (top-left, clockwise, seen north-up)
    size_m: float

    def to_dict(self) -> dict:
        return {'name': self.name, 'marker_id': self.marker_id, 'role': self.role,
                'center_enu': self.center_enu.tolist(), 'corners_enu': self.corners_enu.tolist(),
                'size_m': self.size_m}

    @classmethod
    def from_dict(cls, d: dict) -> 'Target':
        return cls(d['name'], int(d['marker_id']), d['role'], np.asarray(d['center_enu'], float),
                   np.asarray(d['corners_enu'], float), float(d['size_m']))


def layout_targets(rng: np.random.Generator, area: tuple[float, float, float, float], n_gcp: int,
                   n_check: int, margin_m: float) -> list[tuple[str, str, float, float]]:
    """GCPs at the corners and centre of the area (as surveyors place them), check points between."""
    xmin, xmax, ymin, ymax = area
    xmin, xmax, ymin, ymax = xmin + margin_m, xmax - margin_m, ymin + margin_m, ymax - margin_m
    xc, yc = (xmin + xmax) / 2, (ymin + ymax) / 2
    gcp_spots = [(xmin, ymin), (xmax, ymax), (xmin, ymax), (xmax, ymin), (xc, yc),
                 (xc, ymin), (xc, ymax), (xmin, yc), (xmax, yc)]
    chk_spots = [((xmin + xc) / 2, (ymin + yc) / 2), ((xc + xmax) / 2, (yc + ymax) / 2),
                 ((xmin + xc) / 2, (yc + ymax) / 2), ((xc + xmax) / 2, (ymin + yc) / 2),
                 (xc, (ymin + yc) / 2), (xc, (yc + ymax) / 2)]
    out = []
    jitter = lambda: rng.uniform(-2.0, 2.0)  # noqa: E731
    for k in range(n_gcp):
        x, y = gcp_spots[k % len(gcp_spots)]
        out.append((f'GCP{k + 1:02d}', 'gcp', x + jitter(), y + jitter()))
    for k in range(n_check):
        x, y = chk_spots[k % len(chk_spots)]
        out.append((f'CHK{k + 1:02d}', 'check', x + jitter(), y + jitter()))
    return out


def level_ground(dem: Grid, x_m: float, y_m: float, radius_m: float) -> float:
    """Flatten the DEM within `radius_m` of a point (blending outward); returns the level height."""
    z0 = float(dem.sample(x_m, y_m))
    h, w = dem.shape
    xs = dem.x0_m + np.arange(w) * dem.res_m
    ys = dem.y0_m + np.arange(h) * dem.res_m
    d = np.maximum(np.abs(xs[None, :] - x_m), np.abs(ys[:, None] - y_m))  # square pad
    wgt = np.clip((2.0 * radius_m - d) / radius_m, 0.0, 1.0).astype(np.float32)
    dem.data[:] = wgt * z0 + (1.0 - wgt) * dem.data
    return z0


def draw_marker(texture: Grid, marker_id: int, x_m: float, y_m: float, size_m: float) -> None:
    """Draw an ArUco marker (black border side `size_m`) centred at (x, y), top edge to the north."""
    dictionary = cv2.aruco.getPredefinedDictionary(ARUCO_DICT)
    px_per_cell = 40
    marker = cv2.aruco.generateImageMarker(dictionary, marker_id, MARKER_CELLS * px_per_cell)
    pad = QUIET_CELLS * px_per_cell
    marker = cv2.copyMakeBorder(marker, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    m = marker.shape[0]
    total_m = size_m * (MARKER_CELLS + 2 * QUIET_CELLS) / MARKER_CELLS
    # Marker image pixel (a, b), edges at -0.5 and m-0.5 -> texture coordinates; b grows southward.
    scale = total_m / (m * texture.res_m)
    u_w = (x_m - total_m / 2 - texture.x0_m) / texture.res_m
    v_n = (y_m + total_m / 2 - texture.y0_m) / texture.res_m
    A = np.array([[scale, 0.0, u_w + 0.5 * scale], [0.0, -scale, v_n - 0.5 * scale]])
    h, w = texture.shape
    # Work on a small region only: warping the whole texture would be slow.
    r = int(np.ceil(total_m / texture.res_m)) + 4
    uc, vc = int((x_m - texture.x0_m) / texture.res_m), int((y_m - texture.y0_m) / texture.res_m)
    u0, v0 = max(uc - r, 0), max(vc - r, 0)
    u1, v1 = min(uc + r, w), min(vc + r, h)
    A_roi = A.copy()
    A_roi[0, 2] -= u0
    A_roi[1, 2] -= v0
    roi = texture.data[v0:v1, u0:u1]
    warped = cv2.warpAffine(marker, A_roi, (u1 - u0, v1 - v0), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    mask = cv2.warpAffine(np.full_like(marker, 255), A_roi, (u1 - u0, v1 - v0), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(np.float32) / 255.0
    # Targets are painted boards: slightly off-white and off-black, not pure 0/255.
    paint = 25.0 + warped.astype(np.float32) * (205.0 / 255.0)
    blended = roi.astype(np.float32) * (1 - mask[..., None]) + paint[..., None] * mask[..., None]
    texture.data[v0:v1, u0:u1] = np.clip(blended, 0, 255).astype(np.uint8)


def marker_corners_enu(x_m: float, y_m: float, z_m: float, size_m: float) -> np.ndarray:
    """ArUco corner order (top-left, top-right, bottom-right, bottom-left) with top = north."""
    s = size_m / 2
    return np.array([[x_m - s, y_m + s, z_m], [x_m + s, y_m + s, z_m],
                     [x_m + s, y_m - s, z_m], [x_m - s, y_m - s, z_m]])
