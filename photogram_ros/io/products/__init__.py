"""The export products, one module each, in one registry (io/export.py `export_map` runs the chosen ones in
this order): clouds.py (cloud.las, cloud.laz, cloud.ply), dsm.py, dtm.py, contours.py (on a contour
interval), ortho.py. Each is an `ExportProduct` (io/products/job.py): its name, its progress step, the
intermediate results it needs (the cloud's classes, the DSM surface, the DTM: each made once) and its
`write(job)`. A new product is one module and one line here.
"""

from __future__ import annotations

from photogram_ros.io.products.clouds import LAS, LAZ, PLY
from photogram_ros.io.products.contours import CONTOURS
from photogram_ros.io.products.dsm import DSM
from photogram_ros.io.products.dtm import DTM
from photogram_ros.io.products.job import ExportJob, ExportProduct, Writers, plan
from photogram_ros.io.products.ortho import ORTHO

PRODUCTS: tuple[ExportProduct, ...] = (LAS, LAZ, PLY, DSM, DTM, CONTOURS, ORTHO)


def product_names() -> tuple[str, ...]:
    """The products asked for by name (--products), in the registry's order."""
    return tuple(p.key for p in PRODUCTS if p.by_name)


__all__ = ['PRODUCTS', 'ExportJob', 'ExportProduct', 'Writers', 'plan', 'product_names']
