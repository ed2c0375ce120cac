"""Antenna trajectories from the post-processing programs surveyors use, recognised by their content.

One reader per format behind one small protocol (`TrajectoryReader`: `sniff` the file's first lines,
`read` it into the shared track type; io/trajectory_base.py, with the helpers the readers share), in a
registry (`READERS`; a new format is one more `register(...)`). The registry imports the readers; a
reader imports io/trajectory_base.py only.

`read_trajectory(path)` sniffs the file's first `HEAD_LINES` lines with every reader and reads it
with the one that is surest; it says which format it recognised (the track's first note) and refuses
a file no reader recognises, or two readers recognise equally well, with one line naming what each
format expects. The readers: io/rtklib_pos.py (RTKLIB, RTKLIB-demo5, Emlid Studio `.pos` and
`_events.pos`), io/trajectory_grafnav.py (NovAtel Waypoint GrafNav / Inertial Explorer ASCII
exports), io/trajectory_csv.py (Emlid Studio CSV, Trimble Business Center CSV, Leica Infinity CSV).

Every format's quality maps onto the one scale (`--accept fix|float|all` works on each; the tables
are in each reader and in docs/commands.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from photogram_ros.core.exposure_positions import Q_NAMES
from photogram_ros.errors import DataError
from photogram_ros.io.rtklib_pos import RtklibPosReader
from photogram_ros.io.trajectory_base import (HEAD_LINES, Trajectory, TrajectoryReader, datetime_to_gps_s, head_lines,
                                              per_axis_from_horizontal, quality_counts, read_lines, seconds_of_day,
                                              track_from_epochs)
from photogram_ros.io.trajectory_csv import EmlidCsvReader, LeicaInfinityCsvReader, TbcCsvReader
from photogram_ros.io.trajectory_grafnav import GrafNavReader

AMBIGUOUS_MARGIN = 0.05    # two readers this close in score: the file is ambiguous

READERS: list[TrajectoryReader] = []


def register(reader: TrajectoryReader) -> TrajectoryReader:
    """Add a reader to the registry (once per name)."""
    if not isinstance(reader, TrajectoryReader):
        raise TypeError(f'{reader!r} is not a TrajectoryReader (name, expects, sniff, read)')
    if all(r.name != reader.name for r in READERS):
        READERS.append(reader)
    return reader


for _reader in (RtklibPosReader(), EmlidCsvReader(), TbcCsvReader(), LeicaInfinityCsvReader(), GrafNavReader()):
    register(_reader)


def sniff(path: str | Path) -> tuple[TrajectoryReader, list[tuple[str, float]]]:
    """The reader surest of the file, and every reader's score (name, score) that recognised it."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f'{path} does not exist (give the post-processed trajectory: an RTKLIB/Emlid .pos, a GrafNav/'
                        'Inertial Explorer export, an Emlid, TBC or Leica Infinity CSV)')
    head = head_lines(path)
    scores = []
    for r in READERS:
        s = r.sniff(head)
        if s is not None and s > 0:
            scores.append((r, float(s)))
    scores.sort(key=lambda rs: -rs[1])
    expected = '; '.join(f'{r.name}: {r.expects}' for r in READERS)
    if not scores:
        raise DataError(f'{path}: not a trajectory format read here (expected one of {expected})')
    if len(scores) > 1 and scores[0][1] - scores[1][1] < AMBIGUOUS_MARGIN:
        a, b = scores[0][0], scores[1][0]
        raise DataError(f'{path}: ambiguous, it looks as much like {a.name} ({a.expects}) as like {b.name} '
                        f'({b.expects}); export it again with its program\'s own header')
    return scores[0][0], [(r.name, s) for r, s in scores]


def read_trajectory(path: str | Path, require_fix: bool = True) -> Trajectory:
    """The trajectory of a file of any registered format (see the module docstring); a file with no
    fixed epoch is refused unless `require_fix` is False."""
    path = Path(path)
    reader, _ = sniff(path)
    track = reader.read(path)
    if not track.format:
        track.format = reader.name
    if len(track) == 0:
        raise DataError(f'{path} ({reader.name}) holds no solution epoch')
    if require_fix and not np.any(track.q == 1):
        qs = track.q
        counts = ', '.join(f'{int(np.sum(qs == q))} {Q_NAMES.get(int(q), q)}' for q in sorted(set(qs.tolist())))
        raise DataError(f'{path}: no fixed solution in its {len(track)} epochs ({counts}; first at line '
                        f'{int(track.line[0])}): the post-processing did not resolve the ambiguities; check the base '
                        'station data and its position, or pass --accept-no-fix to use it anyway')
    track.notes.insert(0, f'{path.name}: read as {track.format} ({len(track)} epochs, times in {track.time_system})')
    return track



__all__ = ['AMBIGUOUS_MARGIN', 'HEAD_LINES', 'READERS', 'Trajectory', 'TrajectoryReader', 'datetime_to_gps_s',
           'head_lines', 'per_axis_from_horizontal', 'quality_counts', 'read_lines', 'read_trajectory', 'register',
           'seconds_of_day', 'sniff', 'track_from_epochs']
