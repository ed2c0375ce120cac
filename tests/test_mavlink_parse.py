"""MAVLink framing/decoding: counts against plain pymavlink on real logs, damage, signing, filters."""

from __future__ import annotations

import subprocess
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from conftest import ROOT, SAMPLE_BAG, shared_data
from photogram_ros.errors import ConfigError
from photogram_ros.io.mavlink import MavlinkStream, read_tlog, signing_key

PHOENIX = ('mavlink', 'phoenix_mission1_2018-09-17_16-44-06.tlog')
SITL = ('mavlink', 'sitl_vtol.tlog')


def sample_flight_dir(tmp_root) -> Path:
    """The committed sample flight (from git when the working copy is being regenerated)."""
    if (SAMPLE_BAG / 'flight.tlog').exists() and (SAMPLE_BAG / 'ground_truth.json').exists():
        return SAMPLE_BAG
    out = Path(tmp_root) / 'sample_flight'
    out.mkdir(exist_ok=True)
    for name in ('flight.tlog', 'ground_truth.json', 'ground_truth_dem.npz', 'metadata.yaml', 'sample_flight.db3'):
        blob = subprocess.run(['git', 'show', f'HEAD:bags/sample_flight/{name}'], cwd=ROOT, capture_output=True)
        if blob.returncode != 0:
            pytest.skip('sample flight missing from the working copy and from git')
        (out / name).write_bytes(blob.stdout)
    return out


@pytest.fixture(scope='module')
def sample_dir(tmp_path_factory):
    return sample_flight_dir(tmp_path_factory.mktemp('sample'))


def _pymavlink_counts(path) -> Counter:
    conn = mavutil.mavlink_connection(str(path), robust_parsing=True)
    out = Counter()
    while True:
        m = conn.recv_match()
        if m is None:
            return out
        out[m.get_type()] += 1


@pytest.mark.parametrize('parts', [PHOENIX, SITL])
def test_real_tlog_counts_match_pymavlink(parts):
    path = shared_data(*parts)
    msgs, stats = read_tlog(path)
    mine = Counter(m.get_type() for m, _ in msgs)
    assert mine == _pymavlink_counts(path)
    assert stats.crc_errors == 0 and stats.junk_bytes == 0
    assert all(t is not None for _, t in msgs)        # every packet got its recorded time


def test_phoenix_known_counts():
    msgs, _ = read_tlog(shared_data(*PHOENIX))
    c = Counter(m.get_type() for m, _ in msgs)
    assert sum(c.values()) == 29475
    assert (c['GPS_RAW_INT'], c['GLOBAL_POSITION_INT'], c['ATTITUDE']) == (786, 782, 902)
    fix_types = Counter(m.fix_type for m, _ in msgs if m.get_type() == 'GPS_RAW_INT')
    assert fix_types[3] == 781 and sum(v for k, v in fix_types.items() if k < 2) == 5


def test_sample_flight_counts_match_pymavlink(sample_dir):
    path = sample_dir / 'flight.tlog'
    msgs, _ = read_tlog(path)
    assert Counter(m.get_type() for m, _ in msgs) == _pymavlink_counts(path)


def _clean_packets(path):
    data = open(path, 'rb').read()
    s = MavlinkStream(record_gap=8)
    out = s.feed(data, final=True, with_offsets=True)
    return data, [(off, bytes(m._msgbuf)) for m, off in out]


@pytest.mark.parametrize('seed', [1, 2, 3])
def test_fuzz_every_intact_packet_survives(seed):
    """Bytes flipped, dropped and inserted (with fake start bytes): every untouched packet decodes."""
    data, packets = _clean_packets(shared_data(*PHOENIX))
    rng = np.random.default_rng(seed)
    damaged = set(rng.choice(len(packets), size=len(packets) // 20, replace=False).tolist())
    pieces, cursor = [], 0
    for k, (off, pkt) in enumerate(packets):
        pieces.append(data[cursor:off])        # the tlog timestamp before it
        cursor = off + len(pkt)
        if k not in damaged:
            pieces.append(pkt)
            continue
        b = bytearray(pkt)
        r = rng.random()
        if r < 0.3:
            b[int(rng.integers(len(b)))] ^= int(rng.integers(1, 256))
        elif r < 0.5:
            del b[int(rng.integers(len(b))):]           # truncated
        elif r < 0.7:
            del b[int(rng.integers(len(b)))]            # one byte dropped
        else:
            # Junk with a false start byte claiming a long packet, in front of a damaged packet.
            junk = bytes([0xFD, 250, 0]) + rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8).tobytes()
            b = bytearray(junk) + b[1:]
        pieces.append(bytes(b))
    stream = b''.join(pieces) + data[cursor:]
    s = MavlinkStream(record_gap=8)
    got = Counter(bytes(m._msgbuf) for m in s.feed(stream, final=True))
    want = Counter(pkt for k, (_, pkt) in enumerate(packets) if k not in damaged)
    missing = want - got
    assert not missing, f'{sum(missing.values())} intact packets lost'
    assert s.stats.crc_errors > 0 and s.stats.junk_bytes > 0
    # pymavlink's own parser loses intact packets on the same stream (why we frame ourselves).
    mav = mavlink2.MAVLink(None)
    mav.robust_parsing = True
    plain = Counter(bytes(m._msgbuf) for m in (mav.parse_buffer(stream) or []) if m.get_type() != 'BAD_DATA')
    assert sum((want - plain).values()) > 0


def test_chunked_feed_equals_whole(sample_dir):
    data, packets = _clean_packets(sample_dir / 'flight.tlog')
    rng = np.random.default_rng(0)
    s = MavlinkStream(record_gap=8)
    got, i = [], 0
    while i < len(data):
        n = int(rng.integers(1, 300))
        got += s.feed(data[i:i + n], final=i + n >= len(data))
        i += n
    assert [bytes(m._msgbuf) for m in got] == [p for _, p in packets]


def _packets(mav, n=5):
    return [mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav) for _ in range(n)]


def _signed_mav(key, link_id=0, sysid=1):
    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = True
    mav.signing.link_id = link_id
    mav.signing.timestamp = 1
    return mav


def test_signing_accepts_only_correctly_signed():
    key, wrong = signing_key('correct horse'), signing_key('battery staple')
    good = _packets(_signed_mav(key, link_id=1))
    bad = _packets(_signed_mav(wrong, link_id=1, sysid=2))
    unsigned = _packets(mavlink2.MAVLink(None, srcSystem=3, srcComponent=1))
    stream = b''.join(a + b + c for a, b, c in zip(good, bad, unsigned))

    s = MavlinkStream(secret_key=key)
    msgs = s.feed(stream, final=True)
    assert [m._header.srcSystem for m in msgs] == [1] * 5
    assert all(m.get_signed() for m in msgs)
    assert (s.stats.signature_rejected, s.stats.unsigned_rejected, s.stats.crc_errors) == (5, 5, 0)

    s = MavlinkStream(secret_key=key, allow_unsigned=True)
    assert Counter(m._header.srcSystem for m in s.feed(stream, final=True)) == {1: 5, 3: 5}
    assert s.stats.signature_rejected == 5

    s = MavlinkStream(secret_key=key, link_id=2)    # right key, but from another link
    assert s.feed(stream, final=True) == []
    assert s.stats.signature_rejected == 10

    s = MavlinkStream()                              # no key: everything decodes, nothing is checked
    assert len(s.feed(stream, final=True)) == 15


def test_signing_key_forms():
    assert signing_key('00' * 32) == bytes(32)
    assert len(signing_key('passphrase')) == 32
    with pytest.raises(ConfigError):
        MavlinkStream(secret_key=b'short')


def test_replayed_signed_packet_rejected():
    key = signing_key('k')
    pkts = _packets(_signed_mav(key))
    s = MavlinkStream(secret_key=key)
    assert len(s.feed(b''.join(pkts) + pkts[0], final=True)) == 5
    assert s.stats.signature_rejected == 1


def test_filter_by_system_and_component_and_seq_gaps():
    a = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    g = mavlink2.MAVLink(None, srcSystem=1, srcComponent=154)
    o = mavlink2.MAVLink(None, srcSystem=7, srcComponent=1)
    pkts = []
    for k in range(10):
        for mav in (a, g, o):
            pkts.append(mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav))
            mav.seq = (mav.seq + (2 if mav is a and k == 4 else 1)) % 256   # autopilot skips one
    s = MavlinkStream(sysid=1, compid=1)
    msgs = s.feed(b''.join(pkts), final=True)
    assert len(msgs) == 10 and {(m._header.srcSystem, m._header.srcComponent) for m in msgs} == {(1, 1)}
    assert s.stats.filtered == 20 and s.stats.seq_lost == 1


def test_mavlink1_and_random_bytes():
    from pymavlink.dialects.v10 import ardupilotmega as mavlink1
    m1 = mavlink1.MAVLink(None, srcSystem=1, srcComponent=1)
    v1 = m1.gps_raw_int_encode(1000, 3, 491234567, -1231234567, 100000, 120, 200, 0, 0, 12).pack(m1)
    rng = np.random.default_rng(5)
    noise = rng.integers(0, 256, 5000, dtype=np.uint8).tobytes()
    s = MavlinkStream()
    msgs = s.feed(noise + v1 + noise + v1, final=True)
    assert [m.get_type() for m in msgs] == ['GPS_RAW_INT', 'GPS_RAW_INT']
    assert msgs[0].lat == 491234567 and s.stats.junk_bytes >= 10000
