"""rosbag2 reading and writing (sqlite3 and MCAP) through the `rosbags` library.

Messages travel as CDR bytes, exactly as rosbag2 stores them and rclpy publishes them, so replay
needs no deserialization. Damage is reported, not hidden: a truncated or corrupt bag yields every
message that is still readable (io/bag_storage.py reads the storage files directly) and
`BagReader.errors` says how many of how many were read, and what was lost.
"""

from __future__ import annotations

import heapq
import importlib
import re
import sqlite3
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Iterator

from photogram_ros.errors import BagError


@dataclass(frozen=True)
class BagMessage:
    topic: str
    msgtype: str          # 'sensor_msgs/msg/Image'
    stamp_ns: int         # receive time recorded in the bag
    data: bytes           # CDR, with encapsulation header


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    msgtype: str
    count: int                     # messages that can be read
    expected: int | None = None    # messages recorded, per metadata.yaml (None: no usable metadata.yaml)


@lru_cache(maxsize=None)
def msg_class(msgtype: str):
    """'sensor_msgs/msg/Image' (or 'sensor_msgs/Image') -> the rclpy message class."""
    parts = msgtype.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3:
        raise BagError(f'message type {msgtype!r} is not of the form package/msg/Type')
    pkg, kind, name = parts
    try:
        module = importlib.import_module(f'{pkg}.{kind}')
        return getattr(module, name)
    except (ImportError, AttributeError) as exc:
        raise BagError(f'unknown message type {msgtype!r}: its Python package {pkg!r} is not installed '
                       f'(pip install ros-jazzy-{pkg.replace("_", "-")})') from exc


def serialize(msg) -> bytes:
    from rclpy.serialization import serialize_message
    return serialize_message(msg)


def deserialize(msgtype: str, data: bytes):
    from rclpy.serialization import deserialize_message
    return deserialize_message(data, msg_class(msgtype))


def msgtype_of(msg) -> str:
    """rclpy message instance -> 'pkg/msg/Type'."""
    module = type(msg).__module__.split('.')
    return f'{module[0]}/msg/{type(msg).__name__}'


def bag_qos(profile):
    """An rclpy QoSProfile -> the rosbags Qos that rosbag2 records as a topic's offered_qos_profiles."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    def t(d):
        ns = int(d.nanoseconds)
        return QosTime(ns // 1_000_000_000, ns % 1_000_000_000)
    return Qos(QosHistory(int(profile.history)), int(profile.depth), QosReliability(int(profile.reliability)),
               QosDurability(int(profile.durability)), t(profile.deadline), t(profile.lifespan),
               QosLiveliness(int(profile.liveliness)), t(profile.liveliness_lease_duration),
               bool(profile.avoid_ros_namespace_conventions))


ROS_DISTRO = 'jazzy'          # the distro of the message definitions written (rosbags' ROS2_JAZZY type store)
MCAP_COMPRESSION = ('zstd', '')


def latched_qos(depth: int = 1):
    """The rosbags Qos of a latched topic (reliable, transient local: /tf_static, map/georeference), without rclpy."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    never = QosTime(9223372036, 854775807)      # rmw's infinite duration, as rosbag2 (Jazzy) records it
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, never, never,
               QosLiveliness.AUTOMATIC, never, False)


class BagWriter:
    """Writes rclpy messages to a rosbag2 (sqlite3 by default, or MCAP, ROS 2 Jazzy's default).

    MCAP chunks are zstd-compressed unless `compression=''` (rosbag2's default storage preset for MCAP
    records them uncompressed; `ros2 bag record --storage-preset-profile zstd_fast` as here). The bag's
    metadata (metadata.yaml and the MCAP's own rosbag2 record) names the ROS distro of the message
    definitions, ROS_DISTRO. Messages without an rclpy class (tf2_msgs is not among the PyPI wheels)
    are written from rosbags' type store (`write_typed`).

    `checkpoint_s` > 0 (a recorder): what was written is made durable at least that often, so that a
    recording cut short by a kill or a power loss keeps all but its last seconds: sqlite3 writes in WAL
    mode and commits and checkpoints; MCAP closes its pending chunk and syncs the file. 0 (the
    simulator, conversions): one transaction and 1 MB chunks, written whole at the end.
    """

    def __init__(self, path: str | Path, storage: str = 'sqlite3', checkpoint_s: float = 0.0,
                 compression: str = 'zstd'):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
        from rosbags.typesys import Stores, get_typestore
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f'{self.path} exists already: choose a new bag name or delete it')
        plugin = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}.get(storage)
        if plugin is None:
            raise BagError(f'unknown bag storage {storage!r}: use sqlite3 or mcap')
        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        if compression not in MCAP_COMPRESSION:
            raise BagError(f'unknown MCAP chunk compression {compression!r}: use zstd or none (\'\')')
        self._writer = Writer(self.path, version=9, storage_plugin=plugin)
        self.compression = compression if storage == 'mcap' else ''
        if self.compression:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._connections = {}
        self.count = 0
        self.storage = storage
        self.checkpoint_s = float(checkpoint_s)
        self._last_checkpoint = 0.0
        self._pending = 0        # messages written since the last checkpoint
        self.checkpoints = 0

    def __enter__(self) -> 'BagWriter':
        import time
        self._writer.open()
        if self.checkpoint_s > 0 and self.storage == 'sqlite3':
            # WAL: a transaction not yet committed never reaches the .db3, and a commit needs no
            # rewrite of the pages before it; checkpoint() copies the committed pages into the .db3.
            con = self._writer.storage.conn
            con.commit()
            con.execute('PRAGMA journal_mode=WAL')
            con.execute('PRAGMA synchronous=NORMAL')
        self._last_checkpoint = time.monotonic()
        return self

    def __exit__(self, *exc) -> None:
        storage_close = self._writer.storage.close

        def close_with_distro(version, metadata: str):
            return storage_close(version, _with_distro(metadata))
        self._writer.storage.close = close_with_distro
        self._writer.close()
        meta = self.path / 'metadata.yaml'
        meta.write_text(_with_distro(meta.read_text()))
        if self.checkpoint_s > 0 and self.storage == 'sqlite3':
            # A finished bag is a plain rollback-journal database, as every reader expects.
            db = next(self.path.glob('*.db3'), None)
            if db is not None:
                con = sqlite3.connect(db)
                try:
                    con.execute('PRAGMA journal_mode=DELETE')
                finally:
                    con.close()

    def checkpoint(self) -> None:
        """Make every message written so far durable in the storage file (see the class)."""
        import os
        import time
        storage = self._writer.storage
        if self.storage == 'sqlite3':
            storage.conn.commit()
            storage.conn.execute('PRAGMA wal_checkpoint(PASSIVE)')
        else:
            if storage.chunk.bio.tell():
                storage.close_chunk()
            storage.bio.flush()
            os.fsync(storage.bio.fileno())
        self._pending = 0
        self.checkpoints += 1
        self._last_checkpoint = time.monotonic()

    def checkpoint_if_due(self) -> bool:
        """checkpoint() when `checkpoint_s` has passed since the last one and something is pending."""
        import time
        if self.checkpoint_s > 0 and self._pending and time.monotonic() - self._last_checkpoint >= self.checkpoint_s:
            self.checkpoint()
            return True
        return False

    def add_topic(self, topic: str, msgtype: str, msgdef: str | None = None, qos=()) -> None:
        """`msgdef`: the .msg text of a type outside the ROS 2 Jazzy type store (px4_msgs: io/bag_px4.py).
        `qos`: the publishers' rclpy QoSProfiles (or rosbags Qos, e.g. latched_qos()), recorded as the topic's
        offered_qos_profiles (rosbag2 play offers the same ones again)."""
        if topic in self._connections:
            return
        from rosbags.interfaces import Qos
        kwargs = {'typestore': self._typestore,
                  'offered_qos_profiles': [q if isinstance(q, Qos) else bag_qos(q) for q in qos]}
        if msgtype not in self._typestore.fielddefs:
            if msgdef is None:
                raise BagError(f'message type {msgtype!r} of topic {topic} is not in the ROS 2 Jazzy '
                               'type store and no definition was given')
            # Registered (.msg text) so that the bag records its definition and type hash, as rosbag2 does.
            from rosbags.typesys import get_types_from_msg
            self._typestore.register(get_types_from_msg(msgdef, msgtype))
        self._connections[topic] = self._writer.add_connection(topic, msgtype, **kwargs)

    def write(self, topic: str, stamp_ns: int, msg) -> None:
        """Serialize an rclpy message and write it at `stamp_ns`."""
        self.add_topic(topic, msgtype_of(msg))
        self.write_raw(topic, stamp_ns, serialize(msg))

    def write_typed(self, topic: str, stamp_ns: int, msg) -> None:
        """Write a message built from the type store's classes (`self.types`), serialized by rosbags."""
        self.add_topic(topic, msg.__msgtype__)
        self.write_raw(topic, stamp_ns, bytes(self._typestore.serialize_cdr(msg, msg.__msgtype__)))

    @property
    def types(self):
        """The ROS 2 Jazzy type store (rosbags): `bag.types.types['tf2_msgs/msg/TFMessage']` is a message class."""
        return self._typestore

    def write_raw(self, topic: str, stamp_ns: int, data: bytes) -> None:
        if topic not in self._connections:
            raise BagError(f'topic {topic} has not been added to the bag')
        self._writer.write(self._connections[topic], int(stamp_ns), data)
        self.count += 1
        self._pending += 1
        if self.checkpoint_s > 0:
            self.checkpoint_if_due()


def _with_distro(metadata_yaml: str) -> str:
    """rosbags writes `ros_distro: rosbags` into the metadata; the distro of the definitions is ROS_DISTRO."""
    return re.sub(r'^(\s*)ros_distro: rosbags$', rf'\g<1>ros_distro: {ROS_DISTRO}', metadata_yaml, flags=re.M)


class BagReader:
    """Reads a rosbag2 folder (sqlite3 or MCAP, or a bare .db3 / .mcap file) or a ROS 1 .bag, in time order.

    Whatever the bag still holds is read, and what it lost is said: `topics()` counts the messages
    that are readable and `expected` what metadata.yaml says was recorded; `errors` describes every
    loss (damage found on opening, and damage met while reading: after a complete `messages()`
    iteration, the messages of its topics that could not be read); `warnings` what cannot be
    checked (no metadata.yaml). `health()` puts it in lines for a command to print. ROS 1 messages
    come out as ROS 2 CDR, like the rest.
    """

    def __init__(self, path: str | Path):
        from photogram_ros.io.bag_storage import read_metadata
        self.path = Path(path)
        self.errors: list[str] = []
        self.warnings: list[str] = []
        if not self.path.exists():
            raise BagError(f'{self.path} does not exist')
        self.metadata, why = read_metadata(self.path) if self.path.is_dir() else (None, '')
        if why:
            self.warnings.append(why)
        self._files, self._rosbags, self._scan, self._ros1 = [], None, None, None
        self.storage = self._open()
        self._infos = self._count()
        self._report_losses()
        if why and not self.errors and self.path.is_dir() and not any(i.count for i in self._infos.values()):
            # A recording ends with its metadata.yaml; one cut before its first commit holds nothing.
            self.errors.append(f'{self.path.name}: holds no message and no metadata.yaml: a recording cut short (a '
                               'kill or a power loss) before its first message was committed, or one that received '
                               'none')

    # --- opening ---------------------------------------------------------------------------------

    def _storage_files(self, suffix: str) -> list[Path]:
        if self.path.is_file():
            return [self.path] if self.path.suffix == suffix else []
        if self.metadata is not None and self.metadata.files:
            listed = [self.path / Path(f).name for f in self.metadata.files]
            missing = [p.name for p in listed if not p.exists()]
            note = f'{self.path.name}: storage files missing: {missing}'
            if missing and note not in self.errors:
                self.errors.append(note)
            listed = [p for p in listed if p.exists() and p.suffix == suffix]
            if listed:
                return listed
        return sorted(self.path.glob(f'*{suffix}'))

    def _open(self) -> str:
        from photogram_ros.io.bag_storage import SqliteFile, UnreadableStorage
        meta = self.metadata
        if self.path.is_file() and self.path.suffix == '.bag':
            self._ros1 = _Ros1(self.path)
            return 'ros1'
        compressed = meta is not None and bool(meta.compression)
        dbs = [] if compressed else self._storage_files('.db3')
        if dbs:
            why = []
            for db in dbs:
                expected = meta.file_counts.get(db.name) if meta is not None else None
                try:
                    self._files.append(SqliteFile(db, expected))
                except (UnreadableStorage, sqlite3.DatabaseError) as exc:
                    why.append(str(exc))
            if not self._files:
                raise BagError(f'{self.path} is not a readable rosbag2 (sqlite3): {"; ".join(why)}')
            self.errors += [f'{w}: its messages are lost' for w in why]
            return 'sqlite3'
        mcaps = self._storage_files('.mcap')
        if not mcaps and not compressed and not (self.path / 'metadata.yaml').exists() and self.path.is_dir():
            bags = sorted(self.path.glob('*.bag'))
            if bags:
                self._ros1 = _Ros1(bags[0])
                return 'ros1'
            raise BagError(f'{self.path} holds no bag: no metadata.yaml and no .db3, .mcap or .bag file')
        from rosbags.rosbag2 import Reader, ReaderError
        try:
            self._rosbags = Reader(self.path)
            self._rosbags.open()
            return meta.storage if meta is not None else 'mcap'
        except Exception as exc:   # ReaderError, or the storage's own errors on files that are not bags
            self._rosbags = None
            if not mcaps:
                kind = 'readable rosbag2' if isinstance(exc, ReaderError) else 'rosbag2 (sqlite3 or MCAP)'
                raise BagError(f'{self.path} is not a {kind}: {exc}') from exc
            from photogram_ros.io.bag_storage import McapScan
            self._scan = McapScan(mcaps[0])   # whether it is damaged, the scan (in _count) says
            self._scan_why = f'{exc}'
            return 'mcap'

    def _count(self) -> dict:
        """topic -> TopicInfo with the readable count (and the expected one from metadata.yaml)."""
        counts: dict = {}
        if self._files:
            for f in self._files:
                for tid, n in f.counts().items():
                    if tid in f.topics:
                        name, mtype, qos = f.topics[tid]
                        prev = counts.get(name, (mtype, 0, qos))
                        counts[name] = (mtype, prev[1] + n, qos)
                for name, mtype, qos in f.topics.values():
                    counts.setdefault(name, (mtype, 0, qos))
                self.errors += [e for e in f.problems if e not in self.errors]
        elif self._scan is not None:
            stamps = []
            for ts, cid, _ in self._scan.messages():
                stamps.append(ts)
                name, mtype, qos = self._scan.channels.get(cid, (f'channel {cid}', '', ''))
                prev = counts.get(name, (mtype, 0, qos))
                counts[name] = (mtype, prev[1] + 1, qos)
            for name, mtype, qos in self._scan.channels.values():
                counts.setdefault(name, (mtype, 0, qos))
            self._scan_span = (min(stamps), max(stamps)) if stamps else None
            if self._scan.stopped:
                # Without metadata.yaml the rosbag2 reader says only that: the scan says what the file holds.
                why = '' if 'metadata' in self._scan_why.lower() else f' ({self._scan_why})'
                self.errors.append(f'{self._scan.path.name}: damaged MCAP{why}: {self._scan.stopped}'
                                   + (f'; {self._scan.chunks_lost} chunks lost' if self._scan.chunks_lost else '')
                                   + '; read record by record up to there')
        elif self._ros1 is not None:
            counts = self._ros1.counts()
        else:
            for c in self._rosbags.connections:
                prev = counts.get(c.topic, (c.msgtype, 0, ''))
                counts[c.topic] = (c.msgtype, prev[1] + c.msgcount, '')
        expected = self.metadata.topics if self.metadata is not None else {}
        out = {t: TopicInfo(t, m, n, expected[t][1] if t in expected else None) for t, (m, n, _) in counts.items()}
        for t, (mtype, n, _) in expected.items():
            if t not in out:   # recorded, but its topic row is gone
                out[t] = TopicInfo(t, mtype, 0, n)
        return out

    def _report_losses(self) -> None:
        lost = {t: (i.count, i.expected) for t, i in self._infos.items()
                if i.expected is not None and i.count < i.expected}
        if lost:
            read = sum(i.count for i in self._infos.values())
            total = self.metadata.message_count if self.metadata is not None else read
            per = ', '.join(f'{t} {n} of {e}' for t, (n, e) in sorted(lost.items()))
            self.errors.append(f'{self.path.name}: {read} of {total} messages readable, {total - read} lost '
                               f'({per})')

    def close(self) -> None:
        if self._rosbags is not None:
            self._rosbags.close()
        if self._ros1 is not None:
            self._ros1.close()

    def __enter__(self) -> 'BagReader':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- what it holds ---------------------------------------------------------------------------

    @property
    def damaged(self) -> bool:
        return bool(self.errors)

    def _span(self) -> tuple[int, int] | None:
        if self._files:
            spans = [s for s in (f.span_ns() for f in self._files) if s is not None]
            return (min(s[0] for s in spans), max(s[1] for s in spans)) if spans else None
        if self._ros1 is not None:
            return self._ros1.span()
        if self._scan is not None:
            return self._scan_span
        if self._rosbags is not None and self._rosbags.message_count:
            return int(self._rosbags.start_time), int(self._rosbags.end_time) - 1
        if self.metadata is not None and self.metadata.message_count:
            return self.metadata.start_ns, self.metadata.start_ns + self.metadata.duration_ns
        return None

    @property
    def duration_ns(self) -> int:
        span = self._span()
        return 0 if span is None else span[1] - span[0]

    @property
    def start_ns(self) -> int:
        span = self._span()
        return 0 if span is None else span[0]

    def topics(self) -> dict[str, TopicInfo]:
        """topic -> TopicInfo; `count` is what messages() can yield, `expected` what was recorded."""
        return dict(self._infos)

    def message_definition(self, topic: str) -> str | None:
        """The .msg text the recording holds for `topic`'s type (its own definition, without those of the types it
        uses), or None when the bag does not say (read from its storage files, or not in .msg form)."""
        if self._rosbags is None:
            return None
        for c in self._rosbags.connections:
            d = getattr(c, 'msgdef', None)
            if c.topic == topic and d is not None and getattr(d.format, 'name', '') == 'MSG' and d.data.strip():
                return d.data.split('\n' + '=' * 80, 1)[0]
        return None

    def verify(self) -> None:
        """Read every message once, so that `topics()` counts what really reads back (a damaged file
        can list a row whose data is gone); worth it for a damaged bag, whose readable part is small."""
        got = dict.fromkeys(self._infos, 0)
        for m in self.messages():
            got[m.topic] += 1
        self._infos = {t: TopicInfo(i.topic, i.msgtype, got[t], i.expected) for t, i in self._infos.items()}

    def health(self) -> list[str]:
        """What a command should print about the bag's state: losses first, then what is unchecked."""
        return [f'bag damaged: {e}' for e in self.errors] + [f'warning: {w}' for w in self.warnings]

    def messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None,
                 stop_ns: int | None = None) -> Iterator[BagMessage]:
        wanted = sorted(self._infos) if topics is None else list(topics)
        missing = sorted(set(wanted) - set(self._infos))
        if missing:
            raise BagError(f'topics not in {self.path.name}: {missing}; it has {sorted(self._infos)}')
        got = dict.fromkeys(wanted, 0)
        for m in self._iterate(set(wanted), start_ns, stop_ns):
            got[m.topic] += 1
            yield m
        if start_ns is None and stop_ns is None:
            short = {t: (n, self._infos[t].count) for t, n in got.items() if n < self._infos[t].count}
            if short:
                per = ', '.join(f'{t} {n} of {c}' for t, (n, c) in sorted(short.items()))
                self.errors.append(f'{self.path.name}: damage met while reading: {sum(got.values())} of '
                                   f'{sum(self._infos[t].count for t in wanted)} messages read ({per})')

    def _iterate(self, wanted: set, start_ns, stop_ns) -> Iterator[BagMessage]:
        if self._files:
            streams = []
            for k, f in enumerate(self._files):
                ids = {tid for tid, (name, _, _) in f.topics.items() if name in wanted}
                if ids:
                    streams.append(((ts, k, i, tid, data) for ts, i, tid, data in f.rows(ids, start_ns, stop_ns)))
            for ts, k, _, tid, data in heapq.merge(*streams, key=lambda r: (r[0], r[1], r[2])):
                name, mtype, _ = self._files[k].topics[tid]
                yield BagMessage(name, mtype, int(ts), bytes(data))
            for f in self._files:
                self.errors += [e for e in f.problems if e not in self.errors]
            return
        if self._scan is not None:
            for ts, cid, data in self._scan.messages(start_ns, stop_ns):
                name, mtype, _ = self._scan.channels.get(cid, ('', '', ''))
                if name in wanted:
                    yield BagMessage(name, mtype, int(ts), data)
            return
        if self._ros1 is not None:
            yield from self._ros1.messages(wanted, start_ns, stop_ns)
            return
        conns = [c for c in self._rosbags.connections if c.topic in wanted]
        if not conns:
            return
        try:
            for conn, stamp, data in self._rosbags.messages(connections=conns, start=start_ns, stop=stop_ns):
                yield BagMessage(conn.topic, conn.msgtype, int(stamp), bytes(data))
        except Exception as exc:  # sqlite3/apsw, or rosbags's own types for broken MCAP chunks
            self.errors.append(f'{self.path.name}: bag damaged ({type(exc).__name__}: {exc})')


class _Ros1:
    """A ROS 1 .bag through rosbags, its messages converted to the ROS 2 types (CDR)."""

    def __init__(self, path: Path):
        from rosbags.rosbag1 import Reader
        from rosbags.typesys import Stores, get_typestore
        try:
            self._reader = Reader(path)
            self._reader.open()
        except Exception as exc:
            raise BagError(f'{path} is not a readable ROS 1 bag: {exc}') from exc
        self._ts1 = get_typestore(Stores.ROS1_NOETIC)
        self._ts2 = get_typestore(Stores.ROS2_JAZZY)
        from rosbags.typesys import get_types_from_msg
        for c in self._reader.connections:
            for ts in (self._ts1, self._ts2):
                if c.msgtype not in ts.fielddefs:
                    try:
                        ts.register(get_types_from_msg(c.msgdef.data, c.msgtype))
                    except Exception:
                        pass

    def counts(self) -> dict:
        out = {}
        for c in self._reader.connections:
            prev = out.get(c.topic, (c.msgtype, 0, ''))
            out[c.topic] = (c.msgtype, prev[1] + c.msgcount, '')
        return out

    def span(self):
        r = self._reader
        return (int(r.start_time), int(r.end_time)) if r.message_count else None

    def _to_ros2(self, value, msgtype: str):
        """A ROS 1 message object -> the ROS 2 type of the same name (fields by name; ROS 1's Header.seq goes)."""
        cls = self._ts2.types[msgtype]
        kwargs = {}
        for name, (kind, spec) in self._ts2.fielddefs[msgtype][1]:
            v = getattr(value, name)
            if kind.name == 'NAME':
                v = self._to_ros2(v, spec)
            elif kind.name in ('ARRAY', 'SEQUENCE') and spec[0][0].name == 'NAME':
                v = [self._to_ros2(x, spec[0][1]) for x in v]
            kwargs[name] = v
        return cls(**kwargs)

    def messages(self, wanted: set, start_ns, stop_ns) -> Iterator[BagMessage]:
        conns = [c for c in self._reader.connections if c.topic in wanted]
        for c, stamp, raw in self._reader.messages(connections=conns, start=start_ns, stop=stop_ns):
            msg = self._to_ros2(self._ts1.deserialize_ros1(raw, c.msgtype), c.msgtype)
            yield BagMessage(c.topic, c.msgtype, int(stamp), bytes(self._ts2.serialize_cdr(msg, c.msgtype)))

    def close(self) -> None:
        self._reader.close()


MAVLINK_TOPIC = '/mavlink/from_fcu'


def messages_from_bag(bag: BagReader, stream=None, topic: str = MAVLINK_TOPIC) -> Iterator[tuple]:
    """Raw MAVLink bytes recorded on `topic` (std_msgs/UInt8MultiArray) -> (decoded message, stamp_s).

    `stream` decodes the bytes (an io.mavlink.MavlinkStream, with the link's signing key if any; a
    plain one by default). stamp_s is the bag's receive time of the chunk that completed the message,
    in seconds; messages completed only by the end of the bytes come last with stamp_s None.
    """
    if stream is None:
        from photogram_ros.io.mavlink import MavlinkStream
        stream = MavlinkStream()
    for bm in bag.messages([topic]):
        data = bytes(deserialize(bm.msgtype, bm.data).data)
        for m in stream.feed(data):
            yield m, bm.stamp_ns * 1e-9
    for m in stream.feed(b'', final=True):
        yield m, None
