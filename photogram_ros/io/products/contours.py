"""contours.gpkg: the DTM's contour lines every `contour_interval_m` (io/contours.py), when that is above 0."""

from __future__ import annotations

from photogram_ros.io.products.job import ExportJob, ExportProduct


def write(job: ExportJob) -> None:
    from photogram_ros.io.contours import contour_lines, write_contours_gpkg
    lines = contour_lines(job.dtm().raster, job.contour_interval_m)
    job.keep('contours', job.out / 'contours.gpkg', lambda tmp: write_contours_gpkg(
        lines, tmp, job.crs, f'DTM contours every {job.contour_interval_m:g} m, {job.heights} heights (elevation_m)'))
    job.res.dtm['contour_lines'] = len(lines)


CONTOURS = ExportProduct('contours', 'contours', ('surface', 'dtm'), write, by_name=False,
                         wanted=lambda job: job.contour_interval_m > 0)
