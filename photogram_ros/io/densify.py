"""Dense matching after the flight, from the final adjustment: a new map folder for the products.

In flight, stereo pairs a keyframe once it has left the bundle window, with the pose it has then;
the final full adjustment moves poses again (by centimetres and tens of arcseconds), and a pair's
depth is sensitive to its two cameras' relative tilt (Z^2 / B per radian: 2 cm per 10 arcsec at
40 m with an 8 m baseline). So the survey products are made again from the keyframes and the final
poses of the in-flight map folder, the way photogrammetry software densifies after triangulation:
the same pair planner (core/pairs.plan_pairs), stereo and fusion as the nodes, in keyframe order, with
the planner's final_* criteria (PairCriteria.for_final): one partner along and two across each
keyframe (the stereo node takes one and one) down to a quarter of the image in common: a cell of the
products is confirmed by two pairs that agree (export's min_pairs 2; one pair's cells fill in where no
confirmed cell is near), and across lines most cells have more than two candidates.
The map folder holds no tie points (io/map_store.py), only their median height (io/flight_inputs.py): each pair
searches the ground height (the in-flight map's, else the tie points') +- relief_m, unless the caller passes tie points (the flight's, or the in-flight map's surface: surface_points). The in-flight map stays
what it was (what the ground station saw); the products come from the new folder. Given the map
folder the result is deterministic, unlike the in-flight map, whose pairing depends on timing.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from photogram_ros.core import gsd
from photogram_ros.core.fusion import Fusion, FusionConfig, downsample
from photogram_ros.core.pairs import BELOW_GROUND, PairCriteria, plan_pairs
from photogram_ros.core.stereo import StereoParams, stereo_pair
from photogram_ros.errors import DataError, PhotogramError
from photogram_ros.io import flight_inputs
from photogram_ros.io.map_store import MapStore, as_map_store


@dataclass
class DensifyResult:
    map_dir: Path
    store: MapStore                       # the new map folder, open
    keyframes: int = 0
    pairs_done: int = 0
    pairs_depth_from_tie_points: int = 0
    pairs_skipped: dict = field(default_factory=dict)
    points_fused: int = 0
    ground_m: float = float('nan')
    ground_from: str = ''                 # where ground_m came from (_ground_height: GROUND_FROM_MAP, ...)
    seconds: float = 0.0
    pairs_failed: list = field(default_factory=list)   # 'stamp_a/stamp_b: why' of pairs that raised
    gsd: dict | None = None               # core/gsd.GsdSettings of the flight (as_dict)
    derived: list = field(default_factory=list)        # the parameters taken from it
    stereo_s: float = 0.0                 # time in stereo_pair


MAX_FAILED_NAMED = 20   # pairs_failed keeps the first ones; pairs_skipped['failed'] counts them all


GROUND_FROM_MAP = 'the in-flight map'
GROUND_FROM_TIE_POINTS = 'the adjuster\'s tie points'
GROUND_ASSUMED = 'assumed 40 m below the keyframes'
ASSUMED_HEIGHT_M = 40.0


def _ground_height(store: MapStore, kfs: list[dict]) -> tuple[float, str]:
    """The ground the depth search centres on (map z, m) and where it came from: the median height of the
    in-flight map, else of the adjuster's latest tie points (io/flight_inputs.tie_point_ground: a replay whose
    stereo found no partner or shed its pairs fused nothing), else 40 m below the keyframes (nothing better is
    known: a pair's depth search then misses a ground much further down)."""
    z = []
    for key in store.tile_keys()[:64]:
        cells = store.load_tile(key)
        if cells is not None:
            z.append(np.asarray(cells['z'][cells['n'] > 0], float)[::7])
    z = np.concatenate(z) if z else np.zeros(0)
    if z.size >= 20:
        return float(np.median(z)), GROUND_FROM_MAP
    tie_ground_m = flight_inputs.tie_point_ground(store.root)
    if tie_ground_m is not None:
        return tie_ground_m, GROUND_FROM_TIE_POINTS
    return float(np.median([k['map_T_cam'][2, 3] for k in kfs])) - ASSUMED_HEIGHT_M, GROUND_ASSUMED


def surface_points(store: MapStore, block_cells: int = 4, max_points: int = 500_000) -> np.ndarray | None:
    """The in-flight map's fused surface as (N, 3) map points (block means of block_cells x block_cells
    cells, at most max_points), or None when it holds too few: what each final pair searches around."""
    fusion = Fusion(FusionConfig(store.cell_m, store.tile_cells, max_tiles_in_memory=1), store)
    parts = []
    for key, cells in fusion.iter_tiles():
        q = downsample(fusion.tile_points(key, cells), block_cells, store.cell_m)
        if q['x'].size:
            parts.append(np.column_stack([q['x'], q['y'], q['z']]))
    if not parts:
        return None
    P = np.concatenate(parts)
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) < 100:
        return None
    return P[::int(np.ceil(len(P) / max_points))]


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


MAX_IMAGES_HELD = 6   # decoded keyframe images held at once while matching (13 MB each at 2400x1800)


class ImageCache:
    """Decoded keyframe images for the pairs of keyframes 0, 1, ... in turn: `uses[i]` lists the images the
    pairs of keyframe i read. An image is dropped after its last use, and past `max_held` the one needed
    latest goes first (read again when its turn comes): memory stays at a few images, not the flight's."""

    def __init__(self, path_of, uses: list[list[int]], max_held: int = MAX_IMAGES_HELD):
        self.path_of, self.max_held = path_of, max(int(max_held), 2)
        self.uses = {}   # image -> the keyframes (in order) whose pairs read it
        for i, used in enumerate(uses):
            for j in dict.fromkeys(used):
                self.uses.setdefault(j, []).append(i)
        self.held: dict[int, np.ndarray] = {}
        self.reads = 0

    def _next_use(self, j: int, now: int) -> int:
        return next((i for i in self.uses.get(j, ()) if i >= now), 1 << 62)

    def get(self, j: int, now: int) -> np.ndarray:
        """Image j for the pairs of keyframe `now` (BGR); a DataError when it cannot be read."""
        if j not in self.held:
            img = cv2.imread(str(self.path_of(j)), cv2.IMREAD_COLOR)
            if img is None:
                raise DataError(f'keyframe image {self.path_of(j)} is unreadable')
            self.reads += 1
            while len(self.held) >= self.max_held:
                del self.held[max(self.held, key=lambda k: self._next_use(k, now))]
            self.held[j] = img
        return self.held[j]

    def done(self, now: int) -> None:
        """The pairs of keyframe `now` are matched: images no later keyframe reads are dropped."""
        for j in [j for j in self.held if self._next_use(j, now + 1) == 1 << 62]:
            del self.held[j]


def densify_map(map_dir: str | Path | MapStore, out_dir: str | Path, stereo: StereoParams, criteria: PairCriteria,
                fusion: FusionConfig, progress=None, tie_points_map: np.ndarray | None = None) -> DensifyResult:
    """Match the keyframes of `map_dir` (a folder or an open MapStore) with their final poses into a new
    map folder `out_dir`.

    `criteria` and `stereo` are the nodes' (the flight's parameter file); the pairs are planned with
    criteria.for_final() and matched with its final_min_overlap (final_lr_check false: no left-right check).
    `out_dir` gets the origin, camera (the final adjustment's when the bundle adjuster sent it), the targets'
    detections and the keyframes (hard links where the file system allows) of `map_dir` and freshly fused tiles; an existing folder there is replaced. Pairs and depth searches
    come from core/pairs.plan_pairs around the in-flight map's ground height, narrowed to the pair's
    tie points `tie_points_map` (N, 3, map m; default: none, the ground +- relief_m). Passing the in-flight
    map's surface (surface_points) makes the search narrower but is not the default: on the sample flight it
    raised the DSM's RMSE from 1.33 to 1.53 GSD (walls and roofs the in-flight map holds no height for) for
    no gain in time on phantom3 (29 s against 25 s for 118 pairs, within the machine's noise).
    `progress(done, total)` is called after each keyframe. Parameters left at core/gsd.AUTO are derived
    from the camera and the keyframes' median height above that ground (res.gsd, res.derived). A pair
    that cannot be matched (rectification impossible, unreadable image, ...) is skipped and named in
    res.pairs_failed: one bad pair costs one pair.
    """
    t0 = time.perf_counter()
    src = as_map_store(map_dir)
    cam, origin, kfs = src.load_camera(), src.origin, sorted(src.keyframes(), key=lambda k: k['stamp_ns'])
    if cam is None or origin is None or len(kfs) < 2:
        missing = [w for w, gone in (('no camera (camera.json)', cam is None),
                                     ('no origin (the bundle adjuster georeferenced no keyframe)', origin is None),
                                     (f'{len(kfs)} posed keyframes (2 are needed)', len(kfs) < 2)) if gone]
        images = len(list((src.root / 'keyframes').glob('*.jpg')))
        raise DataError(f'{src.root}: nothing to densify: ' + ', '.join(missing)
                        + (f'; {images} keyframe images were saved before the flight was cut short' if images else ''))
    out = Path(out_dir)
    if out.resolve() == src.root.resolve():
        raise DataError('densify writes a new map folder: give another out_dir than the map itself')
    ground_m, ground_from = _ground_height(src, kfs)
    # After the flight the matching has time the stereo node has not: more partners per keyframe.
    criteria = criteria.for_final()
    stereo = dataclasses.replace(stereo, min_overlap=criteria.min_overlap,
                                 lr_check=stereo.lr_check and criteria.final_lr_check)
    settings = gsd.derive(cam.width, cam.height, cam.fx,
                          float(np.median([k['map_T_cam'][2, 3] for k in kfs])) - ground_m, stereo.downscale)
    stereo, names_s = gsd.resolve(stereo, settings)
    criteria, names_c = gsd.resolve(criteria, settings)
    fusion, names_f = gsd.resolve(fusion, settings)
    if out.exists():
        shutil.rmtree(out)
    dst = MapStore(out, fusion.cell_m, fusion.tile_cells)
    dst.set_origin(origin)
    dst.save_camera(cam, src.camera_name() or 'camera')
    control_points = src.control_points()   # the in-flight detections of the targets, for the report
    if control_points is not None:
        dst.save_control_points(control_points)
    flight_inputs.copy_inputs(src.root, dst.root)   # the flight's fixes and first calibration, for the report
    for k in kfs:
        _link_or_copy(k['image_path'], dst.keyframes_dir / k['image_path'].name)
        dst.save_keyframe_pose(k['stamp_ns'], k['map_T_cam'])
    res = DensifyResult(out, dst, keyframes=len(kfs), ground_m=ground_m, ground_from=ground_from, gsd=settings.as_dict(),
                        derived=sorted(set(names_s + names_c + names_f)))
    fuser = Fusion(fusion, dst)
    C = np.array([k['map_T_cam'][:3, 3] for k in kfs])
    plans = []   # each keyframe's pairs, from the poses alone: when each image is last needed is known up front
    for i, kf in enumerate(kfs):
        T = kf['map_T_cam']
        height = float(T[2, 3] - res.ground_m)
        # Partners can only be keyframes whose footprints overlap: a distance test first keeps pair
        # choice linear in the flight length.
        reach = 2.0 * max(height, 0.0) * max(cam.width, cam.height) / cam.fx
        near = np.flatnonzero(np.linalg.norm(C[:i] - C[i], axis=1) < reach)
        others = {int(j): kfs[j]['map_T_cam'] for j in near}
        plans.append(plan_pairs(cam, T, others, res.ground_m, criteria, (stereo.min_depth_m, stereo.max_depth_m),
                                tie_points_map))
    images = ImageCache(lambda i: kfs[i]['image_path'],
                        [[i] + [p.other for p in plan.pairs] if plan.status != BELOW_GROUND else []
                         for i, plan in enumerate(plans)])

    for i, (kf, plan) in enumerate(zip(kfs, plans)):
        T = kf['map_T_cam']
        if plan.status == BELOW_GROUND:
            res.pairs_skipped['below_ground'] = res.pairs_skipped.get('below_ground', 0) + 1
        for pair in plan.pairs if plan.status != BELOW_GROUND else ():
            res.pairs_depth_from_tie_points += pair.from_tie_points
            t_pair = time.perf_counter()
            try:
                r = stereo_pair(cam, images.get(pair.other, i), kfs[pair.other]['map_T_cam'], images.get(i, i), T,
                                stereo, pair.depth_range_m)
            except (PhotogramError, cv2.error) as exc:
                res.pairs_skipped['failed'] = res.pairs_skipped.get('failed', 0) + 1
                if len(res.pairs_failed) < MAX_FAILED_NAMED:
                    res.pairs_failed.append(f'{kfs[pair.other]["stamp_ns"]}/{kf["stamp_ns"]}: {exc}')
                continue
            finally:
                res.stereo_s += time.perf_counter() - t_pair
            if not r.ok:
                res.pairs_skipped[r.status] = res.pairs_skipped.get(r.status, 0) + 1
                continue
            res.points_fused += fuser.add(r.cloud)
            res.pairs_done += 1
        images.done(i)
        if progress is not None and plan.status != BELOW_GROUND:
            progress(i + 1, len(kfs))
    fuser.flush()
    dst.sync()
    res.seconds = time.perf_counter() - t0
    return res
