"""A minimal ArduPilot dataflash (.bin) writer: FMT records and CAM messages, as ArduPilot 4.x logs them.

Each record is 0xA3 0x95, the message type, then the fields packed little-endian as the FMT record of
that type says. CAM: TimeUS (boot time, us), I (instance), Img (image number), GPSTime (ms of the GPS
week), GPSWeek, Lat/Lng (1e-7 deg), Alt (MSL, cm), RelAlt (cm), GPSAlt (cm), R/P/Y (cdeg; Y unsigned).
pymavlink's DFReader reads it back.
"""

from __future__ import annotations

import struct
from pathlib import Path

HEAD = b'\xa3\x95'
FMT_TYPE, CAM_TYPE = 128, 200
CAM_FORMAT, CAM_COLUMNS = 'QBHIHLLeeeccC', 'TimeUS,I,Img,GPSTime,GPSWeek,Lat,Lng,Alt,RelAlt,GPSAlt,R,P,Y'
CAM_STRUCT = '<QBHIHiiiiihhH'


def _fmt_record(msg_type: int, name: str, fmt: str, columns: str, length: int) -> bytes:
    return HEAD + bytes([FMT_TYPE]) + struct.pack('<BB4s16s64s', msg_type, length, name.encode(), fmt.encode(),
                                                  columns.encode())


def write_cam_log(path: str | Path, cams: list[dict]) -> None:
    """cams: dicts with boot_us, img, gps_week, gps_ms, lat_deg, lon_deg, alt_msl_m, rel_alt_m, roll_deg,
    pitch_deg, yaw_deg."""
    out = bytearray(_fmt_record(FMT_TYPE, 'FMT', 'BBnNZ', 'Type,Length,Name,Format,Columns', 89))
    out += _fmt_record(CAM_TYPE, 'CAM', CAM_FORMAT, CAM_COLUMNS, 3 + struct.calcsize(CAM_STRUCT))
    for c in cams:
        out += HEAD + bytes([CAM_TYPE]) + struct.pack(
            CAM_STRUCT, int(c['boot_us']), 0, int(c['img']), int(c['gps_ms']), int(c['gps_week']),
            int(round(c['lat_deg'] * 1e7)), int(round(c['lon_deg'] * 1e7)), int(round(c['alt_msl_m'] * 100)),
            int(round(c['rel_alt_m'] * 100)), int(round(c['alt_msl_m'] * 100)), int(round(c['roll_deg'] * 100)),
            int(round(c['pitch_deg'] * 100)), int(round((c['yaw_deg'] % 360.0) * 100)) % 36000)
    Path(path).write_bytes(bytes(out))
