"""photogram-ros fixes: every GNSS fix of a flight log or live link, exactly as mavlink_node publishes it."""

from __future__ import annotations

HELP = 'print the GNSS fixes of a .tlog, dataflash .bin, bag or live MAVLink link as CSV, GeoJSON or JSON lines'

COLUMNS = ('t_unix_s', 'utc', 'receiver', 'fix_type', 'fix_name', 'status', 'lat_deg', 'lon_deg', 'h_m',
           'var_e_m2', 'var_n_m2', 'var_u_m2', 'cov_type', 'height_source', 'sats', 'hdop', 'source')


def add_arguments(p) -> None:
    p.add_argument('source', help='a .tlog, an ArduPilot .bin, a bag folder (topic /mavlink/from_fcu) or a link '
                                  '(udpin:0.0.0.0:14550, tcp:HOST:PORT, /dev/ttyUSB0)')
    p.add_argument('--format', choices=('csv', 'geojson', 'jsonl'), default='csv')
    p.add_argument('--all-receivers', action='store_true',
                   help='print every receiver\'s fixes (/gps/fix_N), not only the chosen one (/gps/fix)')
    p.add_argument('--with-no-fix', action='store_true', help='also print NO_FIX records (empty position)')
    p.add_argument('--clock-source', choices=('auto', 'system_time', 'arrival'), default='auto')
    p.add_argument('--baud', type=int, default=57600, help='serial baud rate')
    p.add_argument('--duration', type=float, default=0.0, help='live links: stop after this many seconds')
    p.add_argument('--signing-key', default='', help='MAVLink 2 signing secret (64 hex digits or passphrase)')
    p.add_argument('--sysid', type=int, default=0)
    p.add_argument('--compid', type=int, default=0)
    p.add_argument('--topic', default='/mavlink/from_fcu', help='bag topic of raw MAVLink bytes')


def _record(fix, source: str) -> dict:
    import math
    from datetime import datetime, timezone
    d = fix.as_dict()
    d['t_unix_s'] = d.pop('t_s')
    d['utc'] = datetime.fromtimestamp(fix.t_s, tz=timezone.utc).isoformat(timespec='milliseconds')
    d['source'] = source
    for k, v in list(d.items()):
        if isinstance(v, float) and not math.isfinite(v):
            d[k] = None
    return d


class _Writer:
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


def iter_fixes(a):
    """(Fix, source) in publication order, from whichever input `a.source` names."""
    import os
    from photogram_ros.io import mavlink as ml
    kw = dict(clock_source=a.clock_source)
    key = ml.signing_key(a.signing_key) if a.signing_key else None

    def events(pairs):
        ing = ml.Ingest(**kw)
        for m, t in pairs:
            for ev in ing.handle(m, t):
                if isinstance(ev, ml.FixEvent) and (ev.best or a.all_receivers):
                    yield ev.fix, ('GPS_RAW_INT', 'GPS2_RAW')[ev.fix.receiver] if ev.fix.receiver < 2 else 'GPS'

    src = a.source
    if ml.is_live_url(src):
        import time
        link = ml.Link(src, a.baud)
        stream = ml.MavlinkStream(secret_key=key, sysid=a.sysid, compid=a.compid)
        end = time.monotonic() + a.duration if a.duration > 0 else float('inf')

        def live():
            try:
                while time.monotonic() < end:
                    data = link.read(0.2)
                    now = time.time()
                    for m in stream.feed(data):
                        yield m, now
            finally:
                link.close()
        yield from events(live())
        return
    if not os.path.exists(src):
        from photogram_ros.errors import MavlinkError
        raise MavlinkError(f'{src} does not exist (give a .tlog, .bin, bag folder or a link URL)')
    kind = ml.file_kind(src)
    if kind == 'dataflash':
        from photogram_ros.io.dataflash import read_dataflash_fixes
        fixes, _ = read_dataflash_fixes(src)
        for f in fixes:
            yield f, f'dataflash GPS[{f.receiver}]'
        return
    if kind == 'bag':
        from photogram_ros.io.bag import BagReader, messages_from_bag
        stream = ml.MavlinkStream(secret_key=key, sysid=a.sysid, compid=a.compid)
        with BagReader(src) as bag:
            yield from events(messages_from_bag(bag, stream, a.topic))
        return
    stream = ml.MavlinkStream(secret_key=key, sysid=a.sysid, compid=a.compid, record_gap=8)
    messages, _ = ml.read_tlog(src, stream)
    yield from events(messages)


def run(a) -> int:
    import sys
    w = _Writer(a.format, sys.stdout)
    try:
        for fix, source in iter_fixes(a):
            if fix.has_position or a.with_no_fix:
                w.write(_record(fix, source))
        w.close()
    except BrokenPipeError:     # `| head` closed the pipe: that is not an error
        return 0
    print(f'{w.n} fixes', file=sys.stderr)
    return 0
