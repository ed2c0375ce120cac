"""photogram-ros fixes: every GNSS fix of a flight log or live link, exactly as mavlink_node publishes it."""

from __future__ import annotations

import sys

from photogram_ros.io.fix_rows import RowWriter, fix_row, navsat_row

HELP = 'print the GNSS fixes of a .tlog, dataflash .bin, bag or live MAVLink link as CSV, GeoJSON or JSON lines'

def add_arguments(p) -> None:
    p.add_argument('source', help='a .tlog, an ArduPilot .bin, a bag (raw MAVLink on --topic, else its NavSatFix '
                                  'topics; rosbag2 folder, .db3, .mcap or ROS 1 .bag) or a link '
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
    p.add_argument('--events', action='store_true',
                   help='print the camera exposures instead of the fixes: CAM/TRIG of a .bin, CAMERA_FEEDBACK / '
                        'CAMERA_TRIGGER / CAMERA_IMAGE_CAPTURED of a .tlog, or the lines of a DJI Timestamp.MRK '
                        '(GPS week and seconds, UTC, the position the log wrote, the attitude)')
    p.add_argument('--event-type', default='auto', help='with --events: CAM or TRIG (.bin); CAMERA_FEEDBACK, '
                                                        'CAMERA_TRIGGER or CAMERA_IMAGE_CAPTURED (.tlog)')
    p.add_argument('--topic', default='/mavlink/from_fcu', help='bag topic of raw MAVLink bytes (without it in the '
                                                             'bag, its sensor_msgs/NavSatFix topics are printed)')


class _Counted:
    """Decoded MAVLink messages passed through, counted (to tell "no MAVLink" from "no fixes")."""

    def __init__(self, pairs):
        self.pairs, self.n = pairs, 0

    def __iter__(self):
        for p in self.pairs:
            self.n += 1
            yield p


def iter_rows(a, state: dict):
    """Rows (dicts of COLUMNS) in publication order, from whichever input `a.source` names; `state`
    gets 'mavlink' (the counted decoded messages, for files and links) and 'bag' (its health lines)."""
    import os
    from photogram_ros.errors import MavlinkError
    from photogram_ros.io import mavlink as ml
    key = ml.signing_key(a.signing_key) if a.signing_key else None

    def events(pairs):
        ing = ml.Ingest(clock_source=a.clock_source)
        state['mavlink'] = counted = _Counted(pairs)
        state['ingest'] = ing
        for m, t in counted:
            for ev in ing.handle(m, t):
                if isinstance(ev, ml.FixEvent) and (ev.best or a.all_receivers):
                    if ev.fix.has_position or a.with_no_fix:
                        yield fix_row(ev.fix)

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
        raise MavlinkError(f'{src} does not exist (give a .tlog, .bin, bag folder or a link URL)')
    kind = ml.file_kind(src)
    if kind == 'dataflash':
        from photogram_ros.io.dataflash import read_dataflash_fixes
        fixes, _ = read_dataflash_fixes(src)
        for f in fixes:
            if f.has_position or a.with_no_fix:
                yield fix_row(f)
        return
    if kind == 'bag':
        yield from _bag_rows(a, src, key, events, state)
        return
    stream = ml.MavlinkStream(secret_key=key, sysid=a.sysid, compid=a.compid, record_gap=8)
    messages, _ = ml.read_tlog(src, stream)
    if not messages:
        raise MavlinkError(f'{src} holds no MAVLink: not one packet decoded from its {os.path.getsize(src)} bytes '
                           '(give a .tlog, an ArduPilot .bin, a bag or a link URL)')
    yield from events(messages)


def _bag_rows(a, src: str, key, events, state: dict):
    """A bag: its raw MAVLink topic decoded, else its NavSatFix topics as they are."""
    from photogram_ros.errors import MavlinkError
    from photogram_ros.io import mavlink as ml
    from photogram_ros.io.bag import BagReader, deserialize, messages_from_bag
    with BagReader(src) as bag:
        topics = bag.topics()
        try:
            if a.topic in topics:
                stream = ml.MavlinkStream(secret_key=key, sysid=a.sysid, compid=a.compid)
                yield from events(messages_from_bag(bag, stream, a.topic))
                if state['mavlink'].n == 0:
                    raise MavlinkError(f'{src}: {a.topic} holds no MAVLink (not one packet decoded)')
                return
            navsat = sorted(t for t, i in topics.items() if i.msgtype.split('/')[-1] == 'NavSatFix')
            if a.topic != DEFAULT_TOPIC or not navsat:
                raise MavlinkError(f'{src} has no {a.topic} (raw MAVLink) and no NavSatFix topic; it has '
                                   f'{sorted(topics)}')
            for m in bag.messages(navsat):
                row = navsat_row(deserialize(m.msgtype, m.data), m.topic)
                if row['status'] >= 0 or a.with_no_fix:
                    yield row
        finally:
            state['bag'] = bag.health()
            state['bag_damaged'] = bag.damaged


DEFAULT_TOPIC = '/mavlink/from_fcu'


EVENT_COLUMNS = ('seq', 'source', 'gps_week', 'gps_seconds', 't_unix_s', 'utc', 'lat_deg', 'lon_deg', 'alt_msl_m',
                 'roll_deg', 'pitch_deg', 'yaw_deg')


def _event_rows(a):
    from photogram_ros.core.exposure_positions import gps_s_to_utc_unix, gps_s_to_week_tow
    from photogram_ros.io.camera_events import read_events
    from photogram_ros.io.fix_rows import utc_text
    notes: list[str] = []
    events = read_events(a.source, a.event_type, notes)
    for note in notes:
        print(f'note: {note}', file=sys.stderr)
    for ev in events:
        week, tow = gps_s_to_week_tow(ev.t_gps_s)
        unix = gps_s_to_utc_unix(ev.t_gps_s)
        llh = ev.logged_llh or (None, None, None)
        rpy = ev.rpy_deg or (None, None, None)
        yield {'seq': ev.seq, 'source': ev.where, 'gps_week': week, 'gps_seconds': round(tow, 6),
               't_unix_s': round(unix, 6), 'utc': utc_text(unix), 'lat_deg': llh[0], 'lon_deg': llh[1],
               'alt_msl_m': llh[2], 'roll_deg': rpy[0], 'pitch_deg': rpy[1], 'yaw_deg': rpy[2]}


def _print_events(a) -> int:
    import json
    import math
    import sys
    n = 0
    rows = list(_event_rows(a))      # read first: a log without camera events is an error, not an empty table
    if a.format == 'csv':
        print(','.join(EVENT_COLUMNS))
    elif a.format == 'geojson':
        print('{"type": "FeatureCollection", "features": [')
    for row in rows:
        row = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}
        if a.format == 'csv':
            print(','.join('' if row[k] is None else (f'{row[k]:.9f}' if k in ('lat_deg', 'lon_deg') else str(row[k]))
                           for k in EVENT_COLUMNS))
        elif a.format == 'jsonl':
            print(json.dumps(row))
        else:
            geom = None if row['lat_deg'] is None else {'type': 'Point', 'coordinates': [
                row['lon_deg'], row['lat_deg'], row['alt_msl_m']]}
            print((',' if n else '') + json.dumps({'type': 'Feature', 'geometry': geom, 'properties': row}))
        n += 1
    if a.format == 'geojson':
        print(']}')
    print(f'{n} camera events', file=sys.stderr)
    return 0


def check_arguments(a) -> None:
    """The numbers argparse takes but a link cannot use: a ConfigError before anything is printed."""
    from photogram_ros.errors import ConfigError
    for opt, v, lo, hi in (('--sysid', a.sysid, 0, 255), ('--compid', a.compid, 0, 255),
                           ('--baud', a.baud, 300, 10_000_000)):
        if not lo <= v <= hi:
            raise ConfigError(f'{opt} {v}: choose {lo} to {hi}' + (' (0: any)' if opt != '--baud' else ''))
    if not 0 <= a.duration < float('inf'):
        raise ConfigError(f'--duration {a.duration:g}: seconds of a live link to read, 0 (until Ctrl-C) or more')


def run(a) -> int:
    """Exit status 0; 2 when the input holds no MAVLink (or no GNSS topic); 3 when the bag is damaged
    (the fixes it still holds are printed)."""
    import sys
    check_arguments(a)
    if getattr(a, 'events', False):
        try:
            return _print_events(a)
        except BrokenPipeError:
            return 0
    w = RowWriter(a.format, sys.stdout)
    state: dict = {}
    try:
        for row in iter_rows(a, state):
            w.write(row)
        w.close()
    except BrokenPipeError:     # `| head` closed the pipe: that is not an error
        return 0
    for line in state.get('bag', []):
        print(line, file=sys.stderr)
    ing = state.get('ingest')
    clock = [p for p in (ing.problems if ing is not None else []) if p.startswith('autopilot clock')]
    for p in dict.fromkeys(clock):
        print(f'note: {p}', file=sys.stderr)
    counted = state.get('mavlink')
    if counted is not None and counted.n == 0:
        print(f'{w.n} fixes: no MAVLink received', file=sys.stderr)
    else:
        print(f'{w.n} fixes', file=sys.stderr)
    return 3 if state.get('bag_damaged') else 0
