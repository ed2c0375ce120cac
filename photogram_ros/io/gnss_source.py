"""One interface for the recorded GNSS fix sources: `GnssSource`, a typing.Protocol (as rosbags types its storage
readers), which every reader of fixes from a file implements.

A source has a `name` (the file it reads) and gives its fixes once, in the file's order (`fixes()`: core/gnss_fix.py
`GnssFix`, NaN position where the receiver had none), and afterwards `counts()` (what was read and what was dropped, by
name). Implemented by io/mavlink_ingest.py `TlogFixes` (a MAVLink telemetry log: the fixes the MAVLink node would
publish on /gps/fix) and io/dataflash.py `DataflashFixes` (an ArduPilot .bin log's GPS/GPA messages);
`open_gnss_source` picks one by the file's content.
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


def open_gnss_source(path: str | Path) -> GnssSource:
    """The GnssSource of a recorded file: an ArduPilot dataflash log by its header, else a MAVLink telemetry log."""
    from photogram_ros.io.mavlink_link import file_kind
    if file_kind(str(path)) == 'dataflash':
        from photogram_ros.io.dataflash import DataflashFixes
        return DataflashFixes(path)
    from photogram_ros.io.mavlink_ingest import TlogFixes
    return TlogFixes(path)
