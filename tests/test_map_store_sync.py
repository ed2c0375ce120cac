"""io/map_store.MapStore.sync while another thread appends (stages/map.py syncs outside the stage's lock while the
fusion appends): no error, nothing appended is left unsynced for good, and the index never claims more than a
tile holds."""

from __future__ import annotations

import json
import threading

import numpy as np

from photogram_ros.core.fusion import CELL_DTYPE
from photogram_ros.io.map_store import MapStore


def _cells(n: int, z: float) -> tuple[np.ndarray, np.ndarray]:
    cells = np.zeros(n, CELL_DTYPE)
    cells['z'] = z
    cells['n'] = 1
    return np.arange(n, dtype=np.uint32), cells


def test_appends_during_syncs_are_all_made_durable_and_indexed(tmp_path):
    store = MapStore(tmp_path / 'map', cell_m=0.5, tile_cells=64)
    keys = [(0, 0), (0, 1), (1, 0), (2, 2)]
    stop = threading.Event()
    errors = []

    def syncer():
        try:
            while not stop.is_set():
                store.sync()
        except Exception as exc:   # a set changed during iteration, an index written twice at once
            errors.append(exc)
    t = threading.Thread(target=syncer)
    t.start()
    try:
        for k in range(300):
            idx, cells = _cells(10 + k % 7, float(k))
            store.append_cells(keys[k % len(keys)], idx, cells)
    finally:
        stop.set()
        t.join()
    assert errors == []
    store.sync()   # the end of the flight: whatever the last concurrent sync left
    assert store.check_tiles() == []
    index = json.loads((store.tiles_dir / 'index.json').read_text())['sizes']
    for key in keys:
        size = store.tile_path(key).stat().st_size
        assert index[f'{key[0]}_{key[1]}'] == size


def test_a_tile_appended_after_the_snapshot_is_synced_next_time(tmp_path, monkeypatch):
    store = MapStore(tmp_path / 'map', cell_m=0.5, tile_cells=64)
    idx, cells = _cells(5, 1.0)
    store.append_cells((0, 0), idx, cells)
    import os
    real_fsync = os.fsync
    appended = []

    def fsync_and_append(fd):   # another thread appends to the same tile while this sync runs
        if not appended:
            appended.append(True)
            store.append_cells((0, 0), idx, cells)
        return real_fsync(fd)
    monkeypatch.setattr('photogram_ros.io.map_store.os.fsync', fsync_and_append)
    store.sync()
    monkeypatch.setattr('photogram_ros.io.map_store.os.fsync', real_fsync)
    size = store.tile_path((0, 0)).stat().st_size
    index = json.loads((store.tiles_dir / 'index.json').read_text())['sizes']
    assert index['0_0'] < size          # the first sync vouches only for what it snapshotted
    store.sync()                        # the second block is still owed a sync
    index = json.loads((store.tiles_dir / 'index.json').read_text())['sizes']
    assert index['0_0'] == size
