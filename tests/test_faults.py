"""Faults and bad input, as a hostile but realistic user meets them (docs/faults.md).

One test per case, each with its expected outcome: a clear message, an exit status, and what was
kept. The onboard stop (`run` with camera frames, SIGTERM) is in the fast set; the other long
flights are marked slow.
"""

from __future__ import annotations

import datetime
import json
import re
import os
import shutil
import signal
import socket
import sqlite3
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, SAMPLE_BAG, shared_data
from helpers.processes import reaped
from test_mavlink_node import _free_udp_port

CLI = [sys.executable, '-m', 'photogram_ros.cli']


def cli(*args, timeout=300, **kw):
    return subprocess.run(CLI + [str(a) for a in args], cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                          **kw)


def _copy_bag(tmp_path: Path, name='bag') -> Path:
    dst = tmp_path / name
    shutil.copytree(SAMPLE_BAG, dst, ignore=shutil.ignore_patterns('*.tlog', 'ground_truth*', 'targets.txt'))
    return dst


def _truncate(bag: Path, fraction: float) -> Path:
    db = next(bag.glob('*.db3'))
    data = db.read_bytes()
    db.write_bytes(data[:int(len(data) * fraction)])
    return db


def _messages(path) -> dict:
    """(topic, stamp_ns) -> data of every message a BagReader yields."""
    from photogram_ros.io.bag import BagReader
    with BagReader(path) as bag:
        return {(m.topic, m.stamp_ns): m.data for m in bag.messages()}


@pytest.fixture(scope='module')
def intact() -> dict:
    return _messages(SAMPLE_BAG)


# --- damaged bags ----------------------------------------------------------------------------------


def _dump_count(db: Path, tmp_path: Path) -> int | None:
    """Independent oracle: rows the sqlite3 shell's .dump still finds (the header's page count set
    to the pages the file holds, which the shell needs to open it); None without the shell."""
    if shutil.which('sqlite3') is None:
        return None
    data = bytearray(db.read_bytes())
    pages = len(data) // 4096
    data[28:32] = struct.pack('>I', pages)
    copy = tmp_path / 'oracle.db3'
    copy.write_bytes(bytes(data[:pages * 4096]))
    out = subprocess.run(['sqlite3', str(copy), '.dump messages'], capture_output=True, text=True).stdout
    return sum(line.startswith('INSERT INTO messages') for line in out.splitlines())


@pytest.mark.parametrize('fraction', [0.3, 0.6, 0.9])
def test_truncated_sqlite_bag_gives_what_it_holds(tmp_path, intact, fraction):
    """Power loss: a .db3 cut at 30/60/90 %. Every readable message comes out byte for byte, the count
    matches the sqlite3 shell's, and every command says how many of the 3726 it read."""
    from photogram_ros.io.bag import BagReader
    bag = _copy_bag(tmp_path)
    db = _truncate(bag, fraction)
    got = _messages(bag)
    assert got and all(intact[k] == v for k, v in got.items())
    assert 0.8 * fraction < len(got) / len(intact) < fraction + 0.05   # about what the file still holds
    oracle = _dump_count(db, tmp_path)
    with BagReader(bag) as r:
        readable = sum(t.count for t in r.topics().values())
        assert any(f'of {len(intact)} messages readable' in e for e in r.errors)
        assert r.duration_ns * 1e-9 == pytest.approx(77.7 * fraction, abs=3.0)
    if oracle is not None:
        assert len(got) == oracle
    assert 0 <= readable - len(got) <= 1      # a row whose last overflow page is cut lists, but does not read
    res = cli('bag-info', bag)
    assert res.returncode == 3 and f'{len(got)} messages of {len(intact)} recorded' in res.stdout
    assert 'lost' in res.stderr and 'cut short' in res.stderr


def test_truncated_mcap_bag_gives_its_complete_chunks(tmp_path, intact):
    """The same flight as MCAP (what `record` writes by default), cut at 60 %: the complete chunks
    are read, in order, byte for byte; the command says what was lost."""
    from photogram_ros.io.bag import BagReader, BagWriter
    mc = tmp_path / 'mc'
    with BagReader(SAMPLE_BAG) as r, BagWriter(mc, storage='mcap') as w:
        for t in r.topics().values():
            w.add_topic(t.topic, t.msgtype)
        for m in r.messages():
            w.write_raw(m.topic, m.stamp_ns, m.data)
    f = next(mc.glob('*.mcap'))
    size = f.stat().st_size
    f.write_bytes(f.read_bytes()[:int(size * 0.6)])
    got = _messages(mc)
    assert all(intact[k] == v for k, v in got.items())
    # Chunks hold 1 MB: all but the chunk the cut went through.
    assert 0.6 * len(intact) - 1.2e6 / size * len(intact) < len(got) < 0.6 * len(intact)
    # Chunks follow one another in time: what is lost comes after what was read (to within a chunk's span).
    assert max(k[1] for k in got) < min(k[1] for k in set(intact) - set(got)) + 1_000_000_000
    res = cli('bag-info', mc)
    assert res.returncode == 3 and f'{len(got)} messages of {len(intact)} recorded' in res.stdout
    assert 'damaged MCAP' in res.stderr


def test_overwritten_pages_lose_only_their_rows(tmp_path, intact):
    """64 KB of garbage in the middle of the .db3: the rows on those pages are lost, the rows after
    them are still read (not "counts of 0", not half the bag), and the loss is said."""
    bag = _copy_bag(tmp_path)
    db = next(bag.glob('*.db3'))
    data = bytearray(db.read_bytes())
    mid = len(data) // 2 // 4096 * 4096
    data[mid:mid + 65536] = np.random.default_rng(0).integers(0, 256, 65536, dtype=np.uint8).tobytes()
    db.write_bytes(bytes(data))
    got = _messages(bag)
    assert 0.9 * len(intact) < len(got) < len(intact)
    assert max(k[1] for k in got) == max(k[1] for k in intact)       # read past the damage to the end
    # SQLite has no checksums: a row whose overflow page (part of a JPEG) was overwritten reads back
    # with the garbage, as it would in any reader; at most the 16 overwritten pages' worth.
    changed = [k for k, v in got.items() if intact[k] != v]
    assert len(changed) <= 16 and all(k[0] == '/camera/image_raw/compressed' for k in changed)
    res = cli('bag-info', bag)
    assert res.returncode == 3 and 'lost' in res.stderr and f'of {len(intact)} recorded' in res.stdout


def test_missing_or_garbled_metadata_is_a_warning_not_zero(tmp_path, intact):
    """A recording cut short has no metadata.yaml; a garbled one is as good as none. The database still
    gives the duration and the counts (not 0.0 s and 0), and the command says nothing can be compared."""
    for what in ('missing', 'garbled'):
        bag = _copy_bag(tmp_path, what)
        meta = bag / 'metadata.yaml'
        meta.unlink() if what == 'missing' else meta.write_text('rosbag2_bagfile_information: [oops')
        res = cli('bag-info', bag)
        assert res.returncode == 0, res.stderr
        assert '77.7 s' in res.stdout and f'{len(intact)} messages' in res.stdout
        assert f'metadata.yaml is {"missing" if what == "missing" else "unreadable"}' in res.stderr
    # Cut short and without metadata (the usual power loss): what it holds, and that the loss is unknown.
    bag = _copy_bag(tmp_path, 'cut')
    (bag / 'metadata.yaml').unlink()
    _truncate(bag, 0.5)
    res = cli('bag-info', bag)
    assert res.returncode == 3 and 'unknown' in res.stderr and 'page' in res.stderr


def test_fixes_of_a_truncated_bag_say_what_was_lost(tmp_path):
    bag = _copy_bag(tmp_path)
    _truncate(bag, 0.5)
    res = cli('fixes', bag)
    assert res.returncode == 3 and 'of 3726 messages readable' in res.stderr
    rows = res.stdout.strip().splitlines()[1:]
    assert 150 < len(rows) < 200          # half the flight's 389 fixes


@pytest.mark.slow
def test_replay_of_a_truncated_bag_maps_what_it_holds(tmp_path, tiny_flight):
    bag = tmp_path / 'tiny'
    shutil.copytree(tiny_flight, bag)
    _truncate(bag, 0.6)
    res = cli('replay', bag, '--out', tmp_path / 'out', '--quiet', timeout=900)
    assert res.returncode == 3, res.stdout[-2000:] + res.stderr[-2000:]
    assert 'messages readable' in res.stdout
    run = json.loads((tmp_path / 'out' / 'run.json').read_text())
    assert run['bag_errors'] and 0 < run['frames'] < 23
    assert (tmp_path / 'out' / 'report.md').exists()


@pytest.mark.slow
def test_triangulate_of_a_truncated_bag_says_what_was_lost(tmp_path, tiny_flight):
    bag = tmp_path / 'tiny'
    shutil.copytree(tiny_flight, bag)
    _truncate(bag, 0.7)
    res = cli('triangulate', bag, '--out', tmp_path / 'at', timeout=900)
    assert 'messages readable' in res.stderr
    assert 'bag damaged' in (tmp_path / 'at' / 'report.md').read_text()


# --- the onboard stop ------------------------------------------------------------------------------


def _run_with_player(tmp_path: Path, flight: Path, sig: int, ignore_sigint: bool = False):
    """`run` (no camera node: a player publishes the flight's camera and MAVLink), stopped by `sig` once
    the flight has been played and mapped. Returns (exit status, output, signal time, map folder,
    products folder). A second attempt is made, in fresh folders, when no keyframe reached the map: Fast
    DDS's shared-memory transport now and then delivers nothing between two processes after other
    processes were killed (eProsima/Fast-DDS#5469); the test is about the stop, not the transport."""
    first = _try_run_with_player(tmp_path / 'a', flight, sig, ignore_sigint)
    return first if first is not None else _try_run_with_player(tmp_path / 'b', flight, sig, ignore_sigint,
                                                                last=True)


def _try_run_with_player(tmp_path: Path, flight: Path, sig: int, ignore_sigint: bool, last: bool = False):
    tmp_path.mkdir(parents=True)
    cfg = tmp_path / 'onboard.yaml'
    cfg.write_text(f'map_node:\n  ros__parameters:\n    map_dir: {tmp_path / "map"}\n')
    cmd = CLI + ['run', '--params', str(cfg), '--out', str(tmp_path / 'products')]
    if ignore_sigint:   # as a non-interactive shell starts a background job: SIGINT ignored
        cmd = ['bash', '-c', "trap '' INT; exec \"$@\"", 'bash'] + cmd
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []     # the run's output, read all along (a full pipe would stall its nodes)
    running = threading.Event()

    def read_output():
        for line in proc.stdout:
            lines.append(line)
            if 'photogram_ros running' in line:
                running.set()
        running.set()

    reader = threading.Thread(target=read_output, daemon=True)
    reader.start()
    keyframes = tmp_path / 'map' / 'keyframes'
    try:
        assert running.wait(300) and proc.poll() is None, ''.join(lines)[-3000:]
        # The camera, its calibration and the MAVLink stream each have their subscriber before playing.
        play = cli('play', flight, '--rate', '1', '--exclude', '/gps/fix', '--wait-for-subscribers', '3',
                   timeout=300)
        assert play.returncode == 0, play.stdout + play.stderr
        deadline = time.monotonic() + 120.0     # a bound on the wait for the mapping of the last frames
        while len(list(keyframes.glob('*.json'))) <= 5 and time.monotonic() < deadline:
            time.sleep(1.0)
        time.sleep(3.0)
        if len(list(keyframes.glob('*.json'))) <= 5:
            assert not last, ''.join(lines)[-3000:]
            return None
        t_signal = time.time()
        proc.send_signal(sig)
        proc.wait(timeout=600)
        reader.join(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, ''.join(lines), t_signal, tmp_path / 'map', tmp_path / 'products'


def _assert_final_adjustment_products(rc, out, t_signal, map_dir, products):
    assert rc == 0, out[-3000:]
    for words in ('context is invalid', 'adjustment failed', 'flush failed', 'Traceback'):
        assert words not in out, out[-3000:]
    assert json.loads((map_dir / 'flight_end.json').read_text())['final_adjustment'] == 'done'
    # The final adjustment republished every pose: the map rewrote each one after the signal.
    poses = list((map_dir / 'keyframes').glob('*.json'))
    assert poses and min(p.stat().st_mtime for p in poses) >= t_signal - 0.5
    report = json.loads((products / 'report.json').read_text())
    assert report['run']['products_from'] == 'final adjustment (map_final)'
    assert 'final adjustment' in (products / 'report.md').read_text()
    for name in ('cloud.las', 'dsm.tif', 'ortho.tif'):
        assert (products / name).stat().st_size > 0


@pytest.fixture(scope='module')
def stopped_run(tmp_path_factory, tiny_flight):
    tmp = tmp_path_factory.mktemp('run_sigterm')
    return _run_with_player(tmp, tiny_flight, signal.SIGTERM)


def test_run_stopped_by_sigterm_keeps_the_final_adjustment(stopped_run):
    """The onboard stop: SIGTERM ends the flight with rclpy still up: the final adjustment publishes,
    the map saves its poses, the products and the report come from it, exit 0."""
    rc, out, t_signal, map_dir, products = stopped_run
    assert 'SIGTERM: ending the flight' in out
    _assert_final_adjustment_products(rc, out, t_signal, map_dir, products)


@pytest.mark.slow
def test_run_in_the_background_stopped_by_sigint_keeps_the_final_adjustment(tmp_path, tiny_flight):
    """SIGINT to a `run` a shell started in the background (SIGINT ignored): it stops, the same way."""
    rc, out, t_signal, map_dir, products = _run_with_player(tmp_path, tiny_flight, signal.SIGINT, True)
    assert 'SIGINT: ending the flight' in out
    _assert_final_adjustment_products(rc, out, t_signal, map_dir, products)


def test_products_say_when_the_final_adjustment_failed(stopped_run, tmp_path):
    """A map whose flight ended without its final adjustment: the report says the products come from the
    in-flight poses, and why (never "from the final adjustment")."""
    from photogram_ros.commands.products import export_products
    from photogram_ros.io.map_store import MapStore
    map_dir = tmp_path / 'map'
    shutil.copytree(stopped_run[3], map_dir)
    MapStore(map_dir).save_flight_end({'final_adjustment': 'failed', 'reason': 'publisher context invalid',
                                       'errors': []})
    res = export_products(map_dir, tmp_path / 'out', None, live_map=True)
    assert 'the final adjustment failed (publisher context invalid)' in res['figures']['run']['products_from']
    assert any('final adjustment failed' in n for n in res['notes'])


def test_final_adjustment_outcome_from_the_bundle_counters():
    from photogram_ros.nodes.graph import _final_adjustment_outcome
    assert _final_adjustment_outcome({'full_adjustments': 0}, {'full_adjustments': 1}, [], '')[0] == 'done'
    st, why = _final_adjustment_outcome({'keyframes_oriented': 9}, {'keyframes_oriented': 9},
                                        ['full adjustment failed: Failed to publish'], '')
    assert st == 'failed' and 'Failed to publish' in why
    assert _final_adjustment_outcome({}, {}, [], '') == ('none', 'no keyframe was oriented')
    assert _final_adjustment_outcome({}, {'keyframes_oriented': 3}, [], 'bundle: finish failed: x')[0] == 'failed'


@pytest.mark.slow
def test_kill_9_of_run_corrupts_nothing_on_disk(tmp_path, tiny_flight):
    """kill -9 mid-flight: the map folder opens, every tile reads (CRC-checked blocks), no temporary
    files are left, and it exports afterwards."""
    from photogram_ros.io.map_store import MapStore
    cfg = tmp_path / 'onboard.yaml'
    cfg.write_text(f'map_node:\n  ros__parameters:\n    map_dir: {tmp_path / "map"}\n')
    log = tmp_path / 'run.log'
    with log.open('w') as out:
        proc = subprocess.Popen(CLI + ['run', '--params', str(cfg), '--no-export'], cwd=ROOT, stdout=out,
                                stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 300
        while 'photogram_ros running' not in log.read_text() and time.monotonic() < deadline:
            assert proc.poll() is None, log.read_text()[-3000:]
            time.sleep(0.5)
        player = subprocess.Popen(CLI + ['play', str(tiny_flight), '--exclude', '/gps/fix'], cwd=ROOT,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(list((tmp_path / 'map' / 'tiles').glob('*.pgt'))) < 2:
            time.sleep(0.2)
        proc.kill()
        player.wait(timeout=120)
    finally:
        for p in (proc,):
            if p.poll() is None:
                p.kill()
    store = MapStore(tmp_path / 'map')
    assert store.tile_keys() and all(store.load_tile(k) is not None for k in store.tile_keys())
    assert not list((tmp_path / 'map').rglob('*.tmp'))
    res = cli('export', tmp_path / 'map', '--crs', 'EPSG:32632', '--out', tmp_path / 'out', '--min-pairs', '1',
              timeout=600)
    assert res.returncode == 0, res.stderr


def _children(pid: int) -> list[int]:
    out = subprocess.run(['pgrep', '-P', str(pid)], capture_output=True, text=True).stdout
    return [int(p) for p in out.split()]


def _replay_with_its_child(flight, out):
    """A replay of `flight` at half speed, once its second process runs: (process, the child pids)."""
    proc = subprocess.Popen(CLI + ['replay', str(flight), '--out', str(out), '--rate', '0.5'],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    children = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not children and proc.poll() is None:
        children = _children(proc.pid)
        time.sleep(0.2)
    if not children:
        proc.kill()
        raise AssertionError('the replay started no child process: ' + proc.communicate()[0][-2000:])
    return proc, children


def test_kill_9_of_replay_ends_its_child(tmp_path, tiny_flight):
    """The replay's second process (bundle, stereo, map) dies with its parent, however the parent ends:
    it watches a pipe from it."""
    proc, children = _replay_with_its_child(tiny_flight, tmp_path / 'out')
    try:
        time.sleep(8.0)
        proc.kill()
        proc.wait(timeout=30)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and any(os.path.exists(f'/proc/{c}') and
                                                 'zombie' not in _state(c) for c in children):
            time.sleep(0.2)
        assert not [c for c in children if os.path.exists(f'/proc/{c}') and 'zombie' not in _state(c)]
    finally:
        if proc.poll() is None:
            proc.kill()


def test_sigterm_to_replay_stops_it_in_order(tmp_path, tiny_flight):
    """SIGTERM to a replay mid-flight (`timeout`, a service manager): the graph shuts down in order (the
    second process ends, the map flushes its tiles), one line "stopped by SIGTERM", exit 143, no
    traceback; the map folder holds no flight_end.json, so later products say "in-flight poses"."""
    out = tmp_path / 'out'
    proc, children = _replay_with_its_child(tiny_flight, out)
    with reaped(proc):
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not list((out / 'map' / 'keyframes').glob('*')):
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        text = proc.communicate(timeout=180)[0]
    assert proc.returncode == 143 and text.strip().splitlines()[-1].endswith('replay: stopped by SIGTERM'), text[-3000:]
    assert 'Traceback' not in text
    assert not [c for c in children if os.path.exists(f'/proc/{c}') and 'zombie' not in _state(c)]
    assert (out / 'map' / 'map.json').exists() and not (out / 'map' / 'flight_end.json').exists()


def _state(pid: int) -> str:
    try:
        return Path(f'/proc/{pid}/status').read_text().split('State:')[1].split('\n')[0].lower()
    except (OSError, IndexError):
        return 'zombie'


# --- checked before the first frame ----------------------------------------------------------------


@pytest.mark.parametrize('crs, words', [('EPSG:999999', 'unknown output CRS'), ('EPSG:4326', 'not a projected CRS')])
def test_bad_output_crs_is_refused_before_the_replay(tmp_path, crs, words):
    res = cli('replay', SAMPLE_BAG, '--out', tmp_path / 'out', '--crs', crs, '--quiet', timeout=120)
    assert res.returncode == 2 and words in res.stderr and 'Traceback' not in res.stderr
    assert not (tmp_path / 'out' / 'map').exists()


def test_bad_output_crs_is_refused_by_export_before_it_reads_the_map(tmp_path):
    res = cli('export', tmp_path / 'no_map', '--crs', 'EPSG:999999', '--out', tmp_path / 'out', timeout=60)
    assert res.returncode == 2 and 'unknown output CRS' in res.stderr and 'Traceback' not in res.stderr


def test_parameter_errors_of_the_child_process_come_at_once(tmp_path):
    """A mistake in a parameter of a node of replay's second process: named within seconds, not after
    the child's 60 s start timeout; a child that fails at its start is noticed at once too."""
    bad = tmp_path / 'bad.yaml'
    bad.write_text('bundle_node:\n  ros__parameters:\n    window_sise: 10\n')
    res = cli('replay', SAMPLE_BAG, '--out', tmp_path / 'o1', '--params', bad, '--quiet', timeout=120)
    assert res.returncode == 2 and 'window_sise' in res.stderr and 'window_size' in res.stderr
    worse = tmp_path / 'worse.yaml'
    worse.write_text(f'bundle_node:\n  ros__parameters:\n    control_file: {tmp_path / "no_such_targets.txt"}\n')
    res = cli('replay', SAMPLE_BAG, '--out', tmp_path / 'o2', '--params', worse, '--quiet', timeout=120)
    # The tracker's target search reads the same file in the first process: named before any child starts.
    assert res.returncode == 2 and 'cannot read the control-point file' in res.stderr \
        and 'no_such_targets.txt' in res.stderr and 'Traceback' not in res.stderr


def test_config_mistakes_get_clear_messages(tmp_path):
    """YAML that does not parse, a section for no node, a value out of range, a control file without a CRS:
    exit 2, the reason, no traceback, in seconds."""
    cases = {'syntax.yaml': ('map_node:\n  ros__parameters:\n    cell_m: [0.05\n', 'not valid YAML'),
             'section.yaml': ('mapnode:\n  ros__parameters:\n    cell_m: 0.05\n', 'name no node'),
             'range.yaml': ('stereo_node:\n  ros__parameters:\n    downscale: 7.0\n', 'downscale')}
    for name, (text, words) in cases.items():
        (tmp_path / name).write_text(text)
        res = cli('run', '--params', tmp_path / name, timeout=60)
        assert res.returncode == 2 and words in res.stderr and 'Traceback' not in res.stderr, (name, res.stderr)
    gcp = tmp_path / 'targets.txt'
    gcp.write_text('GCP01 0 465698.587 5249464.825 489.927\n')
    res = cli('replay', SAMPLE_BAG, '--out', tmp_path / 'o', '--gcp', gcp, '--quiet', timeout=60)
    assert res.returncode == 2 and 'Traceback' not in res.stderr and res.stderr.strip()


# --- a full disk -----------------------------------------------------------------------------------


def test_full_disk_write_leaves_no_temporary_file(tmp_path, monkeypatch):
    """ENOSPC while writing a map file: a StorageError (an OSError too, which the nodes handle) naming
    the folder and the cause, and no zero-byte *.tmp behind."""
    import errno

    from photogram_ros.errors import StorageError
    from photogram_ros.io import map_store

    def full(fd):
        raise OSError(errno.ENOSPC, 'No space left on device')
    monkeypatch.setattr(map_store.os, 'fsync', full)
    with pytest.raises(StorageError, match='disk is full') as exc:
        map_store._atomic_write(tmp_path / 'map.json', b'{}')
    assert isinstance(exc.value, OSError) and exc.value.errno == errno.ENOSPC
    assert not list(tmp_path.iterdir())


@pytest.fixture
def small_disk(tmp_path):
    """A tmpfs of the size asked for (needs root; skipped without)."""
    mounts = []

    def make(mb: int) -> Path:
        d = tmp_path / f'disk{len(mounts)}'
        d.mkdir()
        if subprocess.run(['mount', '-t', 'tmpfs', '-o', f'size={mb}m', 'tmpfs', str(d)],
                          capture_output=True).returncode != 0:
            pytest.skip('cannot mount a small tmpfs here (needs root)')
        mounts.append(d)
        return d
    yield make
    for d in mounts:
        subprocess.run(['umount', '-l', str(d)], capture_output=True)


def test_replay_onto_a_full_disk_is_refused_at_once(small_disk):
    out = small_disk(3) / 'out'
    res = cli('replay', SAMPLE_BAG, '--out', out, '--quiet', timeout=120)
    assert res.returncode == 2 and 'MB free before the replay' in res.stderr and 'Traceback' not in res.stderr


@pytest.mark.slow
def test_replay_stops_when_the_disk_fills(small_disk):
    """The disk fills during the replay: it stops there with the reason (not after minutes of waiting on
    a map that cannot write, not with a traceback) and leaves no temporary files."""
    out = small_disk(40) / 'out'
    res = cli('replay', SAMPLE_BAG, '--out', out, '--quiet', timeout=600)
    assert res.returncode == 2 and 'MB free after' in res.stderr and 'Traceback' not in res.stderr
    assert not list(out.rglob('*.tmp'))


# --- MAVLink and time -----------------------------------------------------------------------------


def _pack(mav, m):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    m.pack(mav)
    m._header = mavlink2.MAVLink_header(m.id, 0, 0, 0, 0, 1, 1)
    return m


def test_poisoned_time_is_refused_and_said():
    """An ATTITUDE with time_boot_ms = 0 and a SYSTEM_TIME in 2100 in the middle of the sample flight:
    every /gps/fix keeps its 2026 stamp, and the problems say what was refused."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from photogram_ros.io.mavlink import fixes_from_messages, read_tlog
    msgs, _ = read_tlog(SAMPLE_BAG / 'flight.tlog')
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    i = len(msgs) // 2
    boot = next(m.time_boot_ms for m, _ in msgs[i:] if m.get_type() == 'ATTITUDE')
    t = msgs[i][1]
    poison = [(_pack(mav, mav.attitude_encode(0, 0, 0, 0, 0, 0, 0)), t),
              (_pack(mav, mav.system_time_encode(int(datetime.datetime(2100, 6, 1).timestamp() * 1e6), boot)), t),
              (_pack(mav, mav.system_time_encode(int((t + 86_400 * 400) * 1e6), boot + 1)), t)]   # plausible, alone
    clean, _ = fixes_from_messages(msgs)
    events, ing = fixes_from_messages(msgs[:i] + poison + msgs[i:])
    years = {datetime.datetime.fromtimestamp(e.fix.t_s, datetime.timezone.utc).year for e in events}
    assert years == {2026} and len(events) == len(clean)
    assert [e.fix.t_s for e in events] == pytest.approx([e.fix.t_s for e in clean], abs=1e-6)
    text = ' '.join(ing.problems)
    assert 'outside 2000-2100' in text and 'not a reboot' in text and 'ignored unless it repeats' in text


def _fixes_over_udp(datagrams, duration_s=10.0):
    port = _free_udp_port()
    proc = subprocess.Popen(CLI + ['fixes', f'udpin:127.0.0.1:{port}', '--duration', str(duration_s), '--format',
                                   'jsonl'], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 30   # until the link's socket is bound (the command starts in seconds)
    while time.monotonic() < deadline and f':{port:04X} ' not in Path('/proc/net/udp').read_text():
        time.sleep(0.1)
    time.sleep(0.5)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for k, d in enumerate(datagrams):   # paced, so that loopback's socket buffer never overflows
        tx.sendto(d, ('127.0.0.1', port))
        time.sleep(0.0015)
        if k == 300:
            time.sleep(3.0)   # the first fixes load what the command loads lazily (the geoid grid)
    tx.close()
    out, err = proc.communicate(timeout=60)
    return proc.returncode, [json.loads(line) for line in out.splitlines() if line.strip()], err


def test_udp_mavlink_with_an_impossible_system_time(tmp_path):
    """A stream whose SYSTEM_TIME says year 586,000 (time_unix_usec near 2^64): refused, said, and the fixes
    come stamped on arrival instead; no traceback."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    grams = []
    for k in range(40):
        boot = 100.0 + 0.2 * k
        if k % 5 == 0:
            grams.append(mav.system_time_encode(2 ** 64 - 1, int(boot * 1000)).pack(mav))
        grams.append(mav.gps_raw_int_encode(int(boot * 1e6), 3, 471000000 + k, 85000000, 500000, 90, 140, 0, 0, 12,
                                            547000, 1800, 2500).pack(mav))
    rc, rows, err = _fixes_over_udp([bytes(g) for g in grams for _ in range(1)], duration_s=9.0)
    assert rc == 0 and 'Traceback' not in err, err
    assert 'outside 2000-2100' in err
    now = time.time()
    assert rows and all(abs(r['t_unix_s'] - now) < 120 for r in rows)


def test_hostile_udp_mavlink_keeps_every_intact_packet():
    """Garbage, flipped, cut and oversized datagrams and CRC-valid hostile packets (a latitude of 95 deg)
    between the sample flight's packets: every fix of the flight comes out, the hostile one is not used."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from photogram_ros.io.mavlink import read_tlog
    msgs, _ = read_tlog(SAMPLE_BAG / 'flight.tlog')
    msgs = msgs[:len(msgs) // 3]
    rng = np.random.default_rng(7)
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    hostile = bytes(mav.gps_raw_int_encode(1, 3, 950_000_000, 0, 0, 90, 140, 0, 0, 12).pack(mav))
    grams = []
    for k, (m, _) in enumerate(msgs):
        buf = bytes(m.get_msgbuf())
        grams.append(buf)
        if k % 7 == 0:
            grams.append(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8).tobytes())
        if k % 11 == 0:
            flipped = bytearray(buf)
            flipped[len(buf) // 2] ^= 0x5A
            grams.append(bytes(flipped))
        if k % 13 == 0:
            grams.append(buf[:len(buf) // 2])
        if k % 50 == 0:
            grams.append(rng.integers(0, 256, 9000, dtype=np.uint8).tobytes())
        if k % 17 == 0:
            grams.append(hostile)
    from photogram_ros.io.mavlink import FixEvent, Ingest, MavlinkStream, fixes_from_messages
    want = [e for e in fixes_from_messages(msgs)[0] if e.best and e.fix.has_position]
    # The datagrams through the parser as the link hands them over: every fix but the stream's last
    # (completed only by the bytes after it), none of the hostile ones.
    stream, ing, got = MavlinkStream(), Ingest(), []
    for k, g in enumerate(grams):
        for m in stream.feed(g):
            got += [e for e in ing.handle(m, 1e9 + 0.001 * k) if isinstance(e, FixEvent) and e.best]
    assert len(got) >= len(want) - 1 and all(abs(e.fix.lat_deg) < 90 for e in got)
    assert ing.counts['fix_rejected'] >= 1
    # The same over UDP to `fixes udpin:` (a loaded machine's loopback may drop a few datagrams).
    rc, rows, err = _fixes_over_udp(grams, duration_s=20.0)
    assert rc == 0 and 'Traceback' not in err, err
    assert len(rows) >= 0.9 * len(want)
    assert all(abs(r['lat_deg']) < 90 for r in rows)


@pytest.mark.parametrize('kind', ['random', 'empty', 'jpeg'])
def test_fixes_on_something_that_holds_no_mavlink(tmp_path, kind):
    path = tmp_path / f'input.{kind}'
    if kind == 'random':
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 50_000, dtype=np.uint8).tobytes())
    elif kind == 'empty':
        path.write_bytes(b'')
    else:
        shutil.copy(shared_data('photos', 'brighton_beach', 'images', 'DJI_0018.JPG'), path)
    res = cli('fixes', path, timeout=60)
    assert res.returncode == 2 and 'holds no MAVLink' in res.stderr and 'Traceback' not in res.stderr


# --- other bags: NavSatFix topics, ROS 1, recording ------------------------------------------------


def test_fixes_of_a_bag_with_navsatfix_topics_only():
    """A robot's bag with /fix (sensor_msgs/NavSatFix) and no raw MAVLink: its fixes as they are."""
    res = cli('fixes', shared_data('bags', 'husky_gps_imu_sqlite3'), timeout=120)
    assert res.returncode == 0, res.stderr
    rows = res.stdout.strip().splitlines()
    assert len(rows) == 1 + 989 and rows[1].endswith(',/fix') and '989 fixes' in res.stderr


def test_fixes_of_a_ros1_bag(tmp_path):
    """A ROS 1 bag (e.g. mavros's global_position/raw/fix): read through rosbags, converted to ROS 2."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS1_NOETIC)
    NavSatFix, Header, Status = (ts.types[t] for t in ('sensor_msgs/msg/NavSatFix', 'std_msgs/msg/Header',
                                                       'sensor_msgs/msg/NavSatStatus'))
    Time = ts.types['builtin_interfaces/msg/Time']
    path = tmp_path / 'flight.bag'
    t0 = 1_700_000_000
    with Writer(path) as w:
        conn = w.add_connection('/mavros/global_position/raw/fix', 'sensor_msgs/msg/NavSatFix', typestore=ts)
        for k in range(25):
            msg = NavSatFix(Header(k, Time(t0 + k, 0), 'gps'), Status(0, 1), 47.0 + k * 1e-5, 8.5, 500.0 + k,
                            np.array([4.0, 0, 0, 0, 4.0, 0, 0, 0, 9.0]), 2)
            w.write(conn, (t0 + k) * 10 ** 9, ts.serialize_ros1(msg, 'sensor_msgs/msg/NavSatFix'))
    res = cli('fixes', path, '--format', 'jsonl', timeout=120)
    assert res.returncode == 0, res.stderr
    rows = [json.loads(line) for line in res.stdout.splitlines()]
    assert len(rows) == 25 and rows[3]['lat_deg'] == pytest.approx(47.00003) and rows[3]['h_m'] == 503.0
    assert rows[3]['t_unix_s'] == t0 + 3 and rows[3]['var_u_m2'] == 9.0


def test_record_writes_mcap_with_qos_profiles(tmp_path, rclpy_context):
    """`record` writes MCAP (ROS 2 Jazzy's default) and the publishers' QoS profiles (here best effort)."""
    import yaml
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import NavSatFix

    from photogram_ros.io.bag import BagReader
    node = Node('h15_publisher', context=rclpy_context)
    pub = node.create_publisher(NavSatFix, '/h15/fix', qos_profile_sensor_data)
    out = tmp_path / 'rec'
    proc = subprocess.Popen(CLI + ['record', str(out), '--topics', '/h15/fix', '--count', '10'], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while proc.poll() is None and time.monotonic() < deadline:
            pub.publish(NavSatFix(latitude=47.0, longitude=8.5))
            time.sleep(0.05)
        assert proc.wait(timeout=30) == 0, proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
        node.destroy_node()
    assert list(out.glob('*.mcap'))
    with BagReader(out) as bag:
        assert bag.storage == 'mcap' and bag.topics()['/h15/fix'].count >= 10 and not bag.damaged
    meta = yaml.safe_load((out / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    qos = meta['topics_with_message_count'][0]['topic_metadata']['offered_qos_profiles']
    assert len(qos) == 1 and qos[0]['reliability'] == 'best_effort'   # as published


# --- replay output -------------------------------------------------------------------------------


def test_hole_fill_raises_no_floating_point_warning():
    """stereo's hole fill on degenerate windows (matched pixels on lines, no plane) computes no inf - inf
    outside its guarded block (every replay printed "invalid value encountered in add")."""
    from photogram_ros.core.stereo import fill_holes
    rng = np.random.default_rng(1)
    with np.errstate(all='raise'):
        for _ in range(20):
            D = np.full((80, 80), np.nan, np.float32)
            for _ in range(3):
                D[rng.integers(5, 75), 10:70] = 20 + rng.normal(0, 0.1, 60)
            D[10:70, rng.integers(5, 75)] = 25 + np.arange(60) * 1e3
            fill_holes(D, np.ones_like(D, bool), 6.0, 0.5, 4)


def test_sqlite_oracle_agrees_on_an_intact_bag(tmp_path):
    """The oracle of the truncation test counts what our reader counts on the intact bag."""
    db = next(SAMPLE_BAG.glob('*.db3'))
    n = _dump_count(db, tmp_path)
    if n is None:
        pytest.skip('no sqlite3 shell')
    assert n == sqlite3.connect(f'file:{db}?mode=ro', uri=True).execute('SELECT count(*) FROM messages').fetchone()[0]


# --- nothing lost, nothing mixed up --------------------------------------------------


def _publish_while(proc, node, pub, msg_of, until):
    """Publish at 50 Hz until `until()` or the process ends; returns the count published."""
    n = 0
    while proc.poll() is None and not until():
        pub.publish(msg_of(n))
        n += 1
        time.sleep(0.02)
    return n


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_record_killed_with_9_keeps_all_but_its_last_seconds(tmp_path, rclpy_context, storage):
    """`record` killed with -9 (a power loss) after about 8 s of 50 Hz fixes: the bag holds what came
    before its last commit (sqlite3: WAL, commit and checkpoint every second; MCAP: a chunk flushed every
    second), not 0; bag-info says what it holds and that the recording was cut short (exit 3)."""
    from rclpy.node import Node
    from sensor_msgs.msg import NavSatFix

    from photogram_ros.io.bag import BagReader
    node = Node(f'h28_publisher_{storage}', context=rclpy_context)
    pub = node.create_publisher(NavSatFix, '/h28/fix', 10)
    out = tmp_path / 'rec'
    proc = subprocess.Popen(CLI + ['record', str(out), '--topics', '/h28/fix', '--storage', storage,
                                   '--checkpoint', '1'], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        with reaped(proc):
            t0 = time.monotonic()
            _publish_while(proc, node, pub, lambda k: NavSatFix(latitude=47.0, longitude=8.5 + k * 1e-6),
                           lambda: out.exists() or time.monotonic() - t0 > 60)
            assert out.exists(), proc.stderr.read() if proc.poll() is not None else 'no bag folder in 60 s'
            t1 = time.monotonic()
            sent = _publish_while(proc, node, pub, lambda k: NavSatFix(latitude=47.0, longitude=8.5 + k * 1e-6),
                                  lambda: time.monotonic() - t1 > 8.0)
            proc.kill()
            proc.wait(timeout=30)
    finally:
        node.destroy_node()
    assert not (out / 'metadata.yaml').exists()        # cut short: no clean close
    with BagReader(out) as bag:
        got = bag.topics()['/h28/fix'].count
        msgs = list(bag.messages())
    assert len(msgs) == got
    # All but the last seconds: at least what was published up to 3 s before the kill (a checkpoint a second,
    # and on a loaded machine the recorder's executor takes the publisher's messages up to a second late).
    assert got >= sent * (8.0 - 3.0) / 8.0 - 20, (got, sent)
    res = cli('bag-info', out)
    assert res.returncode == 3, res.stdout + res.stderr
    assert f'{got} messages' in res.stdout and ('cut short' in res.stderr), res.stderr


def test_output_folder_is_locked_and_not_reused_silently(tmp_path):
    """A second writer into a locked folder is refused with the owner's pid; a folder holding a previous
    run is refused unless --resume or --overwrite; --overwrite never deletes a folder that is not ours;
    the lock dies with its process (kill -9 included)."""
    from photogram_ros.errors import ConfigError
    from photogram_ros.io.out_dir import LOCK_NAME, claim_output
    out = tmp_path / 'out'
    holder = subprocess.Popen([sys.executable, '-c', 'import sys, time; from photogram_ros.io.out_dir import '
                               'claim_output; l = claim_output(sys.argv[1], command="replay"); print("locked", '
                               'flush=True); time.sleep(60)', str(out)], cwd=ROOT, stdout=subprocess.PIPE, text=True,
                              env={**os.environ, 'PYTHONPATH': str(ROOT)})
    try:
        assert holder.stdout.readline().strip() == 'locked'
        for mode in ('new', 'resume', 'overwrite'):
            with pytest.raises(ConfigError, match=f'being written by another photogram-ros \\(pid {holder.pid}, '
                                                  'replay since'):
                claim_output(out, mode)
        res = cli('replay', SAMPLE_BAG, '--out', out, '--overwrite', '--quiet', timeout=60)
        assert res.returncode == 2 and f'pid {holder.pid}' in res.stderr and len(res.stderr.splitlines()) == 1
    finally:
        holder.kill()
        holder.wait()
    (out / 'map').mkdir()
    (out / 'map' / 'map.json').write_text('{}')
    with pytest.raises(ConfigError, match='holds a previous run \\(map\\): --resume continues its map, --overwrite'):
        claim_output(out)
    with claim_output(out, 'resume') as lock:
        assert lock.previous == ['map'] and (out / 'map' / 'map.json').exists()
    with claim_output(out, 'overwrite'):
        assert not (out / 'map').exists() and (out / LOCK_NAME).exists()
    theirs = tmp_path / 'theirs'
    theirs.mkdir()
    (theirs / 'thesis.tex').write_text('x')
    with pytest.raises(ConfigError, match='not a photogram-ros output folder'):
        claim_output(theirs, 'overwrite')
    assert (theirs / 'thesis.tex').exists() and not (theirs / LOCK_NAME).exists()


@pytest.mark.parametrize('mode', ['--resume', '--overwrite'])
def test_resume_or_overwrite_of_a_folder_that_is_not_ours_is_refused(tmp_path, mode):
    """--resume into a folder no photogram-ros run wrote (no lock file, no map) would write a map among
    the user's files; --overwrite would delete them: both refused, nothing written there."""
    out = tmp_path / 'docs'
    out.mkdir()
    (out / 'notes.txt').write_text('mine')
    res = cli('replay', SAMPLE_BAG, '--out', out, mode, '--quiet', timeout=60)
    assert res.returncode == 2 and 'is not a photogram-ros output folder' in res.stderr, res.stderr
    assert sorted(p.name for p in out.iterdir()) == ['notes.txt']


def test_claim_locks_the_lock_file_the_folder_holds_now(tmp_path, monkeypatch):
    """Two claims at once: a refused claim removes the lock file it created while another claim has it
    open; that one then locks the file the folder holds now, not the removed one (two writers would
    each hold a lock of their own)."""
    import fcntl

    from photogram_ros.errors import ConfigError
    from photogram_ros.io import out_dir
    out = tmp_path / 'o'
    real, calls = fcntl.flock, []

    def flock(fd, op):
        if not calls:   # the refused claim's cleanup, between this claim's open and its flock
            (out / out_dir.LOCK_NAME).unlink()
        calls.append(fd)
        return real(fd, op)
    monkeypatch.setattr(out_dir.fcntl, 'flock', flock)
    lock = out_dir.claim_output(out, 'new', 'test')
    monkeypatch.setattr(out_dir.fcntl, 'flock', real)
    try:
        assert len(calls) == 2 and os.path.samestat(os.fstat(lock.fd), os.stat(out / out_dir.LOCK_NAME))
        with pytest.raises(ConfigError, match='is being written by another photogram-ros'):
            out_dir.claim_output(out, 'resume', 'test')
    finally:
        lock.close()


def test_replay_into_a_folder_another_replay_writes_is_refused(tmp_path):
    """Two `replay`s into one --out at once: the second is refused at once (exit 2, one line); the
    first one goes on; after it, reusing the folder needs --resume or --overwrite."""
    out = tmp_path / 'out'
    first = subprocess.Popen(CLI + ['replay', str(SAMPLE_BAG), '--out', str(out), '--quiet'], cwd=ROOT,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (out / 'map').exists():
            time.sleep(0.2)
        assert (out / 'map').exists()
        second = cli('replay', SAMPLE_BAG, '--out', out, '--quiet', timeout=60)
        assert second.returncode == 2 and 'being written by another photogram-ros' in second.stderr
        assert f'pid {first.pid}' in second.stderr and 'Traceback' not in second.stderr
        assert first.poll() is None
    finally:
        first.kill()
        first.wait()
    again = cli('replay', SAMPLE_BAG, '--out', out, '--quiet', timeout=60)
    assert again.returncode == 2 and 'holds a previous run' in again.stderr and '--resume' in again.stderr


@pytest.mark.parametrize('args, words', [
    (('--out', '{file}'), 'is a file, not a folder'),
    (('--out', '{file}/sub'), 'cannot be created (a part of the path is a file)'),
    (('--out', '/proc/photogram/out'), 'cannot be created'),
    (('--rate', 'fast'), "invalid float value: 'fast'"),
    (('--domain', '300'), '--domain=300 is out of range')])
def test_bad_arguments_are_one_line_and_exit_2(tmp_path, args, words):
    f = tmp_path / 'a_file'
    f.write_text('x')
    args = [a.replace('{file}', str(f)) for a in args]
    if '--out' not in args:
        args += ['--out', str(tmp_path / 'o')]
    res = cli('replay', SAMPLE_BAG, *args, '--quiet', timeout=60)
    assert res.returncode == 2 and words in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and 'Traceback' not in res.stderr


@pytest.mark.parametrize('args, words', [
    (('simulate', '{o}', '--gap', 'abc'), '--gap \'abc\': give FROM:TO pairs'),
    (('simulate', '{o}', '--outage', '20'), '--outage \'20\': give FROM:TO pairs'),
    (('simulate', '{o}', '--corrupt-mavlink', '1:2:3'), 'give FROM:TO pairs'),
    (('simulate', '{o}', '--gap', '5:3'), '0 <= FROM < TO'),
    (('simulate', '{o}', '--size', '12'), '--size \'12\': give WIDTHxHEIGHT'),
    (('simulate', '{o}', '--black', 'x'), '--black \'x\': not a number'),
    (('simulate', '{o}', '--repeats', '0'), '--repeats 0'),
    (('simulate', '{o}', '--drop', '2'), '--drop 2.0: a fraction'),
    (('simulate', '{o}', '--tilt', '200'), '--tilt 200.0: degrees from nadir'),
    (('simulate', '{o}', '--gnss-change', '30:bogus'), "unknown GNSS mode 'bogus'"),
    (('record', '{o}', '--topics', ' , '), '--topics names no topic'),
    (('record', '{o}', '--topics', '/a', '--duration', '-1'), '--duration -1'),
    (('record', '{o}', '--topics', '/a', '--count', '-1'), '--count -1'),
    (('record', '{o}', '--topics', '/a', '--discovery-timeout', '-1'), '--discovery-timeout -1'),
    (('ground-station', '--out', '{o}', '--duration', '-1'), '--duration -1'),
    (('ground-station', '--out', '{o}', '--web', '127.0.0.1:99999'), "--web '127.0.0.1:99999'"),
    (('run', '--namespace', 'bad ns!', '--nodes', 'mavlink', '--out', '{o}'), "--namespace 'bad ns!' is not a ROS 2"),
    (('replay', str(SAMPLE_BAG), '--out', '{o}', '--rate', '-1'), '--rate -1'),
    (('replay', str(SAMPLE_BAG), '--out', '{o}', '--rate', 'nan'), '--rate nan'),
    (('replay', str(SAMPLE_BAG), '--out', '{o}', '--min-pairs', '0'), '--min-pairs 0'),
    (('replay', str(SAMPLE_BAG), '--out', '{o}', '--child-nodes', 'tracker'), '--child-nodes'),
    (('replay', str(SAMPLE_BAG), '--out', '{o}', '--domain', '-1'), '--domain=-1 is out of range'),
    (('export', str(SAMPLE_BAG), '--crs', 'EPSG:32632', '--out', '{o}', '--dsm-res-m', '-1'), '--dsm-res-m -1'),
    (('export', str(SAMPLE_BAG), '--crs', 'EPSG:32632', '--out', '{o}', '--contours-m', 'nan'), '--contours-m nan'),
    (('calibrate', str(SAMPLE_BAG / 'metadata.yaml'), '--min-views', '0', '--out', '{o}'), '--min-views 0'),
    (('fixes', 'udpin:127.0.0.1:14999', '--sysid', '999'), '--sysid 999: choose 0 to 255'),
    (('fixes', 'udpin:127.0.0.1:14999', '--duration', '-1'), '--duration -1'),
    (('play', str(SAMPLE_BAG), '--remap', '/a:='), "remap '/a:=' must look like /from:=/to"),
    (('triangulate', str(SAMPLE_BAG), '--out', '{o}', '--window', '-3'), "'window_size' = -3 is outside [2, 200]")])
def test_every_commands_bad_arguments_are_one_line_and_exit_2(tmp_path, args, words):
    """Values argparse takes but the command cannot use: said at once (exit 2, one line, no traceback),
    before any process or folder is made."""
    out = tmp_path / 'o'
    res = cli(*[a.replace('{o}', str(out)) for a in args], timeout=60)
    assert res.returncode == 2 and words in res.stderr, res.stderr[-2000:]
    assert len(res.stderr.strip().splitlines()) == 1 and 'Traceback' not in res.stderr, res.stderr[-2000:]
    assert not out.exists()


@pytest.mark.parametrize('sig, status', [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_command_stopped_before_it_handles_signals_says_so(tmp_path, sig, status):
    """SIGTERM or SIGINT to a command that has no stop of its own (simulate, triangulate, a `run` still
    starting): one line naming the signal, exit 128 + its number, not a silent end."""
    proc = subprocess.Popen(CLI + ['simulate', str(tmp_path / 'sim'), '--preset', 'tiny'], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with reaped(proc):
        assert 'rendered' in proc.stderr.read(len('\rrendered'))   # it is working
        proc.send_signal(sig)
        err = proc.communicate(timeout=60)[1]
    assert proc.returncode == status and err.strip().splitlines()[-1].endswith(f'simulate: stopped by {sig.name}')
    assert 'Traceback' not in err


@pytest.mark.parametrize('rate', ['0.0', '1.0'])
def test_run_separate_with_a_photo_folder_is_refused(tmp_path, rate):
    """`run --separate` cannot hold a photo folder to the tracker: the camera process would publish its
    photos (at rate 0 all at once) while the tracker process starts and end the flight before the tracker
    took one ("the tracker took no keyframe", exit 0). Refused before anything starts."""
    photos = tmp_path / 'photos'
    photos.mkdir()
    cfg = tmp_path / 'photos.yaml'
    cfg.write_text(f'camera_node:\n  ros__parameters:\n    source: {photos}\n    rate: {rate}\n'
                   f'map_node:\n  ros__parameters:\n    map_dir: {tmp_path / "map"}\n')
    res = cli('run', '--separate', '--params', cfg, '--nodes', 'camera,tracker,bundle,stereo,map',
              '--out', tmp_path / 'products', timeout=60)
    assert res.returncode == 2 and '--separate with camera_node playing a photo folder' in res.stderr, \
        res.stderr[-2000:]
    assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / 'map').exists()


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_record_killed_before_its_first_message_is_said_to_be_cut_short(tmp_path, storage):
    """kill -9 of `record` before its first message: bag-info says the recording was cut short (exit 3),
    not "0 messages" with exit 0, whatever the storage."""
    out = tmp_path / 'bag'
    proc = subprocess.Popen(CLI + ['record', str(out), '--topics', '/h28/nobody', '--storage', storage], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    with reaped(proc):
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not any(out.glob(f'*.{"db3" if storage == "sqlite3" else "mcap"}')):
            time.sleep(0.1)
        time.sleep(2.0)   # its tables written: the recorder waits for the topic (discovery, 10 s)
        proc.kill()
        proc.wait()
    res = cli('bag-info', out, timeout=60)
    assert res.returncode == 3, res.stdout + res.stderr
    assert 'cut short' in res.stderr and '0 messages' in res.stdout, res.stderr


@pytest.mark.parametrize('link, words', [('/dev/ttyPHOTOGRAM9', 'no such device'),
                                         ('tcp:no-such-host.invalid:5760', 'cannot open MAVLink link')])
def test_fixes_on_a_link_that_cannot_open_says_why_and_keeps_stdout_clean(link, words):
    """A serial device that is not there, a host that does not resolve: one line on stderr, exit 2, and
    nothing but the CSV header on stdout (pymavlink printed its retries there, among the rows)."""
    res = cli('fixes', link, '--duration', '1', timeout=60)
    assert res.returncode == 2 and words in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert res.stdout.strip().splitlines() == [res.stdout.strip().splitlines()[0]]
    assert res.stdout.startswith('t_unix_s,')


def test_record_leaves_no_empty_bag_when_no_topic_appears(tmp_path):
    res = cli('record', tmp_path / 'bag', '--topics', '/h28/nobody', '--discovery-timeout', '1', timeout=60)
    assert res.returncode == 2 and "none of the topics ['/h28/nobody'] appeared" in res.stderr, res.stderr
    assert not (tmp_path / 'bag').exists()


def test_a_second_replay_on_a_shared_domain_is_refused(tmp_path):
    """`replay --domain N` holds N as a replay's own domain is held: a second replay on N (both trackers
    would take both flights' frames) is refused at once, and N is free again when the first ends."""
    code = ('import time; from photogram_ros.nodes.ros_domain import shared_domain; '
            'print(shared_domain(%d), flush=True); time.sleep(30)')
    mine = int(os.environ['ROS_DOMAIN_ID'])
    holder = subprocess.Popen([sys.executable, '-c', code % mine], cwd=ROOT, stdout=subprocess.PIPE, text=True,
                              env={**os.environ, 'PYTHONPATH': str(ROOT)})
    with reaped(holder):
        assert int(holder.stdout.readline()) == mine
        res = cli('replay', SAMPLE_BAG, '--out', tmp_path / 'o', '--domain', mine, '--quiet', timeout=60)
        assert res.returncode == 2 and f'another replay on this machine plays on ROS_DOMAIN_ID {mine}' in res.stderr
        assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / 'o').exists()
    again = subprocess.run([sys.executable, '-c', code.replace('time.sleep(30)', 'pass') % mine], cwd=ROOT,
                           capture_output=True, text=True, env={**os.environ, 'PYTHONPATH': str(ROOT)}, timeout=60)
    assert again.stdout.strip() == str(mine), again.stderr   # freed with its process


@pytest.mark.parametrize('command', [['replay', str(SAMPLE_BAG), '--quiet'], ['play', str(SAMPLE_BAG)],
                                     ['record', 'x', '--topics', '/a'], ['run']])
@pytest.mark.parametrize('domain', ['233', 'abc'])
def test_ros_domain_id_out_of_range_is_one_line(tmp_path, command, domain):
    res = cli(*command, timeout=60, env={**os.environ, 'ROS_DOMAIN_ID': domain}, )
    assert res.returncode == 2 and 'ROS_DOMAIN_ID' in res.stderr and '0 to 232' in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and 'port number' not in res.stderr


def test_replays_take_domains_of_their_own():
    """Two replays on one machine never share a domain (held with flock for the process's life), and
    never take the user's own."""
    from photogram_ros.nodes import ros_domain
    code = ('import time; from photogram_ros.nodes.ros_domain import own_domain; '
            'print(own_domain(avoid=%d), flush=True); time.sleep(30)')
    mine = int(os.environ['ROS_DOMAIN_ID'])
    procs = [subprocess.Popen([sys.executable, '-c', code % mine], cwd=ROOT, stdout=subprocess.PIPE, text=True,
                              env={**os.environ, 'PYTHONPATH': str(ROOT)}) for _ in range(3)]
    try:
        got = [int(p.stdout.readline()) for p in procs]
    finally:
        for p in procs:
            p.kill()
            p.wait()
    assert len(set(got)) == 3 and all(d in ros_domain.OWN_DOMAINS and d != mine for d in got)
    # Freed with its process: one of them is free again.
    d = ros_domain.own_domain(avoid=mine)
    assert d in ros_domain.OWN_DOMAINS


@pytest.mark.parametrize('share', [False, True])
def test_replay_is_not_heard_on_the_users_domain(tmp_path, rclpy_context, share):
    """A replay started from a terminal (the user's ROS_DOMAIN_ID) plays on a domain of its own: nothing
    of it shows on the user's graph (before, two replays heard each other, and a drone on the domain would
    hear the old flight); it says which domain, and --domain shares one."""
    from rclpy.node import Node
    mine = int(os.environ['ROS_DOMAIN_ID'])
    proc = subprocess.Popen(CLI + ['replay', str(SAMPLE_BAG), '--out', str(tmp_path / 'o')]
                            + (['--domain', str(mine)] if share else []), cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    node = Node('h28_listener', context=rclpy_context)
    try:
        line = ''
        for line in proc.stdout:
            if 'replaying on ROS_DOMAIN_ID' in line or line.startswith('replay: '):
                break
        if not share:
            domain = int(line.split('ROS_DOMAIN_ID')[1].split(',')[0])
            assert domain != mine and 215 <= domain <= 232
        for line in proc.stdout:   # the replay is playing frames now
            if line.startswith('replay: '):
                break
        seen = set()
        for _ in range(20):
            time.sleep(0.25)
            seen |= {i.node_name for t in ('/camera/image_raw/compressed', '/mavlink/from_fcu', '/diagnostics')
                     for i in node.get_publishers_info_by_topic(t)}
        seen.discard('h28_listener')
        assert bool(seen) == share, seen
    finally:
        # The listener goes first, then the replay ends as a user ends it (SIGTERM): a peer killed on this
        # session's domain can leave DDS waiting on it when a node of this process is destroyed.
        node.destroy_node()
        proc.terminate()
        try:
            proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()


def test_a_second_publisher_of_a_graph_topic_is_a_warning(rclpy_context):
    """A live graph that hears another node of its own name publish its topics (a second mapper on the
    domain) says so at WARN on /diagnostics, naming the topic and what to do."""
    from rclpy.node import Node

    from photogram_ros.nodes.diagnostics import WARN
    from photogram_ros.nodes.graph import Graph, GraphSpec, duplicate_publishers
    graph = Graph(GraphSpec(roles=('tracker',)), context=rclpy_context)
    graph.start(watch_period_s=0.3)
    tracker = graph.nodes['tracker']
    pub = next(p for p in tracker.publishers if p.topic_name not in ('/diagnostics', '/rosout', '/parameter_events'))
    other = Node(tracker.get_name(), context=rclpy_context)
    try:
        time.sleep(1.0)
        assert not any('also publishes' in p for p in tracker.diag.recent_problems(20))
        other.create_publisher(pub.msg_type, pub.topic_name, 10)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not any('also publishes' in p for p in tracker.diag.recent_problems(20)):
            time.sleep(0.2)
        said = [p for p in tracker.diag.recent_problems(20) if 'also publishes' in p]
        assert said and pub.topic_name in said[0] and 'ROS_DOMAIN_ID' in said[0]
        assert tracker.diag.status().level == WARN
        assert duplicate_publishers(other)   # the other one hears it too
    finally:
        other.destroy_node()
        graph.shutdown()


@pytest.fixture(scope='module')
def photo_survey(tmp_path_factory):
    """The simulator's tiny survey as geotagged photos (about 25)."""
    from photogram_ros.sim.scenario import preset, simulate
    out = tmp_path_factory.mktemp('run_photos') / 'tiny'
    simulate(preset('tiny', photos=True, fps=1.0, line_length_m=30.0), out)
    return out / 'photos'


def _run_photos(tmp_path, photos, stop_after_keyframes=0):
    cfg = tmp_path / 'photos.yaml'
    cfg.write_text(f'camera_node:\n  ros__parameters:\n    source: {photos}\n    rate: 0.0\n'
                   f'map_node:\n  ros__parameters:\n    map_dir: {tmp_path / "map"}\n')
    proc = subprocess.Popen(CLI + ['run', '--params', str(cfg), '--nodes', 'camera,tracker,bundle,stereo,map',
                                   '--out', str(tmp_path / 'products')], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    with reaped(proc):
        if stop_after_keyframes:
            deadline = time.monotonic() + 300
            while time.monotonic() < deadline and proc.poll() is None and \
                    len(list((tmp_path / 'map' / 'keyframes').glob('*'))) < stop_after_keyframes:
                time.sleep(0.2)
            proc.send_signal(signal.SIGTERM)
        out = proc.communicate(timeout=900)[0]
    report = json.loads((tmp_path / 'products' / 'report.json').read_text())
    return proc.returncode, out, report


@pytest.mark.slow
def test_run_on_a_photo_folder_maps_every_photo_before_the_flight_ends(tmp_path, photo_survey):
    """`run` with camera_node on a photo folder at rate 0: each photo waits for the tracker, the end of
    the source drains tracker, bundle, stereo and map before the final adjustment, and the products and
    the report's accounting are those of a replay of the same folder (before: most photos dropped, "the
    tracker took no keyframe", no products)."""
    n = len(list(photo_survey.glob('*.JPG')))
    rc, out, report = _run_photos(tmp_path, photo_survey)
    assert rc == 0, out[-3000:]
    assert 'end of the camera source: waiting for the tracker' in out
    assert report['run']['frames'] == n and report['run']['ended_by'] == 'end of the camera source'
    assert 0.7 * n <= report['keyframes_taken'] <= n
    assert report['keyframes_oriented'] >= 0.9 * report['keyframes_taken'], report['mapping']
    assert report['mapping']['mapped'] and report['run']['products_from'] == 'final adjustment (map_final)'
    assert report['run']['bag_s'] > 0 and report['nodes']['/camera_node']['values']['frames'] == n
    assert (tmp_path / 'products' / 'dsm.tif').exists()


@pytest.mark.slow
def test_run_stopped_by_sigterm_reports_what_the_nodes_did(tmp_path, photo_survey):
    """SIGTERM in the middle of a photo folder: the report counts the frames and keyframes the nodes
    handled (not "0 frames, 0.0 s of flight", not "the tracker took no keyframe")."""
    n = len(list(photo_survey.glob('*.JPG')))
    rc, out, report = _run_photos(tmp_path, photo_survey, stop_after_keyframes=4)
    assert rc == 0, out[-3000:]
    assert 'SIGTERM: ending the flight' in out
    assert report['run']['ended_by'] == 'SIGTERM' and 4 <= report['run']['frames'] < n
    assert report['keyframes_taken'] >= 4 and report['keyframes_oriented'] >= 3
    assert 'took no keyframe' not in ' '.join(report['mapping']['failures'])
    md = (tmp_path / 'products' / 'report.md').read_text()
    assert f"{report['run']['frames']} frames" in md and ' 0.0 s of flight' not in md


@pytest.mark.slow
@pytest.mark.parametrize('form', ['no metadata.yaml', 'bare .db3'])
def test_triangulate_reads_a_bag_without_metadata(tmp_path, tiny_flight, form):
    """A recording cut short has no metadata.yaml; bag-info and replay read it from its storage file, and
    so does triangulate now (before: taken for a photo folder and refused); a bare .db3 file too."""
    bag = tmp_path / 'tiny'
    shutil.copytree(tiny_flight, bag)
    (bag / 'metadata.yaml').unlink()
    src = bag if form == 'no metadata.yaml' else next(bag.glob('*.db3'))
    res = cli('triangulate', src, '--out', tmp_path / 'at', timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    assert 'metadata.yaml is missing' in res.stderr or form == 'bare .db3'
    n = int(res.stdout.split('oriented ')[1].split('/')[0])
    assert n >= 10 and (tmp_path / 'at' / 'report.md').exists()


def test_export_densify_after_a_kill_does_not_call_in_flight_poses_final(stopped_run, tmp_path):
    """kill -9 during the final adjustment leaves no flight_end.json: `export --densify` says it matched
    the in-flight poses, and why; with the final adjustment recorded as done it says final poses."""
    from photogram_ros.commands.export import poses_label
    map_dir = tmp_path / 'map'
    shutil.copytree(stopped_run[3], map_dir)
    (map_dir / 'flight_end.json').unlink()
    res = cli('export', map_dir, '--densify', '--crs', 'EPSG:32632', '--out', tmp_path / 'out', '--min-pairs', '1',
              timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    assert 'from the in-flight poses (the flight did not end cleanly' in res.stdout and 'final poses' not in res.stdout
    assert poses_label({'final_adjustment': 'done'}) == 'the final poses (final adjustment)'
    assert 'final adjustment failed: x' in poses_label({'final_adjustment': 'failed', 'reason': 'x'})
    assert 'final poses' not in poses_label({'final_adjustment': 'none', 'reason': 'no keyframe was oriented'})


# GCP rows as a surveyor's spreadsheet holds them: (name, marker id, x, y, z, sigma_h, sigma_v).
_GCP_ROWS = [('GCP01', 0, 465698.587, 5249464.825, 489.927, 0.01, 0.02),
             ('Pünkt2', 3, 465728.125, 5249504.5, 491.5, 0.015, 0.03),
             ('CHK01', 7, 465708.0, 5249474.25, 489.0, 0.01, 0.02)]


def _gcp_text(sep=' ', decimal='.', crs_pad='', header=False):
    def num(v):
        return repr(float(v)).replace('.', decimal)
    lines = ['EPSG:32632' + crs_pad] + ([sep.join(['name', 'marker_id', 'x', 'y', 'z', 'sigma_h_m', 'sigma_v_m'])]
                                       if header else []) + [sep.join([n, str(m)] + [num(v) for v in vals]) for n, m, *vals in _GCP_ROWS]
    return '\r\n'.join(lines) + '\r\n'


@pytest.mark.parametrize('form, data', [
    ('Excel CSV UTF-8 (BOM)', lambda: b'\xef\xbb\xbf' + _gcp_text(',').encode()),
    ('Excel Unicode text (UTF-16 LE, BOM, tabs)', lambda: _gcp_text('\t').encode('utf-16')),
    ('UTF-16 BE without BOM', lambda: _gcp_text(' ').encode('utf-16-be')),
    ('European Excel CSV: ";" and decimal commas, padded CRS row',
     lambda: _gcp_text(';', ',', ';;;;;;').encode('cp1252')),
    ('blanks and decimal commas', lambda: _gcp_text(' ', ',').encode()),
    ('tabs, decimal commas, UTF-8 BOM', lambda: b'\xef\xbb\xbf' + _gcp_text('\t', ',').encode()),
    ('Windows-1252', lambda: _gcp_text(' ').encode('cp1252')),
    ('";" with a header row', lambda: _gcp_text(';', '.', ';;;;;;', header=True).encode())])
def test_control_files_from_spreadsheets_are_read(tmp_path, form, data):
    """GCP files as spreadsheets and editors save them (before: a BOM gave "'EPSG:32632' is not a
    coordinate reference system", UTF-16 and decimal commas messages that did not say why): the same
    targets as the plain file, to the digit."""
    from photogram_ros.io.control_file import read_control_file
    plain = tmp_path / 'plain.txt'
    plain.write_text(_gcp_text(), encoding='utf-8')
    f = tmp_path / 'odd.txt'
    f.write_bytes(data())
    want, got = read_control_file(plain), read_control_file(f)
    assert got.crs == 'EPSG:32632' and [t.name for t in got.targets] == ['GCP01', 'Pünkt2', 'CHK01']
    assert [t.marker_id for t in got.targets] == [0, 3, 7]
    for a, b in zip(want.targets, got.targets):
        assert (b.lat_deg, b.lon_deg, b.h_m, b.sigma_h_m, b.sigma_v_m) == (a.lat_deg, a.lon_deg, a.h_m, a.sigma_h_m,
                                                                           a.sigma_v_m)
    assert got.targets[0].h_m == pytest.approx(489.927, abs=1e-9)


@pytest.mark.parametrize('data, words', [
    (lambda: b'PK\x03\x04' + bytes(range(256)) * 4, 'spreadsheet (.xlsx) rather than text'),
    (lambda: _gcp_text(',', ',').encode(), 'decimal commas as well as column separators'),
    (lambda: b'\xff\xfe' + b'E\x00P\x00\x00\xd8', 'looks like UTF-16'),
    (lambda: b'\xd0\xcf\x11\xe0\xa1\xb1\x1a\xe1' + bytes(512), 'Excel 97-2003 spreadsheet (.xls) rather than text'),
    (lambda: _gcp_text(';', ',', ';;;;;;').replace('465698,587', '465.698,587').encode(),
     "'465.698,587' has a thousands separator")])
def test_control_files_that_cannot_be_read_say_why(tmp_path, data, words):
    from photogram_ros.errors import DataError
    from photogram_ros.io.control_file import read_control_file
    f = tmp_path / 'targets.csv'
    f.write_bytes(data())
    with pytest.raises(DataError, match=re.escape(words)):
        read_control_file(f)
    res = cli('replay', SAMPLE_BAG, '--out', tmp_path / 'o', '--gcp', f, '--quiet', timeout=60)
    assert res.returncode == 2 and words in res.stderr and len(res.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize('feed, words', [('forged', "wrong signature so far (signing_key differs"),
                                         ('plain', 'unsigned so far (the autopilot does not sign'),
                                         ('noise', 'no packet decodes (a wrong baud rate'),
                                         ('good', None)])
def test_mavlink_node_that_gets_nothing_usable_warns_with_the_reason(rclpy_context, feed, words):
    """A wrong signing key rejects every packet (right), and /diagnostics now says WARN and why, instead
    of OK with no GNSS at all; so do an unsigned autopilot and bytes that hold no MAVLink."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from photogram_ros.io.mavlink import signing_key
    from photogram_ros.nodes.diagnostics import OK, WARN
    from photogram_ros.nodes.mavlink_node import MavlinkNode
    from test_mavlink_node import _gps_stream

    def signed(key):
        mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.timestamp = key, True, 1
        return mav
    data = {'good': lambda: _gps_stream(signed(signing_key('fleet secret')), lat0=471000000),
            'forged': lambda: _gps_stream(signed(signing_key('guess')), lat0=471000000),
            'plain': lambda: _gps_stream(mavlink2.MAVLink(None, srcSystem=1, srcComponent=1), lat0=471000000),
            'noise': lambda: np.random.default_rng(3).integers(0, 256, 4000, dtype=np.uint8).tobytes()
            .replace(b'\xfd', b'\x00').replace(b'\xfe', b'\x00')}[feed]()
    node = MavlinkNode({'signing_key': 'fleet secret', 'diagnostics_period_s': 60.0}, context=rclpy_context)
    try:
        node.diag.status()   # the start's status out of the way
        node.feed(data, None)
        node._update_diagnostics()
        st = node.diag.status()
        if words is None:
            assert st.level == OK and node.published['fix'] == 10, st.message
        else:
            assert st.level == WARN and words in st.message and node.published['fix'] == 0, st.message
            said = node.diag.counts()['problems']
            node._update_diagnostics()   # nothing new arrived: nothing new to say
            assert node.diag.counts()['problems'] == said
    finally:
        node.destroy_node()


def test_wrong_signing_key_warns_although_a_radios_unsigned_packets_pass(rclpy_context):
    """A wrong signing key with allow_unsigned: the autopilot's signed packets are all rejected while a
    telemetry radio's unsigned RADIO_STATUS pass; no fix, no attitude: WARN with the reason."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from photogram_ros.io.mavlink import signing_key
    from photogram_ros.nodes.diagnostics import WARN
    from photogram_ros.nodes.mavlink_node import MavlinkNode
    from test_mavlink_node import _gps_stream
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.timestamp = signing_key('guess'), True, 1
    radio = mavlink2.MAVLink(None, srcSystem=51, srcComponent=68)
    status = b''.join(radio.radio_status_encode(200, 190, 100, 40, 38, 0, 0).pack(radio) for _ in range(5))
    node = MavlinkNode({'signing_key': 'fleet secret', 'allow_unsigned': True, 'diagnostics_period_s': 60.0},
                       context=rclpy_context)
    try:
        node.diag.status()
        node.feed(_gps_stream(mav, lat0=471000000) + status, None)
        node._update_diagnostics()
        st = node.diag.status()
        assert node.stream.stats.packets >= 5 and node.published['fix'] == 0
        assert st.level == WARN and 'wrong signature so far (signing_key differs' in st.message, st.message
    finally:
        node.destroy_node()


def test_tile_url_with_a_5000_digit_zoom_is_a_404_not_a_traceback(capsys):
    import urllib.error
    import urllib.request

    from photogram_ros.web.server import WebServer
    from test_ground_page import Provider
    srv = WebServer(Provider(), '127.0.0.1', 0).start()
    try:
        for path in (f'tiles/drone1/{"9" * 5000}/1/1.png', f'tiles/drone1/19/{"7" * 400}/1.png'):
            with pytest.raises(urllib.error.HTTPError) as exc:
                urllib.request.urlopen(srv.url + path, timeout=10)
            assert exc.value.code == 404
        with urllib.request.urlopen(srv.url + 'status.json', timeout=10) as r:   # still serving
            assert r.status == 200
    finally:
        srv.stop()
    assert 'Traceback' not in capsys.readouterr().err


@pytest.mark.parametrize('command', [['triangulate', str(SAMPLE_BAG), '--out', '{out}'],
                                     ['ground-station', '--out', '{out}', '--duration', '1'],
                                     ['record', '{out}', '--topics', '/a', '--discovery-timeout', '1']])
def test_out_path_that_is_a_file_is_one_line_without_traceback(tmp_path, command):
    f = tmp_path / 'a_file'
    f.write_text('x')
    out = f if command[0] != 'record' else f / 'bag'
    res = cli(*[c.replace('{out}', str(out)) for c in command], timeout=120)
    assert res.returncode == 2 and 'Traceback' not in res.stderr, res.stderr[-2000:]
    last = res.stderr.strip().splitlines()[-1]
    assert str(f) in last and ('a file' in last or 'is a file' in last), last


class _Counts:
    """Graph.drain's inputs, scripted: counters per call, and whether a node is busy."""

    def __init__(self, script):
        self.script, self.k = script, 0

    def __call__(self):
        c = self.script(self.k)
        self.k += 1
        return c


def _graph(counts, busy=lambda: False):
    from photogram_ros.nodes.graph import Graph
    g = Graph.__new__(Graph)
    g.counts, g.busy = counts, busy
    return g


def _child_graph(code: str):
    """A ChildGraph whose child is `code` in a Python process and whose status comes from a thread
    (counters that never move, one status every 0.1 s), with no ROS."""
    from photogram_ros.nodes.graph import ChildGraph
    g = ChildGraph.__new__(ChildGraph)
    g._status, g._cond, g._seq = {'counts': {'map': {'clouds': 3}}, 'busy': False, 'done': 0}, threading.Condition(), 0
    g._status_at = time.monotonic()
    g._send = lambda **command: 1
    g.proc = subprocess.Popen([sys.executable, '-c', code])
    stop = threading.Event()

    def status():
        while not stop.wait(0.1):
            with g._cond:
                g._status_at = time.monotonic()
                g._cond.notify_all()
    threading.Thread(target=status, daemon=True).start()
    return g, stop


@pytest.mark.parametrize('code, words', [
    ('import time; time.sleep(60)', 'made no progress for 2 s'),          # waiting on a timeout
    ('while True: pass', 'did not finish in 5 s')])                        # computing (a final adjustment)
def test_an_end_of_flight_step_in_the_child_is_waited_for_while_it_works(code, words):
    """An end-of-flight step in the replay's child process is waited for while the child works (a counter
    moves, a node is busy, or it computes: CPU time) and no longer than `stall_s` once it does nothing;
    the wait says what it waits for every 10 s, and does not sit out a fixed 600 s."""
    g, stop = _child_graph(code)
    said = []
    try:
        with reaped(g.proc), pytest.raises(RuntimeError, match=re.escape(words)):
            g.call('stereo', 'flush', timeout_s=5.0, stall_s=2.0, say=said.append)
    finally:
        stop.set()


def test_the_player_stops_holding_back_for_a_stalled_node():
    """The player holds the flight while a node lags the tracker by more than max_lag_keyframes; a
    node that has stalled (no mapping counter moves, nothing busy, its process not computing) ends
    that wait after lag_stall_s (WorkWatch) instead of frame_timeout_s (30 s) at every new keyframe."""
    from photogram_ros.nodes.graph import WorkWatch
    stalled = _graph(_Counts(lambda k: {'tracker': {'keyframes': 40}, 'stereo': {'images': 5, 'pairs_done': 4}}))
    stalled.child = None
    watch = WorkWatch(stalled, period_s=0.05)
    t0 = time.monotonic()
    while watch.idle_s() < 0.5 and time.monotonic() - t0 < 30:
        time.sleep(0.01)
    assert watch.idle_s() >= 0.5      # the stalled node is seen idle (not the 30 s give-up)
    working = _graph(_Counts(lambda k: {'tracker': {'keyframes': 40}, 'stereo': {'images': 5, 'pairs_done': k}}))
    working.child = None
    watch = WorkWatch(working, period_s=0.05)
    time.sleep(0.6)
    assert watch.idle_s() < 0.2   # a counter moves: it works
    busy = _graph(_Counts(lambda k: {'stereo': {'pairs_done': 4}}), busy=lambda: True)
    busy.child = None
    watch = WorkWatch(busy, period_s=0.05)
    time.sleep(0.6)
    assert watch.idle_s() < 0.2   # a node computes in its own thread


def test_drain_does_not_wait_its_timeout_on_work_lost_between_nodes():
    """Two keyframes counted as published by the tracker never reach the bundle adjuster (lost on the
    way) and nothing moves: the end of flight waits stall_s for them, says so, and goes on; before, it
    waited the whole drain timeout (300 s) on a counter, at each of the end-of-flight steps."""
    said = []
    lost = _graph(_Counts(lambda k: {'tracker': {'keyframes': 12}, 'bundle': {'keyframes_received': 10}}))
    left = lost.drain(quiet_s=0.3, timeout_s=120.0, stall_s=1.0, say=said.append)
    assert left == {'keyframes not yet at the bundle adjuster': 2}
    assert said and 'nothing moved for 1 s with 2 keyframes not yet at the bundle adjuster' in said[-1]
    # Work that moves is waited for: the bundle receives one keyframe a call until all 12 are in.
    moving = _graph(_Counts(lambda k: {'tracker': {'keyframes': 12},
                                       'bundle': {'keyframes_received': min(12, k // 5)}}))
    assert moving.drain(quiet_s=0.3, timeout_s=120.0, stall_s=1.0) == {}
    assert moving.counts.k >= 60
    # A busy node (the final adjustment) is not given up on while it computes, counters still.
    t_end = time.monotonic() + 2.5
    busy = _graph(_Counts(lambda k: {'tracker': {'keyframes': 12},
                                     'bundle': {'keyframes_received': 12 if time.monotonic() > t_end else 10}}),
                  busy=lambda: time.monotonic() < t_end)
    assert busy.drain(quiet_s=0.3, timeout_s=120.0, stall_s=1.0) == {}


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_record_stopped_by_sigterm_closes_a_complete_bag(tmp_path, rclpy_context, storage):
    """SIGTERM (a supervisor's stop) ends `record` like Ctrl-C: exit 0, metadata.yaml written, nothing lost
    or damaged; a sqlite3 bag is a plain database again (no -wal beside it)."""
    from rclpy.node import Node
    from sensor_msgs.msg import NavSatFix

    from photogram_ros.io.bag import BagReader
    node = Node(f'h28_term_{storage}', context=rclpy_context)
    pub = node.create_publisher(NavSatFix, '/h28/term', 10)
    out = tmp_path / 'rec'
    proc = subprocess.Popen(CLI + ['record', str(out), '--topics', '/h28/term', '--storage', storage], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        _publish_while(proc, node, pub, lambda k: NavSatFix(latitude=47.0), lambda: out.exists()
                       or time.monotonic() - t0 > 60)
        t1 = time.monotonic()
        _publish_while(proc, node, pub, lambda k: NavSatFix(latitude=47.0), lambda: time.monotonic() - t1 > 3.0)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        node.destroy_node()
    assert proc.returncode == 0, stderr
    n = int(stdout.split('recorded ')[1].split()[0])
    assert n > 50 and (out / 'metadata.yaml').exists() and not list(out.glob('*-wal'))
    with BagReader(out) as bag:
        assert not bag.damaged and bag.topics()['/h28/term'].count == n == bag.topics()['/h28/term'].expected
    if storage == 'sqlite3':
        db = next(out.glob('*.db3'))
        assert sqlite3.connect(db).execute('PRAGMA journal_mode').fetchone()[0] == 'delete'


def test_run_refuses_a_locked_or_finished_map_folder(tmp_path):
    """`run` into a map folder another process writes: refused at once with its pid; a finished flight's map
    (flight_end.json) needs --resume or --overwrite; a map left by a crash (no flight_end.json) is resumed."""
    from photogram_ros.io.map_store import MapStore
    map_dir = tmp_path / 'map'
    cfg = tmp_path / 'onboard.yaml'
    cfg.write_text(f'map_node:\n  ros__parameters:\n    map_dir: {map_dir}\n')
    holder = subprocess.Popen([sys.executable, '-c', 'import sys, time; from photogram_ros.io.out_dir import '
                               'claim_output; l = claim_output(sys.argv[1], command="run"); print("locked", '
                               'flush=True); time.sleep(60)', str(map_dir)], cwd=ROOT, stdout=subprocess.PIPE,
                              text=True, env={**os.environ, 'PYTHONPATH': str(ROOT)})
    try:
        assert holder.stdout.readline().strip() == 'locked'
        res = cli('run', '--params', cfg, '--out', tmp_path / 'products', timeout=60)
        assert res.returncode == 2 and f'pid {holder.pid}, run since' in res.stderr, res.stderr
        assert 'map folder (map_node.map_dir)' in res.stderr and 'Traceback' not in res.stderr
    finally:
        holder.kill()
        holder.wait()
    from photogram_ros.commands.run import claim_folders
    import argparse
    args = argparse.Namespace(params=str(cfg), out=str(tmp_path / 'products'), resume=False, overwrite=False)
    MapStore(map_dir, cell_m=0.1, tile_cells=64)   # a map whose flight did not end: resumed
    for lock in claim_folders(args, ('map',), True):
        lock.close()
    MapStore(map_dir).save_flight_end({'final_adjustment': 'done', 'reason': '', 'errors': []})
    from photogram_ros.errors import ConfigError
    with pytest.raises(ConfigError, match='holds a previous run'):
        claim_folders(args, ('map',), False)
    args.overwrite = True
    for lock in claim_folders(args, ('map',), True):
        lock.close()
    assert not (map_dir / 'flight_end.json').exists()


def test_odm_gcp_list_from_a_spreadsheet_is_read(tmp_path):
    """OpenDroneMap's gcp_list.txt saved with a BOM and decimal commas (a European spreadsheet): read as the
    plain one."""
    from photogram_ros.io.control_file import read_gcp_list
    rows = ['EPSG:32632', '465698.587 5249464.825 489.927 1234.5 987.25 IMG_0001.JPG GCP01',
            '465728.125 5249504.5 491.5 2000 1500 IMG_0002.JPG CHK01']
    plain, odd = tmp_path / 'plain.txt', tmp_path / 'odd.txt'
    plain.write_text('\n'.join(rows) + '\n')
    odd.write_bytes(b'\xef\xbb\xbf' + '\r\n'.join(r.replace('.', ',') if k else r
                                                 for k, r in enumerate(rows)).replace(',JPG', '.JPG').encode())
    a, b = read_gcp_list(plain), read_gcp_list(odd)
    assert b.crs == 'EPSG:32632' and b.points == a.points and b.roles == a.roles
    assert {k: {n: list(v) for n, v in d.items()} for k, d in b.image_uv.items()} == \
        {k: {n: list(v) for n, v in d.items()} for k, d in a.image_uv.items()}


def test_child_process_topics_are_the_parents_own():
    """A replay's parent and child talk on topics named after the parent's pid: two replays sharing a
    domain (--domain) never take each other's "stop" or status."""
    from photogram_ros.nodes.graph import TOPIC_CHILD_COMMAND, TOPIC_CHILD_STATUS, child_topic
    assert child_topic(TOPIC_CHILD_COMMAND, 'p12') == 'graph/child/p12/command'
    assert child_topic(TOPIC_CHILD_STATUS, 'p12') != child_topic(TOPIC_CHILD_STATUS, 'p13')
    assert child_topic(TOPIC_CHILD_STATUS, '') == TOPIC_CHILD_STATUS
