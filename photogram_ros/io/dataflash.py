"""GNSS fixes from an ArduPilot dataflash log (.bin): GPS + GPA messages, read with pymavlink's DFReader.

GPS carries the position (degrees, MSL altitude in m), the fix status and the GPS week time of the
fix; GPA, logged with the same TimeUS, carries the receiver's own accuracy (HAcc/VAcc, 1-sigma m),
VDOP and, in recent firmware, its geoid undulation `Und` (height of the WGS84 ellipsoid above MSL,
so the receiver's own ellipsoidal height is Alt - Und). Fixes logged before the receiver knew GPS
time are stamped through a boot-time fit of the other fixes.
"""

from __future__ import annotations

import math
from collections import Counter

from photogram_ros.core import gnss_fix as gf
from photogram_ros.core.timesync import BootClock
from photogram_ros.errors import MavlinkError

GPS_EPOCH_UNIX_S = 315964800
GPS_LEAP_S = 18          # GPS - UTC since 2017-01-01


def gps_to_unix_s(week: int, ms_of_week: int) -> float:
    return GPS_EPOCH_UNIX_S + week * 604800 + ms_of_week * 1e-3 - GPS_LEAP_S


def _raw_from(gps, gpa) -> gf.RawGnss:
    g = lambda m, k, d=0.0: getattr(m, k, d) if m is not None else d  # noqa: E731
    und = g(gpa, 'Und', 0.0)
    alt_ell_mm = int(round((gps.Alt - und) * 1000)) if und and math.isfinite(und) else 0
    vdop = g(gpa, 'VDop', 0.0)
    return gf.RawGnss(receiver=int(getattr(gps, 'I', 0)), time_usec=int(gps.TimeUS), fix_type=int(gps.Status),
                      lat_e7=int(round(gps.Lat * 1e7)), lon_e7=int(round(gps.Lng * 1e7)),
                      alt_msl_mm=int(round(gps.Alt * 1000)), alt_ellipsoid_mm=alt_ell_mm,
                      eph=int(round(gps.HDop * 100)) if gps.HDop > 0 else gf.UINT16_UNKNOWN,
                      epv=int(round(vdop * 100)) if vdop > 0 else gf.UINT16_UNKNOWN,
                      h_acc_mm=int(round(g(gpa, 'HAcc') * 1000)), v_acc_mm=int(round(g(gpa, 'VAcc') * 1000)),
                      sats=int(gps.NSats), source=f'dataflash GPS[{int(getattr(gps, "I", 0))}]')


def read_dataflash_fixes(path, error_model: gf.ErrorModel | None = None):
    """Every GPS message of a .bin log as a core.gnss_fix.GnssFix (NaN position without a fix); returns (fixes, counts)."""
    from pymavlink import DFReader
    try:
        log = DFReader.DFReader_binary(str(path))
    except Exception as exc:     # DFReader raises assorted errors on foreign files
        raise MavlinkError(f'{path} is not a readable ArduPilot dataflash log: {exc}') from exc
    counts = Counter()
    rows = []                    # [gps, gpa]
    pending_gps = {}
    while True:
        try:
            m = log.recv_match(type=['GPS', 'GPA'])
        except Exception as exc:
            counts['read_errors'] += 1
            counts['stopped_at_damage'] += 1
            _ = exc
            break
        if m is None:
            break
        t = m.get_type()
        counts[t] += 1
        key = (int(getattr(m, 'I', 0)), int(m.TimeUS))
        if t == 'GPS':
            row = [m, None]
            rows.append(row)
            pending_gps[key] = row
        else:
            row = pending_gps.pop(key, None)
            if row is not None:
                row[1] = m
    clock = BootClock()
    for gps, _ in rows:
        if gps.GWk > 0:
            clock.add_system_time(int(gps.TimeUS // 1000), int(gps_to_unix_s(gps.GWk, gps.GMS) * 1e6))
    fixes = []
    for gps, gpa in rows:
        if gps.GWk > 0:
            t = gps_to_unix_s(gps.GWk, gps.GMS)
        else:
            t = clock.to_time(gps.TimeUS * 1e-6)
            if t is None:
                counts['fix_without_time'] += 1
                continue
        res = gf.make_fix(_raw_from(gps, gpa), t, error_model)
        if res.fix is None:
            counts['fix_rejected'] += 1
            continue
        fixes.append(res.fix)
    return fixes, counts


class DataflashFixes:
    """An ArduPilot dataflash log as a GnssSource (io/gnss_source.py): `read_dataflash_fixes`'s fixes and counts."""

    def __init__(self, path, error_model: gf.ErrorModel | None = None):
        self.name = str(path)
        self.error_model = error_model
        self._counts: dict = {}

    def fixes(self):
        fixes, counts = read_dataflash_fixes(self.name, self.error_model)
        self._counts = dict(counts)
        yield from fixes

    def counts(self) -> dict:
        return dict(self._counts)
