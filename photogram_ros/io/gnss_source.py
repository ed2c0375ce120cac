"""One interface for the recorded GNSS fix sources: `GnssSource`, a typing.Protocol (as rosbags types its storage
readers), which every reader of fixes from a file implements.

A source has a `name` (the file it reads) and gives its fixes once, in the file's order (`fixes()`: core/gnss_fix.py
`GnssFix`, NaN position where the receiver had none), and afterwards `counts()` (what was read and what was dropped, by
name). Implemented by io/mavlink_ingest.py `TlogFixes` (a MAVLink telemetry log: the fixes the MAVLink node would
publish on /gps/fix), io/dataflash.py `DataflashFixes` (an ArduPilot .bin log's GPS/GPA messages) and `TrackFixes`
here (a post-processed trajectory of io/trajectory_formats.py, or a DJI Timestamp.MRK's onboard RTK positions: their
epochs, core.exposure_positions.AntennaTrack.fixes); `open_gnss_source` picks one by the file's content.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, Protocol, runtime_checkable

from photogram_ros.core.gnss_fix import GnssFix


@runtime_checkable
class GnssSource(Protocol):
    """A recorded source of GNSS fixes (module docstring)."""

    name: str

    def fixes(self) -> Iterator[GnssFix]:
        """The source's fixes, in the file's order."""
        ...

    def counts(self) -> dict:
        """What the last `fixes()` read and dropped, by name (message types, rejected fixes, damage)."""
        ...


class TrackFixes:
    """A trajectory file (RTKLIB/Emlid .pos, GrafNav/Inertial Explorer export, Emlid/TBC/Leica CSV: `kind`
    'trajectory') or a DJI Timestamp.MRK (`kind` 'mrk': the onboard RTK antenna positions) as a GnssSource; counts:
    the epochs and how many of each quality."""

    def __init__(self, path, kind: str = 'trajectory'):
        self.name, self.kind = str(path), kind
        self._counts: dict = {}

    def track(self):
        if self.kind == 'mrk':
            from photogram_ros.io.camera_events import mrk_track, read_mrk
            return mrk_track(read_mrk(self.name), self.name)
        from photogram_ros.io.trajectory_formats import read_trajectory
        return read_trajectory(self.name, require_fix=False)

    def fixes(self) -> Iterator[GnssFix]:
        from photogram_ros.core.gnss_fix import Q_NAMES
        track = self.track()
        self._counts = {'epochs': len(track), 'format': track.format,
                        **{Q_NAMES.get(int(q), str(q)): int((track.q == q).sum()) for q in sorted(set(track.q.tolist()))}}
        yield from track.fixes()

    def counts(self) -> dict:
        return dict(self._counts)


def open_gnss_source(path: str | Path) -> GnssSource:
    """The GnssSource of a recorded file: an ArduPilot dataflash log by its header, a DJI Timestamp.MRK by its
    name or first line, a trajectory that a reader of io/trajectory_formats.py recognises, else a MAVLink telemetry
    log."""
    from photogram_ros.io.mavlink_link import file_kind
    if file_kind(str(path)) == 'dataflash':
        from photogram_ros.io.dataflash import DataflashFixes
        return DataflashFixes(path)
    from photogram_ros.io.camera_events import event_kind
    if event_kind(path) == 'mrk':
        return TrackFixes(path, 'mrk')
    from photogram_ros.io.trajectory_formats import READERS, head_lines
    head = head_lines(Path(path))
    if head and any((r.sniff(head) or 0) > 0 for r in READERS):
        return TrackFixes(path)
    from photogram_ros.io.mavlink_ingest import TlogFixes
    return TlogFixes(path)
