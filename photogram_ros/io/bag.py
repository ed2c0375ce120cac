"""rosbag2 reading and writing (sqlite3 and MCAP) through the `rosbags` library.

Messages travel as CDR bytes, exactly as rosbag2 stores them and rclpy publishes them, so replay
needs no deserialization. Damage is reported, not hidden: a truncated or corrupt bag yields every
message before the damage and then records what went wrong in `BagReader.errors`.
"""

from __future__ import annotations

import importlib
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
    count: int


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


class BagWriter:
    """Writes rclpy messages to a rosbag2 (sqlite3 by default, or MCAP)."""

    def __init__(self, path: str | Path, storage: str = 'sqlite3'):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f'{self.path} exists already: choose a new bag name or delete it')
        plugin = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}.get(storage)
        if plugin is None:
            raise BagError(f'unknown bag storage {storage!r}: use sqlite3 or mcap')
        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        self._writer = Writer(self.path, version=9, storage_plugin=plugin)
        self._connections = {}
        self.count = 0

    def __enter__(self) -> 'BagWriter':
        self._writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self._writer.close()

    def add_topic(self, topic: str, msgtype: str, msgdef: str | None = None) -> None:
        if topic in self._connections:
            return
        kwargs = {'typestore': self._typestore}
        if msgtype not in self._typestore.fielddefs:
            if msgdef is None:
                raise BagError(f'message type {msgtype!r} of topic {topic} is not in the ROS 2 Jazzy '
                               'type store and no definition was given')
            kwargs = {'msgdef': msgdef, 'rihs01': ''}
        self._connections[topic] = self._writer.add_connection(topic, msgtype, **kwargs)

    def write(self, topic: str, stamp_ns: int, msg) -> None:
        """Serialize an rclpy message and write it at `stamp_ns`."""
        self.add_topic(topic, msgtype_of(msg))
        self.write_raw(topic, stamp_ns, serialize(msg))

    def write_raw(self, topic: str, stamp_ns: int, data: bytes) -> None:
        if topic not in self._connections:
            raise BagError(f'topic {topic} has not been added to the bag')
        self._writer.write(self._connections[topic], int(stamp_ns), data)
        self.count += 1


class BagReader:
    """Reads a rosbag2 folder (or a bare .db3 / .mcap file) in recorded order.

    `messages()` yields what it can; damage (a truncated file, an unreadable row) ends the
    iteration and is described in `errors` instead of raising after partial output.
    """

    def __init__(self, path: str | Path):
        from rosbags.rosbag2 import Reader, ReaderError
        self.path = Path(path)
        self.errors: list[str] = []
        if not self.path.exists():
            raise BagError(f'{self.path} does not exist')
        try:
            self._reader = Reader(self.path)
            self._reader.open()
        except Exception as exc:  # ReaderError, or sqlite3/mcap errors on files that are not bags
            salvage = _SqliteSalvage.open(self.path)
            if salvage is None:
                kind = 'readable rosbag2' if isinstance(exc, ReaderError) else 'rosbag2 (sqlite3 or MCAP)'
                raise BagError(f'{self.path} is not a {kind}: {exc}') from exc
            self._reader = salvage
            self.errors.append(f'{self.path.name}: damaged database ({exc}); reading what precedes the damage')

    def close(self) -> None:
        self._reader.close()

    def __enter__(self) -> 'BagReader':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def duration_ns(self) -> int:
        return int(self._reader.duration)

    @property
    def start_ns(self) -> int:
        return int(self._reader.start_time)

    def topics(self) -> dict[str, TopicInfo]:
        out = {}
        for c in self._reader.connections:
            prev = out.get(c.topic)
            out[c.topic] = TopicInfo(c.topic, c.msgtype, (prev.count if prev else 0) + c.msgcount)
        return out

    def messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None,
                 stop_ns: int | None = None) -> Iterator[BagMessage]:
        wanted = None if topics is None else set(topics)
        conns = [c for c in self._reader.connections if wanted is None or c.topic in wanted]
        if wanted is not None:
            missing = wanted - {c.topic for c in conns}
            if missing:
                raise BagError(f'topics not in {self.path.name}: {sorted(missing)}; '
                               f'it has {sorted(self.topics())}')
        if not conns:
            return
        try:
            for conn, stamp, data in self._reader.messages(connections=conns, start=start_ns, stop=stop_ns):
                yield BagMessage(conn.topic, conn.msgtype, int(stamp), bytes(data))
        except (sqlite3.DatabaseError, OSError, ValueError, KeyError, IndexError, EOFError) as exc:
            self.errors.append(f'{self.path.name}: bag damaged after the last good message '
                               f'({type(exc).__name__}: {exc})')
        except Exception as exc:  # rosbags raises its own types for broken MCAP chunks
            self.errors.append(f'{self.path.name}: bag damaged ({type(exc).__name__}: {exc})')


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


class _SqliteSalvage:
    """Reads a damaged rosbag2 sqlite3 file row by row in insertion order, up to the damage.

    rosbags refuses to open a malformed database; a real flight's bag cut off by a power loss or
    with a bad sector still holds everything written before the damage, so we read it directly.
    """

    def __init__(self, dbs: list[Path], connections: list, first_ns: int, last_ns: int):
        self._dbs = dbs
        self.connections = connections
        self.start_time = first_ns
        self.duration = max(last_ns - first_ns, 0)

    @classmethod
    def open(cls, path: Path) -> '_SqliteSalvage | None':
        dbs = sorted(path.glob('*.db3')) if path.is_dir() else [path] if path.suffix == '.db3' else []
        if not dbs:
            return None
        conns, first, last = {}, None, None
        for db in dbs:
            try:
                con = sqlite3.connect(f'file:{db}?mode=ro', uri=True)
                for tid, name, mtype in con.execute('SELECT id, name, type FROM topics'):
                    conns[(db, tid)] = _SalvageConnection(name, mtype, 0)
                for ts, in con.execute('SELECT timestamp FROM messages ORDER BY rowid LIMIT 1'):
                    first = ts if first is None else min(first, ts)
                con.close()
            except sqlite3.DatabaseError:
                continue
        if not conns or first is None:
            return None
        # The end is unknown until read; estimate it from metadata.yaml when it is readable.
        last = first
        meta = path / 'metadata.yaml' if path.is_dir() else None
        if meta is not None and meta.exists():
            try:
                import yaml
                info = yaml.safe_load(meta.read_text())['rosbag2_bagfile_information']
                last = first + int(info['duration']['nanoseconds'])
            except Exception:
                pass
        self = cls(dbs, list(conns.values()), first, last)
        self._by_id = conns
        return self

    def close(self) -> None:
        pass

    def messages(self, connections=(), start=None, stop=None):
        wanted = {id(c) for c in connections}
        for db in self._dbs:
            con = sqlite3.connect(f'file:{db}?mode=ro', uri=True)
            try:
                for tid, ts, data in con.execute('SELECT topic_id, timestamp, data FROM messages ORDER BY rowid'):
                    conn = self._by_id.get((db, tid))
                    if conn is None or (wanted and id(conn) not in wanted):
                        continue
                    if (start is not None and ts < start) or (stop is not None and ts >= stop):
                        continue
                    yield conn, ts, data
            finally:
                con.close()


@dataclass
class _SalvageConnection:
    topic: str
    msgtype: str
    msgcount: int
