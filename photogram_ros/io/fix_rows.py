"""GNSS fixes as table rows (`photogram-ros fixes`): from MAVLink-decoded fixes or from recorded
NavSatFix messages, written as CSV, GeoJSON or JSON lines."""

from __future__ import annotations

COLUMNS = ('t_unix_s', 'utc', 'receiver', 'fix_type', 'fix_name', 'status', 'lat_deg', 'lon_deg', 'h_m',
           'var_e_m2', 'var_n_m2', 'var_u_m2', 'cov_type', 'height_source', 'sats', 'hdop', 'source')


def utc_text(t_s: float) -> str:
    from datetime import datetime, timezone
    try:
        return datetime.fromtimestamp(t_s, tz=timezone.utc).isoformat(timespec='milliseconds')
    except (ValueError, OverflowError, OSError):   # a time no calendar holds: said, not a traceback
        return ''

def fix_row(fix, source: str | None = None) -> dict:
    """A core.gnss_fix.GnssFix as a row of COLUMNS (with sysid, compid for a receiver's fix), `source` its
    source column (default: the fix's own). A NavSatFix's fix has no receiver, fix type, satellites or HDOP
    (''), and its status named as NavSatStatus names it."""
    import math
    from photogram_ros.core import gnss_fix as gf
    t = fix.t_s
    row = {'t_unix_s': t, 'utc': utc_text(t)}
    var = fix.var_enu_m2
    if fix.native_scale == 'GPS_FIX_TYPE':
        row.update({'receiver': fix.receiver, 'fix_type': fix.fix_type, 'fix_name': gf.fix_name(fix.fix_type)})
    else:
        row.update({'receiver': '', 'fix_type': '',
                    'fix_name': {-1: 'NO_FIX', 0: 'FIX', 1: 'SBAS_FIX', 2: 'GBAS_FIX'}.get(fix.status, str(fix.status))})
    row.update({'status': fix.status, 'lat_deg': fix.lat_deg, 'lon_deg': fix.lon_deg, 'h_m': fix.h_m,
                'var_e_m2': var[0], 'var_n_m2': var[1], 'var_u_m2': var[2], 'cov_type': fix.cov_type,
                'height_source': fix.height_source})
    if fix.native_scale == 'GPS_FIX_TYPE':
        row.update({'sats': fix.sats, 'hdop': fix.hdop, 'sysid': fix.sysid, 'compid': fix.compid})
    else:
        row.update({'sats': '', 'hdop': ''})
    row['source'] = fix.source if source is None else source
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}


def navsat_row(msg, topic: str) -> dict:
    """A recorded sensor_msgs/NavSatFix (e.g. mavros's global_position/raw/fix) as a row."""
    from photogram_ros import msgs
    return fix_row(msgs.gnss_fix_from_navsatfix(msg), topic)


class RowWriter:
    """Rows to CSV, GeoJSON or JSON lines, flushed row by row (a live link shows them as they come)."""

    def __init__(self, fmt: str, out):
        self.fmt, self.out, self.n = fmt, out, 0
        if fmt == 'csv':
            import csv
            self._csv = csv.DictWriter(out, fieldnames=COLUMNS, extrasaction='ignore', lineterminator='\n')
            self._csv.writeheader()
        elif fmt == 'geojson':
            out.write('{"type": "FeatureCollection", "features": [\n')
    def write(self, rec: dict) -> None:
        import json
        if self.fmt == 'csv':
            self._csv.writerow({k: ('' if rec.get(k) is None else (f'{rec[k]:.9f}' if k in ('lat_deg', 'lon_deg')
                                                                  else rec[k])) for k in COLUMNS})
        elif self.fmt == 'jsonl':
            self.out.write(json.dumps(rec) + '\n')
        else:
            geom = None if rec['lat_deg'] is None else {'type': 'Point',
                                                        'coordinates': [rec['lon_deg'], rec['lat_deg'], rec['h_m']]}
            props = {k: v for k, v in rec.items() if k not in ('lat_deg', 'lon_deg')}
            self.out.write((',\n' if self.n else '') + json.dumps({'type': 'Feature', 'geometry': geom,
                                                                   'properties': props}))
        self.n += 1
        self.out.flush()
    def close(self) -> None:
        if self.fmt == 'geojson':
            self.out.write('\n]}\n')
