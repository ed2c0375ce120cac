"""ortho.tif: the orthomosaic (RGBA), the keyframes draped on the DSM with WGS84 ellipsoidal heights."""

from __future__ import annotations

from photogram_ros.io.products.job import ExportJob, ExportProduct


def write(job: ExportJob) -> None:
    from photogram_ros.core.raster import hull_mask
    from photogram_ros.io.export_cloud import enu_to_crs
    from photogram_ros.io.export_raster import StoredKeyframes, ortho_in_crs, surface_in_crs
    from photogram_ros.io.progress import Progress
    kfs = StoredKeyframes(job.store)
    job.res.keyframes = len(kfs)
    if not kfs:
        job.res.notes.append('no orthomosaic: the map folder holds no keyframes with images, poses and camera')
        return
    dsm_ell = job.surface().dsm if job.heights == 'ellipsoidal' else surface_in_crs(
        job.fusion, job.origin, job.crs, 'ellipsoidal', job.dsm_res_m, job.rules, job.min_pairs, job.centres).dsm
    draped = Progress('export: ortho', len(kfs), 'keyframes', job.say, clock=job.steps.clock)
    ortho = ortho_in_crs(dsm_ell, kfs, job.origin, job.crs, job.ortho_res_m, draped.callback())
    seen = ortho.data[..., 3] > 0
    job.res.ortho = {'res_m': ortho.res_m, 'valid_share': float(seen.mean())}
    if len(job.centres):
        ce, cn, _ = enu_to_crs(job.origin, job.centres, job.crs, job.heights)
        inside = hull_mask(ortho.shape, *ortho.to_pixel(ce, cn))
        if inside.any():
            job.res.ortho['camera_hull'] = {'cells': int(inside.sum()), 'valid': float(seen[inside].mean())}
    job.keep('ortho', job.out / 'ortho.tif', lambda tmp: job.writers.geotiff(ortho, tmp, job.crs, 'orthomosaic RGBA',
                                                                             rgba=True, heights=job.heights))


ORTHO = ExportProduct('ortho', 'ortho', ('surface',), write)
