"""The point clouds: cloud.las, cloud.laz (LAS 1.4, classified; io/export_cloud.write_las) and cloud.ply."""

from __future__ import annotations

from photogram_ros.io.products.job import ExportJob, ExportProduct


def _writer(key: str, write_with: str):
    def write(job: ExportJob) -> None:
        writer = getattr(job.writers, write_with)
        job.keep(key, job.out / f'cloud.{key}', lambda tmp: writer(job.cloud, tmp))
    return write


LAS = ExportProduct('las', 'LAS', ('classes',), _writer('las', 'las'))
LAZ = ExportProduct('laz', 'LAZ', ('classes',), _writer('laz', 'las'))
PLY = ExportProduct('ply', 'PLY', ('classes',), _writer('ply', 'ply'))
