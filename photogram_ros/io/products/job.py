"""What every export product shares: the product's description (`ExportProduct`) and the export under way
(`ExportJob`): the map, the options, the cloud, the intermediate results made once for the products that
need them (the cloud's classes, the DSM surface, the DTM) and `keep`, which writes a product whole or
records why a full disk stopped it.

The heavy modules are imported where they are used, so that the registry (io/products/__init__.py) can be
read by a command's --help in no time.
"""

from __future__ import annotations

import errno
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from photogram_ros.errors import StorageError
from photogram_ros.io.export_files import ExportResult, disk_full, write_whole

# The intermediate results a product may need, in the order they are made, and the progress step that makes
# each (None: made within the step before it).
INTERMEDIATE_STEPS = {'classes': None, 'surface': 'DSM', 'dtm': 'DTM'}


@dataclass(frozen=True)
class ExportProduct:
    """One export product: `key` (its name in --products), `step` (its progress step; None: written in the
    step of the intermediate result it needs), `needs` (intermediate results, INTERMEDIATE_STEPS, made before
    it), `write(job)`, and whether it is asked for by name (`by_name`) or by an option (`wanted(job)`)."""
    key: str
    step: str | None
    needs: tuple[str, ...]
    write: Callable[['ExportJob'], None]
    by_name: bool = True
    wanted: Callable[['ExportJob'], bool] | None = None

    def chosen(self, job: 'ExportJob') -> bool:
        return self.key in job.products if self.by_name else bool(self.wanted and self.wanted(job))


@dataclass(frozen=True)
class Writers:
    """The file writers the products write with (io/export.py hands its own: a test can swap one)."""
    las: Callable
    ply: Callable
    geotiff: Callable


@dataclass
class ExportJob:
    """One export of a map folder into `out`: what the products read and what they add to `res`."""
    store: Any                      # io/map_store.MapStore
    fusion: Any                     # core/fusion.Fusion over the map's tiles
    origin: Any                     # core/geodesy.LocalFrame
    crs: str
    heights: str
    out: Path
    products: tuple[str, ...]       # the names asked for
    min_pairs: int
    dsm_res_m: float                # resolved
    ortho_res_m: float              # resolved
    rules: Any                      # io/export_raster.DsmParams, resolved for the map's cell
    contour_interval_m: float
    centres: Any                    # (K, 3) camera centres, map ENU
    cloud: Any                      # io/export_cloud.GeoCloud: the cells min_pairs stereo pairs measured, and
                                    # those one pair measured where none of those is near (covering_clouds)
    res: ExportResult
    steps: Any                      # io/progress.Steps
    writers: Writers
    say: Callable[[str], None] | None = None
    fewer: Any = None               # GeoCloud of the other cells fewer pairs measured (they check the DSM); None: min_pairs 1
    failed: dict = field(default_factory=dict)   # product -> (why it was not written, errno)
    made: dict = field(default_factory=dict)     # intermediate name -> result

    def need(self, name: str):
        """The intermediate result `name` (INTERMEDIATE_STEPS), made the first time it is needed."""
        if name not in self.made:
            step = INTERMEDIATE_STEPS[name]
            make = {'classes': self._classes, 'surface': self._surface, 'dtm': self._dtm}[name]
            if step is not None:
                self.steps.start(step)
            self.made[name] = make()
        return self.made[name]

    def surface(self):
        return self.need('surface')

    def dtm(self):
        return self.need('dtm')

    def _classes(self) -> dict:
        from photogram_ros.io.export_cloud import classify_cloud
        c = classify_cloud(self.cloud)
        self.res.notes += c['notes']
        self.res.classes = {'ground': c['counts'].get(2, 0), 'building': c['counts'].get(6, 0),
                            'unclassified': c['counts'].get(1, 0), 'buildings': c['buildings']}
        return self.res.classes

    def _surface(self):
        import numpy as np

        from photogram_ros.io.export_raster import surface_in_crs
        surf = surface_in_crs(self.fusion, self.origin, self.crs, self.heights, self.dsm_res_m, self.rules,
                              self.min_pairs, self.centres, (self.cloud, self.fewer))
        self.fewer = None     # read only by the DSM's check
        grid = surf.dsm
        self.res.dsm['valid_share'] = float(np.mean(grid.valid())) if grid.data.size else 0.0
        self.res.dsm['raster'] = surf.shares(np.ones(grid.shape, bool))
        if surf.camera_hull.any():
            self.res.dsm['camera_hull'] = surf.shares(surf.camera_hull)
        if surf.region.any():     # the cameras' footprint: what the oriented photos saw
            self.res.dsm['footprint'] = surf.shares(surf.region)
        check = surf.one_pair_check(surf.camera_hull if surf.camera_hull.any() else None)
        if check is not None:
            self.res.dsm['one_pair_check'] = check
        return surf

    def _dtm(self):
        import numpy as np

        from photogram_ros.core.dtm import dtm_from_points
        grid, cloud = self.surface().dsm, self.cloud
        dtm = dtm_from_points(cloud.x, cloud.y, cloud.z, grid, grid.valid(), weights=cloud.count, classes=cloud.classes)
        self.res.notes += [f'DTM: {n}' for n in dtm.notes]
        self.res.dtm = {'ground_points': dtm.ground_points, 'ground_cells_share': float(dtm.ground.mean()),
                        'valid_share': float(np.mean(dtm.raster.valid()))}
        return dtm

    def keep(self, key: str, path: Path, write) -> None:
        """The product `key` written whole at `path` by write(tmp), or its failure recorded: a full disk
        stops this product, not the smaller ones after it."""
        try:
            self.res.files[key] = write_whole(path, write)
        except StorageError as exc:
            self.failed[key] = (str(exc), exc.errno)
        except Exception as exc:   # a writer that wraps the system's error (rasterio, laspy)
            cause = disk_full(exc)
            if cause is None:
                raise
            self.failed[key] = (f'{path}: not written: ' + ('the disk is full' if cause.errno == errno.ENOSPC else
                                                           cause.strerror or str(cause)), cause.errno)
        if key in self.failed and self.say is not None:
            self.say(f'export: {self.failed[key][0]}')


def plan(chosen: list[ExportProduct]) -> list[str]:
    """The progress steps of an export of the `chosen` products: the cloud, then each product's intermediate
    steps (once) and its own."""
    steps = ['cloud']
    for p in chosen:
        steps += [INTERMEDIATE_STEPS[n] for n in p.needs if INTERMEDIATE_STEPS[n] and INTERMEDIATE_STEPS[n] not in steps]
        steps += [p.step] if p.step else []
    return steps
