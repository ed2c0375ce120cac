"""Damaged maps say so (issue 48): map tiles are checked on read against the index of their synced sizes; a
deleted, cut or overwritten tile is named in the output and export.json, and `export` rebuilds the cloud
from the stored keyframes (as --densify) instead of losing its points silently (docs/faults.md)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from conftest import ROOT

TIMES = (2.0, 3.8, 5.6)   # along the first line of the tiny survey (as tests/test_densify.py)
CRS = 'EPSG:32632'


@pytest.fixture(scope='module')
def flight_map(tmp_path_factory):
    """A map folder with keyframes (true poses, rendered), camera, origin and fused tiles, as a flight leaves it."""
    from helpers.sim_world import rendered, world
    from photogram_ros.core.fusion import FusionConfig
    from photogram_ros.core.pairs import PairCriteria
    from photogram_ros.core.geodesy import LocalFrame
    from photogram_ros.core.stereo import StereoParams
    from photogram_ros.io.densify import densify_map
    from photogram_ros.io.map_store import MapStore
    from photogram_ros.params import from_dict
    cfg = world('tiny')[0]
    root = tmp_path_factory.mktemp('damaged_map')
    src = MapStore(root / 'keyframes_only', 0.08, 256)
    src.set_origin(LocalFrame(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_h_m))
    src.save_camera(cfg.camera())
    for k, (_, T, img) in enumerate(rendered(TIMES)):
        src.save_keyframe_image(k + 1, cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes())
        src.save_keyframe_pose(k + 1, T)
    res = densify_map(src, root / 'map', from_dict(StereoParams, {'downscale': 0.5}), PairCriteria(),
                      FusionConfig(cell_m=0.1, tile_cells=64))
    assert len(res.store.tile_keys()) >= 4
    return res.map_dir


def _copy(flight_map, tmp_path, name='map'):
    dst = tmp_path / name
    shutil.copytree(flight_map, dst)
    return dst


def _biggest_tiles(map_dir, n):
    return sorted((map_dir / 'tiles').glob('*.pgt'), key=lambda p: -p.stat().st_size)[:n]


def _cli(*args, timeout=600):
    return subprocess.run([sys.executable, '-m', 'photogram_ros.cli', *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def test_deleted_cut_and_overwritten_tiles_are_named(flight_map, tmp_path):
    from photogram_ros.io.map_store import MapStore
    m = _copy(flight_map, tmp_path)
    gone, cut, overwritten, header = _biggest_tiles(m, 4)
    gone.unlink()
    data = cut.read_bytes()
    cut.write_bytes(data[:len(data) // 2])
    data = bytearray(overwritten.read_bytes())
    data[len(data) // 2:len(data) // 2 + 4096] = bytes(4096)
    overwritten.write_bytes(bytes(data))
    data = bytearray(header.read_bytes())
    data[:8] = b'GARBAGE!'
    header.write_bytes(bytes(data))
    store = MapStore(m)
    found = {d.path.name: d.what for d in store.check_tiles()}
    assert set(found) == {gone.name, cut.name, overwritten.name, header.name}, found
    assert found[gone.name].startswith('missing') and found[cut.name].startswith('cut short')
    assert 'overwritten' in found[overwritten.name] and 'unreadable' in found[header.name]
    # The unreadable tile is left out: the rest of the map still reads.
    keys = store.tile_keys()
    assert header.stem not in {f'{a}_{b}' for a, b in keys} and all(store.load_tile(k) is not None for k in keys)
    assert MapStore(flight_map).check_tiles() == []   # the intact map: nothing said


def test_export_of_a_map_with_a_deleted_tile_names_it_and_rebuilds_its_points(flight_map, tmp_path):
    """The issue's case: the tile named (output and export.json) and the cloud within 1 % of the intact
    map's points (both matched again from the keyframes); --keep-damaged exports the rest and says how
    to rebuild (before: 13-25 % of the cloud gone, exit 0, notes empty)."""
    intact = _cli('export', flight_map, '--crs', CRS, '--out', tmp_path / 'intact', '--products', 'las', '--densify',
                  '--quiet')
    assert intact.returncode == 0, intact.stdout + intact.stderr
    m = _copy(flight_map, tmp_path)
    gone = _biggest_tiles(m, 1)[0]
    gone.unlink()
    r = _cli('export', m, '--crs', CRS, '--out', tmp_path / 'damaged', '--products', 'las', '--quiet')
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    assert f'damaged map tile {m / "tiles" / gone.name}: missing' in out and 'rebuilding the cloud from the 3 ' \
        'keyframes' in out, out
    meta = json.loads((tmp_path / 'damaged' / 'export.json').read_text())
    assert [d['points'] for d in meta['damaged_tiles']] == ['rebuilt from the keyframes'], meta
    assert gone.name in meta['damaged_tiles'][0]['tile'] and any(gone.name in n for n in meta['notes'])
    n_intact = json.loads((tmp_path / 'intact' / 'export.json').read_text())['points']
    print(f'points: intact map {n_intact}, map with {gone.name} deleted {meta["points"]}')
    assert abs(meta['points'] - n_intact) <= 0.01 * n_intact

    kept = _cli('export', m, '--crs', CRS, '--out', tmp_path / 'kept', '--products', 'las', '--keep-damaged',
                '--quiet')
    assert kept.returncode == 0, kept.stdout + kept.stderr
    meta = json.loads((tmp_path / 'kept' / 'export.json').read_text())
    assert meta['damaged_tiles'][0]['points'] == 'missing'
    assert any(gone.name in n and '--densify rebuilds them from the keyframes' in n for n in meta['notes']), meta


def test_a_damaged_map_without_keyframes_says_its_points_are_lost(tmp_path):
    """No keyframes to rebuild from: the export holds what the other tiles hold, names the tile and why it
    cannot be rebuilt."""
    from helpers.clouds import fused_map, pair_cloud
    rng = np.random.default_rng(5)
    store = fused_map(tmp_path / 'map', 0.08, (pair_cloud(rng, lambda x, y: 2.0 + 0.04 * x, -10.0 + 8 * k, 5.0,
                                                          10.0, 8.0, 60.0, 0.01) for k in range(4)),
                      tile_cells=64)
    gone = _biggest_tiles(store.root, 1)[0]
    gone.unlink()
    r = _cli('export', store.root, '--crs', CRS, '--out', tmp_path / 'out', '--products', 'las', '--min-pairs', '1',
             '--quiet')
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    assert 'the damaged tiles cannot be rebuilt' in out and 'nothing to densify' in out, out
    meta = json.loads((tmp_path / 'out' / 'export.json').read_text())
    assert [d['points'] for d in meta['damaged_tiles']] == ['missing'] and gone.name in meta['damaged_tiles'][0]['tile']


def test_keyframes_without_a_pose_are_said_not_dropped_silently(flight_map, tmp_path):
    """A map left by a crash holds keyframe images the bundle adjuster never oriented: the export says how
    many are not in the products (before: nothing said, the report counted only the posed ones)."""
    m = _copy(flight_map, tmp_path)
    (m / 'keyframes' / '3.json').unlink()
    r = _cli('export', m, '--crs', CRS, '--out', tmp_path / 'out', '--products', 'las', '--keep-damaged', '--quiet')
    assert r.returncode == 0, r.stdout + r.stderr
    assert 'note: 1 keyframe images have no pose' in r.stdout and '2 posed keyframes are' in r.stdout, r.stdout
    meta = json.loads((tmp_path / 'out' / 'export.json').read_text())
    assert any('1 keyframe images' in n and '3.jpg' in n for n in meta['notes']), meta['notes']
