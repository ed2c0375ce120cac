"""A product on disk whole or not at all: written under a temporary name, flushed, renamed; what an export
wrote (`ExportResult`) and the error that says which products a full disk stopped (`ProductsIncomplete`)."""

from __future__ import annotations

import errno
from dataclasses import dataclass, field
from pathlib import Path

from photogram_ros.errors import StorageError


@dataclass
class ExportResult:
    files: dict = field(default_factory=dict)    # product -> path
    points: int = 0
    keyframes: int = 0
    notes: list = field(default_factory=list)
    crs_with_heights: str = ''                  # the products' CRS, with its vertical part
    dsm: dict | None = None                     # the DSM rules used (DsmParams, resolved)
    classes: dict | None = None                 # LAS/PLY classes: ground, building, unclassified, buildings
    dtm: dict | None = None                     # ground points and cells of the DTM
    ortho: dict | None = None                   # the orthomosaic's cell size and cells holding a colour


class ProductsIncomplete(StorageError):
    """Some products could not be written (a full disk): the message names each path and why; `result`
    (ExportResult) holds the products that were written whole, and export.json says which failed."""

    def __init__(self, message: str, errno_: int | None, result: 'ExportResult'):
        super().__init__(message, errno_)
        self.result = result


def part_path(path: Path) -> Path:
    """The temporary name a product is written under until it is whole: '.cloud.part.laz' beside
    'cloud.laz' (the suffix kept: writers choose their format by it)."""
    return path.with_name(f'.{path.stem}.part{path.suffix}')


def write_whole(path: str | Path, write) -> Path:
    """`write(tmp)` writes the file under part_path(path); once it returned, the file is flushed to disk and
    renamed to `path`. A failure (a full disk) removes the partial file and raises a StorageError naming
    `path`: a product is on disk whole under its final name, or not at all."""
    import os
    path = Path(path)
    tmp = part_path(path)
    try:
        write(tmp)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        Path(str(tmp) + '.aux.xml').unlink(missing_ok=True)
        cause = disk_full(exc) or exc
        why = 'the disk is full' if cause.errno == errno.ENOSPC else (cause.strerror or str(cause))
        raise StorageError(f'{path}: not written: {why}', cause.errno) from exc
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def disk_full(exc: BaseException) -> OSError | None:
    """The OSError behind a writer's failure (rasterio and laspy wrap the system's error), else None."""
    seen = exc
    while seen is not None:
        if 'No space left on device' in str(seen):
            return OSError(errno.ENOSPC, 'No space left on device')
        if isinstance(seen, OSError) and seen.errno is not None:
            return seen
        seen = seen.__cause__ or seen.__context__
    return None
