"""dsm.tif: the DSM (band 1 heights, band 2 the stereo pairs that measured each cell: 1 for one pair, unconfirmed,
where no confirmed cell is near; 0 where interpolated)."""

from __future__ import annotations

from photogram_ros.io.products.job import ExportJob, ExportProduct


def write(job: ExportJob) -> None:
    import numpy as np

    from photogram_ros.core.raster import NODATA, Raster
    surf = job.surface()
    grid = surf.dsm
    job.keep('dsm', job.out / 'dsm.tif', lambda tmp: job.writers.geotiff(
        Raster(np.dstack([grid.data, surf.pairs]), grid.x0_m, grid.y1_m, grid.res_m, NODATA),
        tmp, job.crs, f'DSM, {job.heights} heights (m); band 2: stereo pairs that measured the cell (1: one '
        f'pair, unconfirmed), 0 where interpolated', heights=job.heights, band_names=('height_m', 'pairs')))


DSM = ExportProduct('dsm', None, ('surface',), write)
