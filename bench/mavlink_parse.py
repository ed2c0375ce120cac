"""Messages per second through mavlink_node's parser vs a bare pymavlink recv_match loop, same logs, same run.

Prints one JSON line per log and method; `ratio` = time of the method / time of the bare loop
(target for the node's parser: <= 1.3). Best of `--repeat` runs each, to damp the shared machine.

The lines go through bench/machine.py's ResultWriter (commit, clean-tree flag, cores, load) into --out (default
/tmp/mavlink_parse.jsonl), and on stdout.

    .venv/bin/python bench/mavlink_parse.py [--repeat 3] [--out FILE.jsonl] [LOG ...]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import ResultWriter  # noqa: E402

DEFAULT_LOGS = [ROOT.parent / 'shared' / 'data' / 'mavlink' / 'phoenix_mission1_2018-09-17_16-44-06.tlog',
                ROOT.parent / 'shared' / 'data' / 'mavlink' / 'sitl_vtol.tlog',
                ROOT / 'bags' / 'sample_flight' / 'flight.tlog']


def bare_pymavlink(path) -> int:
    from pymavlink import mavutil
    conn = mavutil.mavlink_connection(str(path), robust_parsing=True)
    n = 0
    while conn.recv_match() is not None:
        n += 1
    conn.close()
    return n


def node_parser(path) -> int:
    """What the node does to a .tlog before publishing: framing, decoding, counters, record times."""
    from photogram_ros.io.mavlink import read_tlog
    msgs, _ = read_tlog(path)
    return len(msgs)


def node_stream_chunks(path) -> int:
    """Bag/UDP style: the same bytes fed as one packet per call (plus the tlog stamp)."""
    from photogram_ros.io.mavlink import MavlinkStream
    data = Path(path).read_bytes()
    s = MavlinkStream(record_gap=8)
    n = 0
    for i in range(0, len(data), 64):
        n += len(s.feed(data[i:i + 64]))
    n += len(s.feed(b'', final=True))
    return n


def node_full_ingest(path) -> int:
    """Parser plus everything the node computes before ROS messages: time sync, fixes, attitude, triggers."""
    from photogram_ros.io.mavlink import Ingest, read_tlog
    msgs, _ = read_tlog(path)
    ing = Ingest()
    for m, t in msgs:
        ing.handle(m, t)
    return len(msgs)


METHODS = {'pymavlink_recv_match': bare_pymavlink, 'node_parser': node_parser,
           'node_stream_64B_chunks': node_stream_chunks, 'node_parser_plus_ingest': node_full_ingest}


def best_time(fn, path, repeat: int):
    best, n = float('inf'), 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        n = fn(path)
        best = min(best, time.perf_counter() - t0)
    return best, n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('logs', nargs='*', type=Path, default=DEFAULT_LOGS)
    ap.add_argument('--repeat', type=int, default=3)
    ap.add_argument('--out', default=None, help='the result file (JSON lines; default /tmp/mavlink_parse.jsonl)')
    a = ap.parse_args()
    # What it runs: io/mavlink's parser and ingest (not the node, which only calls them).
    w = ResultWriter.for_bench(a.out, 'mavlink_parse', ['photogram_ros/io/mavlink.py', 'photogram_ros/io/mavlink_framing.py',
                                                        'photogram_ros/io/mavlink_ingest.py'])
    node_parser(a.logs[0]) if a.logs and a.logs[0].exists() else None   # warm imports and geoid cache
    node_full_ingest(a.logs[0]) if a.logs and a.logs[0].exists() else None
    for path in a.logs:
        if not path.exists():
            w.write({'log': str(path), 'skipped': 'missing'})
            continue
        base_s, base_n = best_time(bare_pymavlink, path, a.repeat)
        for name, fn in METHODS.items():
            t, n = (base_s, base_n) if name == 'pymavlink_recv_match' else best_time(fn, path, a.repeat)
            w.write({'log': path.name, 'method': name, 'messages': n, 'seconds': round(t, 4),
                     'msgs_per_s': round(n / t), 'ratio_vs_bare': round(t / base_s, 3), 'same_count': n == base_n})


if __name__ == '__main__':
    main()
