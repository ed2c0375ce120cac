"""MAVLink framing: bytes in, decoded pymavlink messages out, with every kind of damage counted.

`MavlinkStream` frames MAVLink 1 and 2 packets out of arbitrary byte chunks and decodes them with
pymavlink (ardupilotmega dialect, which includes common). It does its own framing because
pymavlink's parser, after a false start byte inside damaged data, swallows the length that false
header claims, losing the good packets behind it; here a candidate that fails its CRC is skipped by
one byte only, so every intact packet after damage is still found. MAVLink 2 signing is checked
here too (`signing_key` makes the key); `read_tlog` reads a Mission Planner .tlog through it.
"""

from __future__ import annotations

import hashlib
import struct
from collections import Counter
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from photogram_ros.errors import ConfigError, MavlinkError

STX_V1, STX_V2 = 0xFE, 0xFD
_MIN_LEN = 8                      # shortest MAVLink 1 packet (empty payload)
_TLOG_STAMP_MIN_US = 946684800 * 10 ** 6      # 2000-01-01
_TLOG_STAMP_MAX_US = 4102444800 * 10 ** 6     # 2100-01-01


def signing_key(secret: str) -> bytes:
    """A 32-byte MAVLink 2 key: 64 hex digits as given, anything else hashed like MAVProxy's passphrase."""
    s = secret.strip()
    if len(s) == 64:
        try:
            return bytes.fromhex(s)
        except ValueError:
            pass
    return hashlib.sha256(s.encode('utf-8')).digest()


@dataclass
class LinkStats:
    bytes_in: int = 0
    packets: int = 0               # decoded (accepted) packets
    crc_errors: int = 0            # a packet started where one was due but failed its CRC / length check
    junk_bytes: int = 0            # bytes that belonged to no decodable packet
    unknown_msgid: int = 0
    signature_rejected: int = 0    # signed with a wrong key / replayed timestamp / wrong link id
    unsigned_rejected: int = 0     # unsigned while signing is required
    filtered: int = 0              # from another system or component
    seq_lost: int = 0              # sequence-number gaps (packets lost on the link)
    by_type: Counter = field(default_factory=Counter)

    def as_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != 'by_type'}
        d['by_type'] = dict(self.by_type)
        return d


class MavlinkStream:
    """Feed bytes in, get decoded pymavlink messages out; counts every kind of damage."""

    def __init__(self, secret_key: bytes | None = None, allow_unsigned: bool = False, link_id: int = -1,
                 sysid: int = 0, compid: int = 0, record_gap: int = 0):
        self.mav = mavlink2.MAVLink(None)
        self.mav.robust_parsing = False
        self.require_signed = secret_key is not None and not allow_unsigned
        self.link_id = link_id
        self.sysid, self.compid = sysid, compid
        self.record_gap = record_gap        # bytes between packets (8 in a .tlog: the timestamp)
        self._plain = self.mav
        if secret_key is not None:
            if len(secret_key) != 32:
                raise ConfigError('a MAVLink 2 signing key has 32 bytes (64 hex digits)')
            self.mav.signing.secret_key = secret_key
            # Unsigned packets go through a key-less decoder and are judged in _accept, so that they
            # are counted apart from bad signatures (pymavlink's unsigned callback also lets badly
            # signed packets through).
            self._plain = mavlink2.MAVLink(None)
            self._plain.robust_parsing = False
        self.stats = LinkStats()
        self._buf = bytearray()
        self._expect = record_gap           # offset in _buf where the next packet is due (-1: unknown)
        self._consumed = 0
        self._last_seq: dict = {}

    def feed(self, data: bytes, final: bool = False, with_offsets: bool = False) -> list:
        """Add bytes; return the messages completed by them (with their buffer offsets if asked).

        `final` says no more bytes follow (end of a file), so a truncated candidate at the end is
        given up instead of waited for.
        """
        self.stats.bytes_in += len(data)
        buf = self._buf
        if data:
            buf += data
        out = []
        i = 0
        n = len(buf)
        decode, decode_plain = self.mav.decode, self._plain.decode
        stats = self.stats
        while n - i >= _MIN_LEN:
            b0 = buf[i]
            if b0 != STX_V2 and b0 != STX_V1:
                e = self._expect
                if i < e < n and e - i <= self.record_gap and buf[e] in (STX_V1, STX_V2):
                    j = e           # the .tlog timestamp before a due packet
                else:
                    j = self._find_stx(buf, i, n)
                if j < 0:
                    self._junk(i, n)
                    i = n
                    break
                self._junk(i, j)
                i = j
                if n - i < _MIN_LEN:
                    break
                b0 = buf[i]
            if b0 == STX_V2:
                flags = buf[i + 2]
                if flags & 0xFE:
                    i = self._skip(i)
                    continue
                total = buf[i + 1] + (25 if flags & 1 else 12)
            else:
                total = buf[i + 1] + 8
            if i + total > n:
                if not final:
                    break
                i = self._skip(i)
                continue
            pkt = buf[i:i + total]
            try:
                m = decode(pkt) if b0 == STX_V1 or flags & 1 else decode_plain(pkt)
            except mavlink2.MAVError as exc:
                if 'signature' in str(exc.message):
                    stats.signature_rejected += 1
                    i += total
                    self._expect = i + self.record_gap
                else:
                    i = self._skip(i)
                continue
            except Exception:   # pymavlink raises bare struct/value errors on some malformed payloads
                i = self._skip(i)
                continue
            if isinstance(m, mavlink2.MAVLink_unknown):
                # An unknown id cannot be CRC-checked: trust its framing only where a packet was due,
                # another one follows it, and no good packet hides inside the span it claims.
                nxt = i + total + self.record_gap
                if i == self._expect and nxt + _MIN_LEN > n and not final:
                    break                       # decide when the next packet is here
                if i == self._expect and (nxt >= n or self._decodes_at(buf, nxt)) \
                        and not self._packet_inside(buf, i + 1, i + total):
                    stats.unknown_msgid += 1
                    i += total
                    self._expect = nxt
                else:
                    i = self._skip(i)
                continue
            start = i
            i += total
            self._expect = i + self.record_gap
            if not self._accept(m, pkt, flags if b0 == STX_V2 else 0):
                continue
            out.append((m, start) if with_offsets else m)
        if final and i < n:
            self._junk(i, n)
            i = n
        if i:
            del buf[:i]
            self._expect = self._expect - i if self._expect >= i else -1
            self._consumed += i
        return out

    @staticmethod
    def _find_stx(buf, i: int, n: int) -> int:
        # Bounded windows: an unbounded find of a start byte absent from the rest of a large buffer
        # would rescan it for every packet.
        while i < n:
            end = min(n, i + 1024)
            j2, j1 = buf.find(b'\xfd', i, end), buf.find(b'\xfe', i, end)
            if j2 >= 0 or j1 >= 0:
                return j1 if j2 < 0 else (j2 if j1 < 0 else min(j1, j2))
            i = end
        return -1

    def _decodes_at(self, buf, i: int) -> bool:
        """Whether a known, CRC-valid packet starts at buf[i] (checks the framing of an unknown one)."""
        b0 = buf[i]
        if b0 == STX_V2 and i + 3 <= len(buf) and not buf[i + 2] & 0xFE:
            total = buf[i + 1] + (25 if buf[i + 2] & 1 else 12)
        elif b0 == STX_V1 and i + 2 <= len(buf):
            total = buf[i + 1] + 8
        else:
            return False
        if i + total > len(buf):
            return False
        try:
            m = self._plain.decode(buf[i:i + total]) if self._plain is not self.mav or b0 == STX_V1 \
                else self.mav.decode(buf[i:i + total])
        except Exception:
            return False
        return not isinstance(m, mavlink2.MAVLink_unknown)

    def _packet_inside(self, buf, i: int, j: int) -> bool:
        while i < j:
            k2, k1 = buf.find(b'\xfd', i, j), buf.find(b'\xfe', i, j)
            k = k1 if k2 < 0 else (k2 if k1 < 0 else min(k1, k2))
            if k < 0:
                return False
            if self._decodes_at(buf, k):
                return True
            i = k + 1
        return False

    def _junk(self, i: int, j: int) -> None:
        """Count bytes [i, j) as junk, except a record gap (the .tlog timestamp) before a due packet."""
        e = self._expect
        if e >= 0 and self.record_gap:
            overlap = max(0, min(j, e) - max(i, e - self.record_gap))
            self.stats.junk_bytes += (j - i) - overlap
        else:
            self.stats.junk_bytes += j - i

    def _skip(self, i: int) -> int:
        if i == self._expect:
            self.stats.crc_errors += 1
            self._expect = -1
        self._junk(i, i + 1)
        return i + 1

    def _accept(self, m, pkt, flags: int) -> bool:
        stats = self.stats
        hdr = m.get_header()
        if self.require_signed and not (flags & 1):
            stats.unsigned_rejected += 1
            return False
        if flags & 1 and self.mav.signing.secret_key is not None:
            if self.link_id >= 0 and pkt[-13] != self.link_id:
                stats.signature_rejected += 1
                return False
        src = (hdr.srcSystem, hdr.srcComponent)
        last = self._last_seq.get(src)
        if last is not None:
            gap = (hdr.seq - last - 1) & 0xFF
            if gap and gap < 128:          # larger "gaps" are reordering or a restarted sender
                stats.seq_lost += gap
        self._last_seq[src] = hdr.seq
        if (self.sysid and hdr.srcSystem != self.sysid) or (self.compid and hdr.srcComponent != self.compid):
            stats.filtered += 1
            return False
        stats.packets += 1
        stats.by_type[m.get_type()] += 1
        return True

    @property
    def consumed(self) -> int:
        """Bytes consumed from the start of the stream (offsets from feed() are relative to this)."""
        return self._consumed


def read_tlog(path, stream: MavlinkStream | None = None):
    """Every message of a Mission Planner .tlog with its recorded UNIX time (s, or None if unreadable).

    The file is framed as a byte stream (so damage anywhere only costs the packets it hits); each
    packet's time is the big-endian microsecond stamp in the 8 bytes before it.
    """
    try:
        with open(path, 'rb') as f:
            data = f.read()
    except OSError as exc:
        raise MavlinkError(f'cannot read telemetry log {path}: {exc}') from exc
    stream = stream or MavlinkStream(record_gap=8)
    if stream.record_gap != 8:
        raise ConfigError('read_tlog needs a MavlinkStream made with record_gap=8')
    out = []
    for m, off in stream.feed(data, final=True, with_offsets=True):
        t = None
        if off >= 8:
            us = struct.unpack_from('>Q', data, off - 8)[0]
            if _TLOG_STAMP_MIN_US < us < _TLOG_STAMP_MAX_US:
                t = us * 1e-6
        out.append((m, t))
    return out, stream.stats
