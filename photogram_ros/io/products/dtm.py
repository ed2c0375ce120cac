"""dtm.tif: the bare ground (core/dtm.py: the cloud's ground class on the DSM's grid)."""

from __future__ import annotations

from photogram_ros.io.products.job import ExportJob, ExportProduct


def write(job: ExportJob) -> None:
    dtm = job.dtm()
    job.keep('dtm', job.out / 'dtm.tif', lambda tmp: job.writers.geotiff(
        dtm.raster, tmp, job.crs, f'DTM (bare ground, from the cloud\'s ground class), {job.heights} heights (m)',
        heights=job.heights))


DTM = ExportProduct('dtm', None, ('surface', 'dtm'), write)
