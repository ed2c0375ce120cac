"""A photo folder that grows during the flight is followed (issue 48): camera_node's watch_quiet_s waits for
new photos (a companion computer downloading from the camera) until the folder stays quiet that long or the
flight is stopped; a photo still being copied is taken once whole (docs/faults.md)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from conftest import ROOT, shared_data


def _staged(tmp_path: Path, n: int) -> list[Path]:
    return sorted(shared_data('photos', 'toledo', 'images').glob('*.JPG'))[:n]


def test_refresh_takes_new_photos_once_whole(tmp_path):
    from photogram_ros.io.image_source import FolderSource
    src_photos = _staged(tmp_path, 5)
    folder = tmp_path / 'photos'
    folder.mkdir()
    for p in src_photos[:2]:
        shutil.copy2(p, folder / p.name)
    src = FolderSource(folder)
    frames = src.frames()
    assert len([next(frames), next(frames)]) == 2
    data = src_photos[2].read_bytes()
    (folder / src_photos[2].name).write_bytes(data[:len(data) // 2])   # still being copied
    shutil.copy2(src_photos[3], folder / src_photos[3].name)
    assert src.refresh() == 0          # first look: sizes noted
    assert src.refresh() == 0          # the half one is not a whole JPEG: the older photo waits for it
    (folder / src_photos[2].name).write_bytes(data)
    assert src.refresh() == 0 and src.refresh() == 2
    assert [p.name for p, _ in src.entries] == [p.name for p in src_photos[:4]]
    assert [Path(f.path).name for f in frames] == [p.name for p in src_photos[2:4]]   # the same iterator goes on
    # A photo taken before the last one listed is named and left out (time never goes back).
    from PIL import Image
    with Image.open(src_photos[0]) as im:   # the first photo saved again: other bytes, its time
        im.save(folder / 'OLD_0001.JPG', quality=80, exif=im.info.get('exif', b''))
    src.refresh()
    assert src.refresh() == 0 and any('OLD_0001.JPG was taken before' in w for _, w in src.skipped)


@pytest.mark.ros
def test_camera_node_follows_a_growing_folder_until_it_stays_quiet(tmp_path, rclpy_context):
    from photogram_ros.nodes.camera_node import CameraNode
    src_photos = _staged(tmp_path, 4)
    folder = tmp_path / 'photos'
    folder.mkdir()
    shutil.copy2(src_photos[0], folder / src_photos[0].name)
    cam = CameraNode({'source': str(folder), 'autostart': False, 'rate': 0.0, 'watch_quiet_s': 3.0},
                     context=rclpy_context)

    def download():
        for p in src_photos[1:]:
            time.sleep(1.0)
            shutil.copy2(p, folder / p.name)
    threading.Thread(target=download, daemon=True).start()
    try:
        t0 = time.monotonic()
        while cam.publish_next() and time.monotonic() - t0 < 60:
            time.sleep(0.05)
        took_s = time.monotonic() - t0
        assert cam.finished and cam.diag.counts().get('frames') == 4, cam.diag.counts()
        assert 3.0 + 3.0 <= took_s < 30.0, took_s   # the last photo at about 3 s, then 3 s quiet
    finally:
        cam.destroy_node()


@pytest.mark.ros
def test_run_follows_photos_copied_during_the_flight(tmp_path):
    """`run` on a folder holding 2 photos at its start, 3 more copied during the flight: all 5 are taken and
    the flight ends by itself once the folder stayed quiet (before: it ended after the first 2)."""
    from test_replay_unmappable import write_white_wall
    staged = write_white_wall(tmp_path / 'staged', n=5)
    folder = tmp_path / 'photos'
    folder.mkdir()
    files = sorted(staged.glob('*.JPG'))
    for p in files[:2]:
        shutil.copy2(p, folder / p.name)
    cfg = tmp_path / 'watch.yaml'
    cfg.write_text(f'camera_node:\n  ros__parameters:\n    source: {folder}\n    rate: 0.0\n    watch_quiet_s: 8.0\n'
                   f'map_node:\n  ros__parameters:\n    map_dir: {tmp_path / "map"}\n')
    proc = subprocess.Popen([sys.executable, '-m', 'photogram_ros.cli', 'run', '--params', str(cfg), '--nodes',
                             'camera,tracker,bundle,stereo,map', '--out', str(tmp_path / 'products')], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []

    def read():
        for line in proc.stdout:
            lines.append(line)
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        t0 = time.monotonic()
        while not any('photogram_ros running' in s for s in lines) and time.monotonic() - t0 < 300:
            time.sleep(0.2)
        for p in files[2:]:
            time.sleep(2.0)
            shutil.copy2(p, folder / p.name)
        proc.wait(timeout=600)
        reader.join(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    out = ''.join(lines)
    assert proc.returncode == 5, out[-3000:]   # a white wall maps nothing: MAPPING FAILED, by itself
    assert 'end of the camera source' in out
    report = json.loads((tmp_path / 'products' / 'report.json').read_text())
    assert report['run']['frames'] == 5, report['run']
