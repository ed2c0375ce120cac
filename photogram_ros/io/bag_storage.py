"""The storage files of a rosbag2, read directly, so that a damaged bag gives what it holds.

A drone that loses power leaves a bag cut short: a .db3 whose last pages are missing (and no
metadata.yaml), or an .mcap without its summary. rosbags refuses both whole. Here:

- `SqliteFile` reads a .db3 with Python's sqlite3. A sound file is read with one query in time
  order. A damaged one (SQLite reports "database disk image is malformed" for any query that meets
  a missing or garbled page) is read row by row: each message id is asked for on its own, so
  every row whose pages survive is found and the others are counted as lost. Message ids of a
  rosbag2 run from 1 without gaps, so metadata.yaml's count (or the largest id still readable)
  tells how many there were.
- A .db3 with a `-wal` or `-journal` beside it is a recording cut short in the middle of writing (a
  recorder in WAL mode, or in rollback mode mid-transaction): SQLite's own recovery is run on a copy
  (the bag is never changed), which gives every message up to the last commit.
- `scan_mcap` reads an .mcap record by record from its start, without the summary at its end;
  it stops at the first record cut short or garbled and says where.
- `read_metadata` reads metadata.yaml for what the recorder saw: the counts to compare with.
"""

from __future__ import annotations

import sqlite3
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

# Message ids are asked for in blocks of this many; a block that fails is asked for id by id.
_BLOCK = 256
# Without metadata.yaml or a readable largest id, ids are probed this far past the last one found.
_PROBE_MARGIN = 4096


@dataclass
class Metadata:
    """What metadata.yaml says the recorder wrote."""

    storage: str                              # 'sqlite3', 'mcap'
    files: list                               # relative paths of the storage files
    file_counts: dict                         # file name -> message count
    topics: dict                              # topic -> (msgtype, count, offered_qos_profiles)
    message_count: int
    start_ns: int
    duration_ns: int
    compression: str = ''
    ros_distro: str = ''                      # the ROS distro of the message definitions ('rosbags': unknown)


def read_metadata(folder: Path) -> tuple[Metadata | None, str]:
    """(metadata, '') or (None, why it cannot be used)."""
    import yaml
    path = folder / 'metadata.yaml'
    if not path.exists():
        return None, ('metadata.yaml is missing (a recording cut short by a power loss or a kill writes none): '
                      'nothing to compare the counts with')
    try:
        info = yaml.safe_load(path.read_text())['rosbag2_bagfile_information']
        topics = {}
        for t in info.get('topics_with_message_count') or []:
            md = t['topic_metadata']
            topics[md['name']] = (md['type'], int(t['message_count']), md.get('offered_qos_profiles', ''))
        files = [str(f) for f in info.get('relative_file_paths') or []]
        file_counts = {Path(f['path']).name: int(f['message_count']) for f in info.get('files') or []}
        return Metadata(str(info['storage_identifier']), files, file_counts, topics, int(info['message_count']),
                        int(info['starting_time']['nanoseconds_since_epoch']), int(info['duration']['nanoseconds']),
                        str(info.get('compression_mode') or '').lower().replace('none', ''),
                        str(info.get('ros_distro') or '')), ''
    except Exception as exc:   # YAML errors, missing keys, wrong types: all mean "unreadable"
        why = ' '.join(str(exc).split())[:160]
        return None, f'metadata.yaml is unreadable ({type(exc).__name__}: {why}): nothing to compare the counts with'


def _connect(path: Path) -> sqlite3.Connection:
    # immutable: no locks and no journal (read-only media, a file another process still writes);
    # writable_schema: SQLite then opens a file shorter than its header says instead of refusing it.
    con = sqlite3.connect(f'file:{path}?mode=ro&immutable=1', uri=True)
    con.execute('PRAGMA writable_schema = ON')
    return con


@dataclass
class SqliteFile:
    """One .db3 of a bag. `counts()` says what it holds, `rows()` yields it; `problems` what was lost."""

    path: Path
    expected: int | None = None                # its message count from metadata.yaml
    topics: dict = field(default_factory=dict)  # topic id -> (name, msgtype, offered_qos_profiles)
    damaged: bool = False
    problems: list = field(default_factory=list)
    _index: list | None = None                 # damaged: [(stamp_ns, id, topic_id)] of the readable rows

    def __post_init__(self):
        self.path = Path(self.path)
        self.name = self.path.name
        self.recovered = _recover_cut_short(self)
        con = _connect(self.path)
        try:
            cols = {r[1] for r in con.execute('PRAGMA table_info(topics)')}
            qos = 'offered_qos_profiles' if 'offered_qos_profiles' in cols else "''"
            for tid, name, mtype, q in con.execute(f'SELECT id, name, type, {qos} FROM topics'):
                self.topics[tid] = (name, mtype, q or '')
        except sqlite3.DatabaseError as exc:
            if 'no such table' in str(exc) and not (self.path.parent / 'metadata.yaml').exists():
                raise UnreadableStorage(f'{self.path.name} holds no tables and there is no metadata.yaml: a recording '
                                        'cut short (a kill or a power loss) as it started; nothing to read') from exc
            raise UnreadableStorage(f'{self.path.name}: its topics table is unreadable ({exc})') from exc
        finally:
            con.close()

    def page_note(self) -> str:
        """'the file ends at page 341 of 1135' for a file shorter than its header says, else ''."""
        try:
            with open(self.path, 'rb') as f:
                head = f.read(100)
            page = struct.unpack('>H', head[16:18])[0] or 65536
            pages = struct.unpack('>I', head[28:32])[0]
            have = self.path.stat().st_size // page
            return f'the file ends at page {have} of {pages} (cut short)' if 0 < have < pages else ''
        except (OSError, struct.error):
            return ''

    def counts(self) -> dict:
        """topic id -> messages it holds (readable rows, for a damaged file)."""
        if not self.damaged:
            con = _connect(self.path)
            try:
                return dict(con.execute('SELECT topic_id, count(*) FROM messages GROUP BY topic_id').fetchall())
            except sqlite3.DatabaseError as exc:
                self._mark_damaged(exc)
            finally:
                con.close()
        out: dict = {}
        for _, _, tid in self._readable_index():
            out[tid] = out.get(tid, 0) + 1
        return out

    def span_ns(self) -> tuple[int, int] | None:
        if not self.damaged:
            con = _connect(self.path)
            try:
                lo, hi = con.execute('SELECT min(timestamp), max(timestamp) FROM messages').fetchone()
                return None if lo is None else (int(lo), int(hi))
            except sqlite3.DatabaseError as exc:
                self._mark_damaged(exc)
            finally:
                con.close()
        idx = self._readable_index()
        return (idx[0][0], idx[-1][0]) if idx else None

    def _mark_damaged(self, exc) -> None:
        if not self.damaged:
            self.damaged = True
            note = self.page_note()
            self.problems.append(f'{self.path.name}: damaged database ({exc}{"; " + note if note else ""}); '
                                 'reading every row that is still readable')

    def _readable_index(self) -> list:
        """[(stamp_ns, id, topic_id)] of every row SQLite still finds, in time order."""
        if self._index is not None:
            return self._index
        con = _connect(self.path)
        found = []
        try:
            last = self.expected or 0
            try:
                last = max(last, int(con.execute('SELECT max(id) FROM messages').fetchone()[0] or 0))
                known_end = True
            except sqlite3.DatabaseError:
                known_end = self.expected is not None
            start, top = 1, last if known_end else last + _PROBE_MARGIN
            while start <= top:
                end = min(start + _BLOCK, top + 1)
                try:
                    block = con.execute('SELECT id, topic_id, timestamp FROM messages WHERE id >= ? AND id < ?',
                                        (start, end)).fetchall()
                except sqlite3.DatabaseError:
                    block = []
                    for i in range(start, end):
                        try:
                            block += con.execute('SELECT id, topic_id, timestamp FROM messages WHERE id = ?',
                                                 (i,)).fetchall()
                        except sqlite3.DatabaseError:
                            pass
                found += block
                if block and not known_end:
                    top = max(top, block[-1][0] + _PROBE_MARGIN)
                start = end
        finally:
            con.close()
        self._index = sorted((int(ts), int(i), int(tid)) for i, tid, ts in found)
        n = len(self._index)
        if self.expected is None:   # with metadata.yaml, BagReader says what was lost, topic by topic
            pages = self.page_note()
            self.problems.append(f'{self.path.name}: {n} messages readable; how many were lost is unknown '
                                 f'(no metadata.yaml{"; " + pages if pages else ""})')
        return self._index

    def rows(self, topic_ids: set, start_ns=None, stop_ns=None) -> Iterator[tuple]:
        """(stamp_ns, id, topic_id, data) in time order; damage met on the way switches to row by row."""
        last = (-1, -1)
        if not self.damaged:
            con = _connect(self.path)
            try:
                q = ('SELECT timestamp, id, topic_id, data FROM messages WHERE topic_id IN '
                     f'({",".join("?" * len(topic_ids))})')
                args = list(topic_ids)
                if start_ns is not None:
                    q, args = q + ' AND timestamp >= ?', args + [int(start_ns)]
                if stop_ns is not None:
                    q, args = q + ' AND timestamp < ?', args + [int(stop_ns)]
                for ts, i, tid, data in con.execute(q + ' ORDER BY timestamp, id', args):
                    last = (ts, i)
                    yield ts, i, tid, data
                return
            except sqlite3.DatabaseError as exc:
                self._mark_damaged(exc)
            finally:
                con.close()
        con = _connect(self.path)
        unreadable = 0
        try:
            for ts, i, tid in self._readable_index():
                if tid not in topic_ids or (ts, i) <= last or (start_ns is not None and ts < start_ns) \
                        or (stop_ns is not None and ts >= stop_ns):
                    continue
                try:
                    row = con.execute('SELECT data FROM messages WHERE id = ?', (i,)).fetchone()
                except sqlite3.DatabaseError:
                    unreadable += 1
                    continue
                if row is not None:
                    yield ts, i, tid, row[0]
        finally:
            con.close()
            if unreadable:
                self.problems.append(f'{self.path.name}: the data of {unreadable} messages is unreadable')


def _recover_cut_short(f: 'SqliteFile') -> bool:
    """A .db3 left with its -wal or hot -journal (a writer killed before it closed): let SQLite recover a
    copy (roll the WAL forward to its last commit, or roll the unfinished transaction back) and read that
    instead; the note says so. Returns whether it did."""
    import shutil
    import tempfile
    import weakref
    side = [f.path.with_name(f.path.name + s) for s in ('-wal', '-journal')]
    side = [p for p in side if p.exists() and p.stat().st_size > 0]
    if not side:
        return False
    tmp = Path(tempfile.mkdtemp(prefix='photogram_bag_'))
    weakref.finalize(f, shutil.rmtree, tmp, True)
    copy = tmp / f.path.name
    try:
        shutil.copyfile(f.path, copy)
        for p in side:
            shutil.copyfile(p, tmp / p.name)
        con = sqlite3.connect(copy)
        try:
            n = con.execute('SELECT count(*) FROM messages').fetchone()[0]
            con.execute('PRAGMA wal_checkpoint(TRUNCATE)')
            con.execute('PRAGMA journal_mode=DELETE')
        finally:
            con.close()
    except (OSError, sqlite3.DatabaseError) as exc:
        f.problems.append(f'{f.name}: cut short while it was written ({", ".join(p.name for p in side)} left '
                          f'beside it); SQLite could not recover it ({exc}): read as it is')
        return False
    f.path = copy
    f.problems.append(f'{f.name}: cut short while it was written ({", ".join(p.name for p in side)} left beside '
                      f'it, no clean close): {n} messages up to its last commit; what came after is lost')
    return True


class UnreadableStorage(Exception):
    """A storage file from which nothing at all can be read."""


# --- MCAP --------------------------------------------------------------------------------------

MCAP_MAGIC = b'\x89MCAP0\r\n'
_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_FOOTER = 0x03, 0x04, 0x05, 0x06, 0x02


class _Cut(Exception):
    pass


def _str(buf: bytes, pos: int) -> tuple[str, int]:
    n = struct.unpack_from('<I', buf, pos)[0]
    if pos + 4 + n > len(buf):
        raise _Cut('string runs past its record')
    return buf[pos + 4:pos + 4 + n].decode('utf-8', 'replace'), pos + 4 + n


def _decompress(data: bytes, compression: str, size: int) -> bytes:
    if compression == '':
        return data
    if compression == 'zstd':
        try:
            from compression import zstd
        except ImportError:
            from backports import zstd
        return zstd.decompress(data)
    if compression == 'lz4':
        from lz4.frame import decompress
        return decompress(data)
    raise _Cut(f'chunk compression {compression!r} is not supported')


@dataclass
class McapScan:
    """What a sequential read of an .mcap found: its channels, and where (and why) it stopped."""

    path: Path
    channels: dict = field(default_factory=dict)    # channel id -> (topic, msgtype, offered_qos_profiles)
    schemas: dict = field(default_factory=dict)     # schema id -> msgtype
    stopped: str = ''                               # why the read ended before the footer, '' if it reached it
    chunks_lost: int = 0
    compressions: set = field(default_factory=set)  # the chunks' compressions read ('' for uncompressed ones)

    def _records(self, buf: bytes, pos: int, end: int, top: bool) -> Iterator[tuple]:
        while pos < end:
            if pos + 9 > end:
                raise _Cut(f'a record header is cut short at byte {pos}')
            op, n = struct.unpack_from('<BQ', buf, pos)
            if pos + 9 + n > end:
                raise _Cut(f'a record of {n} bytes at byte {pos} runs past the end ({end} bytes)')
            body = buf[pos + 9:pos + 9 + n]
            pos += 9 + n
            if op == _OP_FOOTER and top:
                self._footer = True
                return
            yield op, body

    def _handle(self, op: int, body: bytes, start_ns, stop_ns) -> Iterator[tuple]:
        if op == _OP_SCHEMA:
            sid = struct.unpack_from('<H', body, 0)[0]
            self.schemas[sid] = _str(body, 2)[0]
        elif op == _OP_CHANNEL:
            cid, sid = struct.unpack_from('<HH', body, 0)
            topic, p = _str(body, 4)
            _, p = _str(body, p)            # message encoding (cdr)
            qos, meta_end = '', p + 4 + struct.unpack_from('<I', body, p)[0]
            p += 4
            while p < meta_end:
                k, p = _str(body, p)
                v, p = _str(body, p)
                if k == 'offered_qos_profiles':
                    qos = v
            self.channels[cid] = (topic, self.schemas.get(sid, ''), qos)
        elif op == _OP_MESSAGE:
            cid, _, log_ns = struct.unpack_from('<HIQ', body, 0)
            if (start_ns is None or log_ns >= start_ns) and (stop_ns is None or log_ns < stop_ns):
                yield log_ns, cid, bytes(body[22:])

    def messages(self, start_ns=None, stop_ns=None) -> Iterator[tuple]:
        """(log_time_ns, channel id, data) of every message before the damage, chunk by chunk in
        file order and in time order within a chunk."""
        buf = self.path.read_bytes()
        self._footer = False
        if not buf.startswith(MCAP_MAGIC):
            self.stopped = ('an empty file (cut short before anything was written)' if not buf else
                            'not an MCAP file (no magic)')
            return
        try:
            for op, body in self._records(buf, len(MCAP_MAGIC), len(buf), True):
                if op != _OP_CHUNK:
                    yield from self._handle(op, body, start_ns, stop_ns)
                    continue
                size, crc = struct.unpack_from('<QI', body, 16)
                comp, p = _str(body, 28)
                self.compressions.add(comp)
                n = struct.unpack_from('<Q', body, p)[0]
                try:
                    raw = _decompress(body[p + 8:p + 8 + n], comp, size)
                    if len(raw) != size or (crc and zlib.crc32(raw) != crc):
                        raise _Cut('size or CRC mismatch')
                    inner = []
                    for op2, b2 in self._records(raw, 0, len(raw), False):
                        inner += list(self._handle(op2, b2, start_ns, stop_ns))
                except (_Cut, struct.error, ValueError, OSError, RuntimeError) as exc:
                    self.chunks_lost += 1   # a garbled chunk loses its messages, not the file's rest
                    self.stopped = self.stopped or f'a chunk is garbled ({exc})'
                    continue
                yield from sorted(inner, key=lambda m: m[0])
            if not self._footer:
                self.stopped = self.stopped or 'the file ends without its footer (cut short)'
        except (_Cut, struct.error) as exc:
            self.stopped = f'{exc}'
