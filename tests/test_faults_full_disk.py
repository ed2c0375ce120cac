"""Full disk keeps whole files (issue 48): `export` writes each product under a temporary name and renames
it when whole; a full disk names the path, leaves no partial file under a final name, and the smaller
products after it are still written (docs/faults.md)."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT

CRS = 'EPSG:32632'


@pytest.fixture(scope='module')
def small_map(tmp_path_factory):
    from helpers.clouds import fused_map, pair_cloud
    rng = np.random.default_rng(5)
    return fused_map(tmp_path_factory.mktemp('full_disk') / 'map', 0.08,
                     (pair_cloud(rng, lambda x, y: 2.0 + 0.04 * x + 0.5 * np.sin(0.2 * y), -10.0 + 8 * k, 5.0, 10.0,
                                 8.0, 60.0, 0.01) for k in range(4))).root


def _full_disk_writer(real):
    """`real`'s output cut at half its bytes, then ENOSPC: a writer meeting a full disk mid-file."""
    def write(cloud, path):
        real(cloud, path)
        data = open(path, 'rb').read()
        with open(path, 'wb') as f:
            f.write(data[:len(data) // 2])
        raise OSError(errno.ENOSPC, 'No space left on device', str(path))
    return write


def test_a_full_disk_mid_cloud_keeps_no_partial_file_and_writes_the_rasters(small_map, tmp_path, monkeypatch):
    from photogram_ros.io import export
    monkeypatch.setattr(export, 'write_las', _full_disk_writer(export.write_las))
    out = tmp_path / 'out'
    with pytest.raises(export.ProductsIncomplete) as err:
        export.export_map(small_map, out, CRS, products=('las', 'dsm', 'dtm'))
    msg = str(err.value)
    assert f'{out / "cloud.las"}: not written: the disk is full' in msg and 'dsm.tif' in msg, msg
    assert err.value.errno == errno.ENOSPC
    names = sorted(os.listdir(out))
    assert names == ['dsm.tif', 'dtm.tif', 'export.json'], names   # no cloud.las, no .part file
    meta = json.loads((out / 'export.json').read_text())
    assert set(meta['failed']) == {'las'} and 'cloud.las' in meta['failed']['las']
    assert set(meta['files']) == {'dsm', 'dtm'}
    import rasterio
    with rasterio.open(out / 'dsm.tif') as ds:   # whole: it opens and reads
        assert ds.read(1).size > 0


def test_a_failed_raster_never_leaves_a_file_under_its_final_name(tmp_path):
    from photogram_ros.errors import StorageError
    from photogram_ros.io.export import part_path, write_whole

    def cut(tmp):
        tmp.write_bytes(b'half a GeoTIFF')
        raise OSError(errno.ENOSPC, 'No space left on device')
    with pytest.raises(StorageError) as err:
        write_whole(tmp_path / 'ortho.tif', cut)
    assert str(err.value) == f'{tmp_path / "ortho.tif"}: not written: the disk is full'
    assert os.listdir(tmp_path) == []
    assert part_path(tmp_path / 'cloud.laz').name == '.cloud.part.laz'   # the writer still sees .laz
    assert write_whole(tmp_path / 'a.txt', lambda tmp: tmp.write_text('whole')).read_text() == 'whole'
    assert os.listdir(tmp_path) == ['a.txt']


def test_export_command_on_a_full_disk_names_the_path_and_exits_3(small_map, tmp_path):
    """The command on a real small tmpfs (root may mount one; skipped where it cannot): the cloud does not fit,
    the path is named, exit 3, and what was written is whole."""
    mnt = tmp_path / 'small'
    mnt.mkdir()
    if os.geteuid() != 0 or shutil.which('mount') is None:
        pytest.skip('needs root to mount a small tmpfs')
    r = subprocess.run(['mount', '-t', 'tmpfs', '-o', 'size=300k', 'tmpfs', str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f'cannot mount a tmpfs here: {r.stderr.strip()}')
    try:
        r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'export', str(small_map), '--crs', CRS,
                            '--out', str(mnt / 'out'), '--products', 'ply,dtm', '--min-pairs', '1', '--quiet'],
                           cwd=ROOT, capture_output=True, text=True, timeout=300)
        text = r.stdout + r.stderr
        assert r.returncode == 3, text
        assert f'{mnt / "out" / "cloud.ply"}: not written: the disk is full' in text, text
        left = sorted(os.listdir(mnt / 'out'))
        assert 'cloud.ply' not in left and not [n for n in left if '.part' in n], left
    finally:
        subprocess.run(['umount', str(mnt)], capture_output=True)
