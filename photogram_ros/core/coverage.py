"""Survey coverage in flight: how often each ground cell was seen, whether stereo covers it, and the gaps.

From the keyframe poses as they come (map ENU, optical cameras) and the ground height under each,
`Coverage.update()` produces a `CoverageReport`:
- per cell of `coverage_cell_m`: `views`, the number of keyframes whose footprint (the image border
  cast on the horizontal plane at the keyframe's ground height) holds the cell, and `stereo`, whether
  the cell lies in both footprints of two consecutive keyframes overlapping by at least
  `min_pair_overlap` (the along-line pairs the stereo node matches);
- the survey area: the mission polygon when one is given, else the swaths of the flight lines (the
  band each line's camera centres sweep from its first to its last keyframe, as wide as its
  footprints across the line, less `swath_margin_m`): the flown track's footprint, without the turns
  and the half footprints beyond the lines' ends that only one keyframe sees;
- forward overlap of consecutive keyframes within a flight line (runs of keyframes flying one
  heading) and side overlap between neighbouring lines (median over the keyframes of a line of the
  share of each footprint that the nearest parallel line also sees);
- gaps, as polygons in map ENU with their area (at least `min_gap_area_m2`): 'coverage' gaps are
  connected cells of the survey area, already passed by the drone (behind the newest footprint and
  within reach of the track, or everything after `finish()`), seen fewer than `min_views` times or by
  no stereo pair; 'not_oriented' gaps are such cells that the camera saw well enough but only through
  keyframes the adjustment has not oriented (stand-in poses from their GNSS fixes) although it oriented
  a later one: seen, not mapped;
  'forward_overlap' gaps are the ground between two consecutive keyframes of a line
  (inside the hull of their footprints) that neither of them sees;
- `coverage_share`: the passed survey cells seen `min_views` times and by a stereo pair of oriented
  keyframes (what the map holds), over all passed survey cells (NaN before any).
No ROS here; the map node feeds it, io/mission.py turns reports into GeoJSON and re-fly plans.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.errors import ConfigError
from photogram_ros.params import param

COVERAGE, NOT_ORIENTED, FORWARD_OVERLAP = 'coverage', 'not_oriented', 'forward_overlap'   # Gap kinds
_SHIFT = 4   # cv2.fillPoly sub-pixel bits


@dataclass
class CoverageConfig:
    """What counts as covered, and which gaps are reported."""
    coverage_cell_m: float = param(1.0, 'Cell of the coverage grid, m', min=0.05, max=100.0)
    min_views: int = param(2, 'A survey cell seen by fewer keyframes is a gap', min=1, max=100)
    min_pair_overlap: float = param(0.4, 'Consecutive keyframes overlapping this much form a stereo pair (as '
                                         'stereo_node.min_overlap)', min=0.0, max=1.0)
    target_forward_overlap: float = param(0.6, 'Forward overlap below this between consecutive keyframes of a '
                                               'line is reported (figures, go/no-go)', min=0.0, max=0.99)
    target_side_overlap: float = param(0.3, 'Side overlap below this between neighbouring lines is reported',
                                       min=0.0, max=0.99)
    swath_margin_m: float = param(1.0, 'Without a mission polygon the survey area is the swath of each flight line '
                                       '(between its first and last keyframe, as wide as the footprints) less '
                                       'this margin at its sides, m', min=0.0, max=1000.0)
    min_gap_area_m2: float = param(4.0, 'Gaps smaller than this are not listed, m^2', min=0.0, max=1e9)
    line_angle_deg: float = param(10.0, 'Keyframes whose step turns more than this start a new flight line',
                                  min=1.0, max=90.0)

    def check(self) -> None:
        if not self.coverage_cell_m > 0:
            raise ConfigError(f'coverage_cell_m {self.coverage_cell_m} must be positive')


@dataclass
class Gap:
    kind: str                  # COVERAGE, NOT_ORIENTED or FORWARD_OVERLAP
    polygon_map_m: np.ndarray  # (N, 2) outline in map ENU, m
    area_m2: float
    centroid_map_m: np.ndarray  # (2,)
    min_views: int             # fewest keyframes that saw a cell of it


@dataclass
class CoverageReport:
    keyframes: int
    lines: int
    survey_area_m2: float
    passed_area_m2: float
    coverage_share: float          # NaN before any survey cell was passed
    stereo_share: float
    forward_overlap_median: float  # NaN without a line of 2 keyframes
    forward_overlap_min: float
    side_overlap_min: float        # NaN with fewer than two lines
    low_forward_pairs: list        # [(stamp_a_ns, stamp_b_ns, overlap)] below target_forward_overlap
    gaps: list = field(default_factory=list)
    survey_outline_map_m: list = field(default_factory=list)   # [(N, 2)] outer rings of the survey area

    def gap_area_m2(self, kind: str = COVERAGE) -> float:
        return float(sum(g.area_m2 for g in self.gaps if g.kind == kind))


def footprint(camera: PinholeCamera, map_T_cam: np.ndarray, ground_z_m: float, per_edge: int = 8,
              max_range_factor: float = 5.0) -> np.ndarray:
    """The image border cast on the plane z = ground_z_m: (4 * per_edge, 2) polygon in map ENU. Rays that
    do not reach the plane (above the horizon) stop at max_range_factor times the height above it."""
    w, h = camera.width - 0.5, camera.height - 0.5
    t = np.linspace(0.0, 1.0, per_edge, endpoint=False)
    u = np.concatenate([-0.5 + t * (w + 0.5), np.full(per_edge, w), w - t * (w + 0.5), np.full(per_edge, -0.5)])
    v = np.concatenate([np.full(per_edge, -0.5), -0.5 + t * (h + 0.5), np.full(per_edge, h), h - t * (h + 0.5)])
    rays = camera.unproject(np.column_stack([u, v])) @ map_T_cam[:3, :3].T
    C = map_T_cam[:3, 3]
    height = C[2] - ground_z_m
    down = -rays[:, 2]
    s = np.where(down > 1e-6, height / np.maximum(down, 1e-6), np.inf)
    s = np.minimum(s, max_range_factor * max(height, 1e-3) / np.maximum(np.linalg.norm(rays[:, :2], axis=1), 1e-9))
    return C[:2] + rays[:, :2] * s[:, None]


@dataclass
class _Kf:
    stamp_ns: int
    centre_m: np.ndarray     # (3,)
    ground_z_m: float
    polygon_m: np.ndarray    # (N, 2)
    oriented: bool           # the adjustment's pose (False: a stand-in from the keyframe's GNSS fix)
    i0: int                  # global cell column of mask[0, 0]
    j0: int                  # global cell row (south to north) of mask[0, 0]
    mask: np.ndarray         # uint8 (rows, cols)


class Coverage:
    def __init__(self, camera: PinholeCamera, config: CoverageConfig | None = None,
                 survey_area_map_m: list | None = None):
        self.camera = camera
        self.cfg = config or CoverageConfig()
        self.cfg.check()
        self.survey_area_map_m = [np.asarray(p, float).reshape(-1, 2) for p in (survey_area_map_m or [])]
        self._kfs: dict[int, _Kf] = {}
        self._judged: np.ndarray | None = None   # sticky: cells the drone has passed
        self._judged_ij = (0, 0)
        self._finished = False
        self.views: np.ndarray | None = None     # last update's grids (rows south to north)
        self.stereo: np.ndarray | None = None
        self.survey: np.ndarray | None = None
        self.grid_ij = (0, 0)                    # global (column, row) of views[0, 0]

    # --- input -----------------------------------------------------------------------------------

    def set_keyframe(self, stamp_ns: int, map_T_cam: np.ndarray, ground_z_m: float, oriented: bool = True) -> None:
        """Add a keyframe, or replace its pose (a refined pose with the same stamp). oriented=False: the pose is
        a stand-in (the keyframe's fix, the attitude of an oriented neighbour) for a keyframe the adjustment
        has not oriented (yet): it counts for what the camera saw, not for what is mapped, and an oriented
        pose replaces it, never the other way round."""
        T = np.asarray(map_T_cam, float)
        old = self._kfs.get(int(stamp_ns))
        if old is not None and old.oriented and not oriented:
            return
        if (old is not None and old.oriented == oriented and np.allclose(old.centre_m, T[:3, 3], atol=1e-3)
                and old.ground_z_m == ground_z_m):
            return
        poly = footprint(self.camera, T, ground_z_m)
        self._kfs[int(stamp_ns)] = self._rasterise(int(stamp_ns), T[:3, 3].copy(), float(ground_z_m), poly, oriented)

    def oriented(self, stamp_ns: int) -> bool:
        k = self._kfs.get(int(stamp_ns))
        return k is not None and k.oriented

    def finish(self) -> None:
        """The flight is over: every survey cell counts as passed."""
        self._finished = True

    def __len__(self) -> int:
        return len(self._kfs)

    @property
    def newest_stamp_ns(self) -> int:
        return max(self._kfs, default=0)

    def flight_figures(self) -> dict:
        """Median height above the ground and footprint across / along the flight (what a re-fly needs), m."""
        kfs = [self._kfs[s] for s in sorted(self._kfs)]
        if len(kfs) < 2:
            return {}
        heights, across, along = [], [], []
        for a, b in zip(kfs[:-1], kfs[1:]):
            d = b.centre_m[:2] - a.centre_m[:2]
            if np.linalg.norm(d) < 1e-3:
                continue
            h = d / np.linalg.norm(d)
            rel = b.polygon_m - b.centre_m[:2]
            along.append(float(np.ptp(rel @ h)))
            across.append(float(np.ptp(rel @ [-h[1], h[0]])))
            heights.append(b.centre_m[2] - b.ground_z_m)
        if not heights:
            return {}
        return {'height_above_ground_m': float(np.median(heights)), 'footprint_width_m': float(np.median(across)),
                'footprint_length_m': float(np.median(along))}

    def _rasterise(self, stamp_ns, centre, ground_z, poly, oriented) -> _Kf:
        c = self.cfg.coverage_cell_m
        i0, j0 = np.floor(poly.min(axis=0) / c).astype(int) - 1
        i1, j1 = np.floor(poly.max(axis=0) / c).astype(int) + 2
        mask = np.zeros((j1 - j0, i1 - i0), np.uint8)
        _fill(mask, poly / c - [i0, j0])
        return _Kf(stamp_ns, centre, ground_z, poly, oriented, int(i0), int(j0), mask)

    # --- the report ------------------------------------------------------------------------------

    def update(self) -> CoverageReport:
        cfg, c = self.cfg, self.cfg.coverage_cell_m
        kfs = [self._kfs[s] for s in sorted(self._kfs)]
        if not kfs:
            return CoverageReport(0, 0, 0.0, 0.0, float('nan'), float('nan'), float('nan'), float('nan'),
                                  float('nan'), [])
        lo = np.min([[k.i0, k.j0] for k in kfs], axis=0)
        hi = np.max([[k.i0 + k.mask.shape[1], k.j0 + k.mask.shape[0]] for k in kfs], axis=0)
        for p in self.survey_area_map_m:
            lo = np.minimum(lo, np.floor(p.min(axis=0) / c).astype(int) - 1)
            hi = np.maximum(hi, np.floor(p.max(axis=0) / c).astype(int) + 2)
        gi, gj = int(lo[0]), int(lo[1])
        shape = (int(hi[1] - gj), int(hi[0] - gi))
        views = np.zeros(shape, np.uint16)      # every keyframe: what the camera saw
        views_or = np.zeros(shape, np.uint16)   # oriented keyframes: what the map can hold
        # The adjuster takes keyframes in stamp order: a stand-in newer than its newest oriented keyframe is
        # still waiting for it, and counts as oriented until a later keyframe is oriented without it.
        newest = max((k.stamp_ns for k in kfs if k.oriented), default=-1)
        mapped = [k.oriented or k.stamp_ns > newest for k in kfs]
        for k, m in zip(kfs, mapped):
            views[self._slice(k, gi, gj)] += k.mask
            if m:
                views_or[self._slice(k, gi, gj)] += k.mask
        lines = _lines(np.array([k.centre_m[:2] for k in kfs]), cfg.line_angle_deg)
        stereo = np.zeros(shape, bool)
        stereo_or = np.zeros(shape, bool)
        overlaps = []   # overlap of each consecutive pair
        for a, (ka, kb) in enumerate(zip(kfs[:-1], kfs[1:])):
            inter, ov = _intersection(ka, kb)
            overlaps.append(ov)
            if inter is not None and ov >= cfg.min_pair_overlap:
                sl = inter[0].shift(gi, gj)
                stereo[sl] |= inter[1]
                if mapped[a] and mapped[a + 1]:
                    stereo_or[sl] |= inter[1]
        survey = self._survey_mask(kfs, lines, shape, gi, gj)
        judged = self._judge(kfs, shape, gi, gj)
        self.views, self.stereo, self.survey, self.grid_ij = views, stereo, survey, (gi, gj)

        bad = survey & judged & ((views < cfg.min_views) | ~stereo)
        unmapped = survey & judged & ~bad & ((views_or < cfg.min_views) | ~stereo_or)
        gaps = [g for g in _components(bad, views, gi, gj, c, COVERAGE) + _components(unmapped, views_or, gi, gj, c,
                                                                                       NOT_ORIENTED)
                if g.area_m2 >= cfg.min_gap_area_m2]
        fwd, low = [], []
        for line in lines:
            for a in line[:-1]:
                fwd.append(overlaps[a])
                if overlaps[a] < cfg.target_forward_overlap:
                    low.append((kfs[a].stamp_ns, kfs[a + 1].stamp_ns, float(overlaps[a])))
                    gaps += [g for g in self._between(kfs[a], kfs[a + 1], views, gi, gj)
                             if g.area_m2 >= cfg.min_gap_area_m2]
        passed = survey & judged
        n_passed = int(passed.sum())
        good = passed & (views_or >= cfg.min_views) & stereo_or
        outline = _outlines(survey, gi, gj, c)
        return CoverageReport(
            keyframes=len(kfs), lines=len(lines), survey_area_m2=float(survey.sum() * c * c),
            passed_area_m2=float(n_passed * c * c),
            coverage_share=float(good.sum() / n_passed) if n_passed else float('nan'),
            stereo_share=float((passed & stereo_or).sum() / n_passed) if n_passed else float('nan'),
            forward_overlap_median=float(np.median(fwd)) if fwd else float('nan'),
            forward_overlap_min=float(np.min(fwd)) if fwd else float('nan'),
            side_overlap_min=self._side_overlap(kfs, lines, shape, gi, gj), low_forward_pairs=low, gaps=gaps,
            survey_outline_map_m=outline)

    @staticmethod
    def _slice(k: _Kf, gi: int, gj: int):
        return (slice(k.j0 - gj, k.j0 - gj + k.mask.shape[0]), slice(k.i0 - gi, k.i0 - gi + k.mask.shape[1]))

    def _survey_mask(self, kfs: list[_Kf], lines: list[list[int]], shape, gi: int, gj: int) -> np.ndarray:
        """The mission polygon, else the union of the flight lines' swaths (holes filled): each the band
        from the line's first to its last camera centre, as wide as its footprints' narrowest
        half-width across the line, less swath_margin_m."""
        c = self.cfg.coverage_cell_m
        m = np.zeros(shape, np.uint8)
        if self.survey_area_map_m:
            for p in self.survey_area_map_m:
                _fill(m, p / c - [gi, gj])
            return m > 0
        for line in lines:
            idx = [*line, line[-1] + 1]
            C = np.array([kfs[i].centre_m[:2] for i in idx])
            d = C[-1] - C[0]
            if np.linalg.norm(d) < 1e-3:
                continue
            h = d / np.linalg.norm(d)
            n = np.array([-h[1], h[0]])
            half = min(_half_width(kfs[i], h) for i in idx)
            half -= self.cfg.swath_margin_m
            if half <= 0:
                continue
            for a, b in zip(C[:-1], C[1:]):   # one quadrilateral per step: follows a curving line
                quad = np.array([a + half * n, b + half * n, b - half * n, a - half * n])
                _fill(m, quad / c - [gi, gj])
        return _fill_holes(m)

    def _judge(self, kfs: list[_Kf], shape, gi: int, gj: int) -> np.ndarray:
        """Cells the drone has passed: within reach of the track (the polyline of the camera centres; reach: the
        newest footprint's half-width across its heading) and behind the newest footprint along the newest step, while flying a line (sticky);
        less those ahead of the drone in the current line's swath."""
        judged = np.zeros(shape, bool)
        if self._judged is not None:   # carry the old mask into the (possibly larger) grid
            oi, oj = self._judged_ij
            h, w = self._judged.shape
            r0, r1 = max(oj - gj, 0), min(oj - gj + h, shape[0])
            c0, c1 = max(oi - gi, 0), min(oi - gi + w, shape[1])
            if r1 > r0 and c1 > c0:
                judged[r0:r1, c0:c1] = self._judged[r0 + gj - oj:r1 + gj - oj, c0 + gi - oi:c1 + gi - oi]
        if self._finished:
            judged[:] = True
        elif len(kfs) >= 4:
            c = self.cfg.coverage_cell_m
            new, prev = kfs[-1], kfs[-2]
            step = new.centre_m[:2] - prev.centre_m[:2]
            if not self._straight(kfs):   # in a turn the footprint sweeps sideways: judge nothing
                self._judged, self._judged_ij = judged, (gi, gj)
                return judged
            h = step / np.linalg.norm(step)
            rel = new.polygon_m - new.centre_m[:2]
            # Reach: the footprint's half-width across the heading (what beside the line is seen from it).
            reach = _half_width(new, h)
            track = np.full(shape, 255, np.uint8)
            ij = np.round((np.array([k.centre_m[:2] for k in kfs]) / c - [gi, gj] - 0.5) * (1 << _SHIFT))
            cv2.polylines(track, [ij.astype(np.int32).reshape(-1, 1, 2)], False, 0, 1, cv2.LINE_8, _SHIFT)
            near = cv2.distanceTransform(track, cv2.DIST_L2, 5) * c <= reach
            front = float(np.max(rel @ h))
            xs = (np.arange(shape[1]) + gi + 0.5) * c - new.centre_m[0]
            ys = (np.arange(shape[0]) + gj + 0.5) * c - new.centre_m[1]
            along = xs[None, :] * h[0] + ys[:, None] * h[1]
            judged |= near & (along < -front)
            # Ahead of the drone, within the line's swath, the line may still cover what an earlier line
            # left: not judged until it has passed (an earlier line's edge is not a gap yet).
            ahead = (along >= -front) & (np.abs(ys[:, None] * h[0] - xs[None, :] * h[1]) <= reach)
            self._judged, self._judged_ij = judged, (gi, gj)
            return judged & ~ahead
        self._judged, self._judged_ij = judged, (gi, gj)
        return judged

    def _straight(self, kfs: list[_Kf], steps: int = 3) -> bool:
        """The newest `steps` steps keep one heading (within line_angle_deg): the drone flies a line."""
        if len(kfs) < steps + 1:
            return False
        d = np.diff(np.array([k.centre_m[:2] for k in kfs[-steps - 1:]]), axis=0)
        n = np.linalg.norm(d, axis=1)
        if np.any(n < 1e-3):
            return False
        d /= n[:, None]
        return bool(np.all(d[1:] @ d[-1] >= np.cos(np.radians(self.cfg.line_angle_deg))))

    def _between(self, a: _Kf, b: _Kf, views, gi, gj) -> list[Gap]:
        """Ground inside the hull of two consecutive footprints that neither sees: what a line missed."""
        c = self.cfg.coverage_cell_m
        hull = np.zeros(views.shape, np.uint8)
        pts = cv2.convexHull(np.vstack([a.polygon_m, b.polygon_m]).astype(np.float32)).reshape(-1, 2)
        _fill(hull, pts / c - [gi, gj])
        seen = np.zeros(views.shape, bool)
        for k in (a, b):
            seen[self._slice(k, gi, gj)] |= k.mask > 0
        missed = ((hull > 0) & ~seen).astype(np.uint8)
        r = max(int(round(2.5 / c)), 1)   # drop the slivers between the hull and bowed footprint edges
        missed = cv2.morphologyEx(missed, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                                                                     (2 * r + 1, 2 * r + 1)))
        return _components(missed > 0, views, gi, gj, c, FORWARD_OVERLAP)

    def _side_overlap(self, kfs: list[_Kf], lines: list[list[int]], shape, gi: int, gj: int) -> float:
        """Smallest over the lines of the median share of a keyframe's footprint the nearest parallel line sees."""
        if len(lines) < 2:
            return float('nan')
        members = [[*line, line[-1] + 1] for line in lines]
        unions, heads = [], []
        for idx in members:
            u = np.zeros(shape, bool)
            for i in idx:
                u[self._slice(kfs[i], gi, gj)] |= kfs[i].mask > 0
            unions.append(u)
            d = kfs[idx[-1]].centre_m[:2] - kfs[idx[0]].centre_m[:2]
            heads.append(d / max(np.linalg.norm(d), 1e-9))
        worst = float('nan')
        for li, idx in enumerate(members):
            others = [lj for lj in range(len(members)) if lj != li and abs(heads[li] @ heads[lj]) > 0.9]
            if not others:
                continue
            shares = []
            for i in idx:
                k = kfs[i]
                m = k.mask > 0
                sl = self._slice(k, gi, gj)
                shares.append(max(float((m & unions[lj][sl]).sum()) for lj in others) / max(int(m.sum()), 1))
            med = float(np.median(shares))
            worst = med if not np.isfinite(worst) else min(worst, med)
        return worst


# --- helpers -------------------------------------------------------------------------------------


def _half_width(k: _Kf, h: np.ndarray) -> float:
    """Half-width of a footprint across heading h, through its camera centre (the nearer side): what a line
    sees beside it all along, where the corners of a distorted footprint reach further."""
    rel = k.polygon_m - k.centre_m[:2]
    along, lat = rel @ h, rel @ np.array([-h[1], h[0]])
    a0, a1 = along, np.roll(along, -1)
    l0, l1 = lat, np.roll(lat, -1)
    cross = (a0 <= 0) != (a1 <= 0)
    if not cross.any():
        return float(np.min(np.abs(lat)))
    t = a0[cross] / (a0[cross] - a1[cross])
    return float(np.min(np.abs(l0[cross] + t * (l1[cross] - l0[cross]))))


def _fill(mask: np.ndarray, poly_cells: np.ndarray) -> None:
    """Fill a polygon given in cell units (x = column, y = row; cell (i, j) spans [i, i + 1))."""
    pts = np.round((np.asarray(poly_cells, float) - 0.5) * (1 << _SHIFT)).astype(np.int32)
    cv2.fillPoly(mask, [pts.reshape(-1, 1, 2)], 1, lineType=cv2.LINE_8, shift=_SHIFT)


def _fill_holes(m: np.ndarray) -> np.ndarray:
    """Cells of m and every region of zeros that m encloses."""
    pad = np.pad((m > 0).astype(np.uint8), 1)
    flood = pad.copy()
    cv2.floodFill(flood, np.zeros((pad.shape[0] + 2, pad.shape[1] + 2), np.uint8), (0, 0), 2)
    return (flood != 2)[1:-1, 1:-1]


class _Window:
    def __init__(self, i0, j0, rows, cols):
        self.i0, self.j0, self.rows, self.cols = i0, j0, rows, cols

    def shift(self, gi, gj):
        return (slice(self.j0 - gj, self.j0 - gj + self.rows), slice(self.i0 - gi, self.i0 - gi + self.cols))


def _intersection(a: _Kf, b: _Kf):
    """(window, bool mask of a & b in it) and the share of a's footprint that b sees."""
    i0, j0 = max(a.i0, b.i0), max(a.j0, b.j0)
    i1 = min(a.i0 + a.mask.shape[1], b.i0 + b.mask.shape[1])
    j1 = min(a.j0 + a.mask.shape[0], b.j0 + b.mask.shape[0])
    na = max(int(a.mask.sum()), 1)
    if i1 <= i0 or j1 <= j0:
        return None, 0.0
    ma = a.mask[j0 - a.j0:j1 - a.j0, i0 - a.i0:i1 - a.i0] > 0
    mb = b.mask[j0 - b.j0:j1 - b.j0, i0 - b.i0:i1 - b.i0] > 0
    inter = ma & mb
    return (_Window(i0, j0, j1 - j0, i1 - i0), inter), float(inter.sum()) / na


def _lines(centres: np.ndarray, angle_deg: float) -> list[list[int]]:
    """Flight lines: runs of at least three steps keeping one heading; each a list of step indices k
    (the step from keyframe k to k + 1)."""
    steps = np.diff(centres, axis=0)
    lines, run, head = [], [], None
    cos_max = np.cos(np.radians(angle_deg))
    for k, s in enumerate(steps):
        n = np.linalg.norm(s)
        if n < 1e-3:
            if run:
                run.append(k)
            continue
        d = s / n
        if head is not None and d @ head >= cos_max:
            run.append(k)
            head = head + 0.2 * (d - head)
            head /= np.linalg.norm(head)
        else:
            if len(run) >= 3:
                lines.append(run)
            run, head = [k], d
    if len(run) >= 3:
        lines.append(run)
    return lines


def _cells_to_map(contour: np.ndarray, gi: int, gj: int, c: float) -> np.ndarray:
    return (contour.reshape(-1, 2).astype(float) + [gi, gj]) * c


def _components(bad: np.ndarray, views: np.ndarray, gi: int, gj: int, c: float, kind: str) -> list[Gap]:
    n, labels, stats, cent = cv2.connectedComponentsWithStats(bad.astype(np.uint8), connectivity=8)
    out = []
    for lab in range(1, n):
        sub = labels == lab
        cs, _ = cv2.findContours(np.pad(sub, 1).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        contour = max(cs, key=cv2.contourArea).reshape(-1, 2) - 1
        # findContours walks cell centres: widen the ring half a cell outward from the component's centre.
        mid = contour.mean(axis=0)
        ring = contour + 0.5 + 0.5 * np.sign(contour - mid)
        out.append(Gap(kind, _cells_to_map(ring, gi, gj, c), float(stats[lab, cv2.CC_STAT_AREA] * c * c),
                       (np.asarray(cent[lab]) + 0.5 + [gi, gj]) * c, int(views[sub].min())))
    return out


def _outlines(mask: np.ndarray, gi: int, gj: int, c: float) -> list[np.ndarray]:
    cs, _ = cv2.findContours(np.pad(mask, 1).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    return [_cells_to_map(ct.reshape(-1, 2) - 1 + 0.5, gi, gj, c) for ct in cs if len(ct) >= 3]
