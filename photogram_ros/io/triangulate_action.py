"""The `triangulate` action: a flight bag or a photo folder read into a block of keyframes and adjusted.

A bag's keyframes (io/bag_keyframes.py) with its control file's targets are adjusted as one block
(io/aerial_triangulation.py `adjust_block`); a folder of photos is matched (io/photo_block.py, on a runner of
io/dask_cluster.py) and adjusted as one block, or above `options.split.split_photos` geotagged photos by
split-merge (io/split_merge_action.py `split_merge_block`).

The heights of what it writes (`options.heights`, as `run`/`replay`/`export --heights` mean it): WGS84 ellipsoidal
as the block is adjusted, or orthometric above the EGM2008 geoid (core/geoid.py): poses.csv's z (the output CRS's
column; lat_deg/lon_deg/h_m stay WGS84 with ellipsoidal heights) and sparse.ply / sparse.las (the LAS CRS compound
with EGM2008 height) are written in that datum (io/aerial_triangulation.write_poses_and_cloud), and the report says
which.

Progress (io/progress.py) goes to `progress(text)`: each step as it starts, and the photos of the
features, the pairs of the matching and the photos added to the incremental adjustment counted with a
percent and an ETA; split-merge counts the sub-blocks done across the cluster.
"""

from __future__ import annotations

import time
from pathlib import Path


from photogram_ros.io.aerial_triangulation import TriangulateOptions, TriangulateResult, adjust_block
from photogram_ros.io.progress import Progress, Steps, sayer
from photogram_ros.io.split_merge_action import split_merge_block


# Labels and units of the photo block's jobs (io/photo_block.py's names for them).
PHOTO_JOBS = {'features': ('features', 'photos'), 'matching pairs': ('matching', 'pairs'),
              'matching more pairs for weakly linked photos': ('matching more pairs for weakly linked photos',
                                                               'pairs'),
             'sub-blocks': ('adjustment of the sub-blocks', 'sub-blocks')}


class CountedRunner:
    """A runner of io/dask_cluster.py whose named jobs report through io/progress.py (percent and ETA,
    to `say`; None: silent) instead of the runner's own lines."""

    def __init__(self, runner, say):
        self.runner, self.say = runner, say
        self.workers, self.where = runner.workers, runner.where

    def run(self, fn, calls, what=None, log=None, keep=False, on_result=None, extra=None) -> list:
        calls = list(calls)
        if what is None or self.say is None:
            return self.runner.run(fn, calls, None, None, keep, on_result)
        label, unit = PHOTO_JOBS.get(what, (what, 'pieces'))
        where = f' on {self.workers} workers{self.where}' if self.workers > 1 else ''
        prog = Progress(f'triangulate: {label}{where}', len(calls), unit, self.say)

        text = (lambda: extra().lstrip(', ')) if extra else ''   # extra(): ', 12 verified'

        def counted(k, result):
            if on_result is not None:
                on_result(k, result)
            prog.add(1, text)

        out = self.runner.run(fn, calls, None, None, keep, counted)
        prog.finish(text)
        return out

    def release(self, handles) -> None:
        self.runner.release(handles)


def triangulate(src: str | Path, out: str | Path, opt: TriangulateOptions, log=None, progress=True,
                bag: bool | None = None) -> TriangulateResult:
    """Aerial triangulation of the bag or photo folder `src` into the folder `out` (see the module
    docstring); log(text): warnings and what was read; progress: True (progress lines to `log`), False
    (none) or a say(text) function for them; bag: whether `src` is a flight bag (None: a folder with a
    metadata.yaml is one; a bag cut short has none, or is a bare storage file: say so)."""
    t0 = time.monotonic()
    src = Path(src)
    steps = Steps('triangulate', None, sayer(progress, log))
    if bag or (bag is None and (src / 'metadata.yaml').exists()):
        steps.start('reading the bag\'s keyframes')
        block, control_set = read_bag_block(src, opt, log)
        return adjust_block(block, out, opt, control_set, log, t0, steps=steps)
    return _triangulate_photos(src, out, opt, log, t0, steps)


def read_bag_block(src: Path, opt: TriangulateOptions, log=None):
    """(KeyframeBlock, ControlSet or None) of a flight bag: its keyframes (io/bag_keyframes.py) with the
    control file's targets found in them."""
    from photogram_ros.io.bag_keyframes import read_bag_keyframes
    from photogram_ros.io.control_file import read_control_file
    control_set = read_control_file(opt.targets, opt.check_names, opt.control_heights) if opt.targets else None
    block = read_bag_keyframes(src, opt.camera, control_set, log)
    if opt.exif_altitude:
        block.assumptions.append(f'--exif-altitude {opt.exif_altitude} ignored: a bag has no EXIF')
    if opt.workers != 1 or opt.scheduler:
        block.assumptions.append('--workers/--scheduler ignored: a bag\'s keyframes are read in this process')
    return block, control_set


def _triangulate_photos(src: Path, out, opt: TriangulateOptions, log, t0: float, steps: Steps) -> TriangulateResult:
    """A photo folder: features and matching on the runner (io/dask_cluster.py), then split-merge above
    opt.split.split_photos geotagged photos, else one block."""
    from photogram_ros.io.dask_cluster import open_runner
    from photogram_ros.io.photo_block import read_photo_block
    steps.start('features and matching of the photos')
    gcps = None
    if opt.gcp:
        from photogram_ros.io.control_file import read_gcp_list
        gcps = read_gcp_list(opt.gcp, opt.check_names)
    with open_runner(opt.workers, opt.scheduler, log) as runner:
        counted = CountedRunner(runner, steps.say)
        block = read_photo_block(src, opt.camera, opt.neighbours, opt.exif_altitude, opt.takeoff_h_m,
                                 opt.takeoff_heights, log, opt.matching, counted,
                                 gcps.central_origin() if gcps is not None else None)
        if opt.split is not None and len(block.records) > opt.split.split_photos:
            if any(r.fix is not None for r in block.records):
                return split_merge_block(block, out, opt, counted, log, t0, steps)
            block.assumptions.append('not split into sub-blocks: without positions the photos cannot be '
                                     'grouped, the block is adjusted whole')
    return adjust_block(block, out, opt, None, log, t0, steps=steps, gcps=gcps)
