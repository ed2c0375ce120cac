"""MAVLink in: the public names of the three modules that do the work, importable from one place.

- `mavlink_framing`: `MavlinkStream` (bytes -> decoded messages, damage counted in `LinkStats`),
  MAVLink 2 signing (`signing_key`), `read_tlog`.
- `mavlink_link`: live links (`Link`, `is_live_url`) and `file_kind` of a recorded input.
- `mavlink_ingest`: `Ingest` (decoded messages -> `FixEvent` / `Attitude` / `Trigger` on the UNIX
  clock), `fixes_from_messages`, `raw_gnss`.
"""

from __future__ import annotations

from photogram_ros.io.mavlink_framing import STX_V1, STX_V2, LinkStats, MavlinkStream, read_tlog, signing_key
from photogram_ros.io.mavlink_ingest import Attitude, FixEvent, Ingest, Trigger, fixes_from_messages, raw_gnss
from photogram_ros.io.mavlink_link import Link, file_kind, is_live_url

__all__ = ['STX_V1', 'STX_V2', 'Attitude', 'FixEvent', 'Ingest', 'Link', 'LinkStats', 'MavlinkStream', 'Trigger',
           'file_kind', 'fixes_from_messages', 'is_live_url', 'raw_gnss', 'read_tlog', 'signing_key']
