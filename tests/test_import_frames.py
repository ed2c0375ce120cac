"""import-frames (io/frame_import.py): the phantom3 village frames as a flight bag the mapper replays."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, shared_data


@pytest.fixture(scope='module')
def phantom3():
    return shared_data('video', 'phantom3_village')


def _read(bag_dir):
    from photogram_ros.io.bag import BagReader, deserialize
    out = {}
    with BagReader(bag_dir) as bag:
        for m in bag.messages():
            out.setdefault(m.topic, []).append((m.stamp_ns, deserialize(m.msgtype, m.data)))
    return out


def test_the_command_writes_frames_camera_and_fixes_on_the_track(phantom3, tmp_path):
    from photogram_ros.io.frame_import import read_map2dfusion_config, read_track
    bag = tmp_path / 'p3'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'import-frames', str(phantom3), '--out', str(bag),
                        '--max-frames', '6', '--fix-rate-hz', '0', '--storage', 'sqlite3'],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert '6 frames, 6 fixes' in r.stdout
    msgs = _read(bag)
    assert sorted(msgs) == ['/camera/camera_info', '/camera/image_raw/compressed', '/gps/fix']
    frames = sorted((phantom3 / 'rgb').glob('*.jpg'))[:6]
    for (stamp, img), path in zip(msgs['/camera/image_raw/compressed'], frames):
        assert stamp == round(float(path.stem) * 1e9) and bytes(img.data) == path.read_bytes()
        assert img.header.stamp.sec == int(float(path.stem))
    info = msgs['/camera/camera_info'][0][1]
    assert (info.width, info.height) == (1920, 1080) and info.k[0] == 1220.0 and info.k[2] == 960.0
    # Without noise the fixes are the track, converted with GPS.Origin: back to ENU they are the track.
    cam, origin = read_map2dfusion_config(phantom3 / 'config.cfg')
    track = read_track(phantom3 / 'trajectory.txt')[:6]
    fixes = [m for _, m in msgs['/gps/fix']]
    enu = np.array([origin.geodetic_to_enu(f.latitude, f.longitude, f.altitude) for f in fixes]).reshape(-1, 3)
    assert np.abs(enu - track[:, 1:4]).max() < 1e-6
    # An independent check of the conversion: pyproj's geodesic distance between the first and the
    # last fix is the track's horizontal distance (ENU is metric about the origin: within 1 mm here).
    from pyproj import Geod
    _, _, dist = Geod(ellps='WGS84').inv(fixes[0].longitude, fixes[0].latitude, fixes[-1].longitude, fixes[-1].latitude)
    assert dist == pytest.approx(np.hypot(*(track[-1, 1:3] - track[0, 1:3])), abs=2e-3)
    assert all(f.status.status == 0 for f in fixes)


def test_noise_of_a_3d_fix_is_seeded_and_stated_in_the_covariance(phantom3, tmp_path):
    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.io.frame_import import FrameImportOptions, import_frames, read_map2dfusion_config, read_track
    cam, origin = read_map2dfusion_config(phantom3 / 'config.cfg')
    assert isinstance(cam, PinholeCamera)
    track = read_track(phantom3 / 'trajectory.txt')
    runs = []
    for name, seed in (('a', 3), ('b', 3), ('c', 4)):
        res = import_frames(FrameImportOptions(phantom3 / 'rgb', tmp_path / name, cam, track, origin, max_frames=40,
                                               noise_h_m=1.5, noise_v_m=3.0, noise_tau_s=0.0, seed=seed))
        msgs = _read(tmp_path / name)
        fixes = [m for _, m in msgs['/gps/fix']]
        t = np.array([s for s, _ in msgs['/gps/fix']]) * 1e-9
        enu = np.array([origin.geodetic_to_enu(f.latitude, f.longitude, f.altitude) for f in fixes]).reshape(-1, 3)
        truth = np.column_stack([np.interp(t, track[:, 0], track[:, k]) for k in (1, 2, 3)])
        runs.append(enu - truth)
        cov = np.array(fixes[0].position_covariance).reshape(3, 3)
        assert np.allclose(np.diag(cov), [1.5 ** 2, 1.5 ** 2, 3.0 ** 2]) and fixes[0].position_covariance_type == 2
        assert res.fixes == len(fixes) and res.frames == 40
    assert np.allclose(runs[0], runs[1]) and not np.allclose(runs[0], runs[2])
    err = np.concatenate(runs)
    # 1 Hz over ~40 frames: about 70 white samples per axis and run.
    assert 1.0 < err[:, :2].std() < 2.0 and 2.0 < err[:, 2].std() < 4.0


def test_a_calibration_of_another_size_is_refused(phantom3, tmp_path):
    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.errors import DataError
    from photogram_ros.io.frame_import import FrameImportOptions, import_frames, read_map2dfusion_config, read_track
    _, origin = read_map2dfusion_config(phantom3 / 'config.cfg')
    cam = PinholeCamera(640, 480, 520.0, 520.0, 320.0, 240.0)
    with pytest.raises(DataError, match='1920x1080'):
        import_frames(FrameImportOptions(phantom3 / 'rgb', tmp_path / 'x', cam,
                                         read_track(phantom3 / 'trajectory.txt'), origin, max_frames=2))
    assert not (tmp_path / 'x').exists()


def test_a_bag_without_attitude_replays_without_the_body_lever_arm(phantom3, tmp_path, sample_bag, capsys):
    """config/replay.yaml sets a body lever arm (FRD); it turns with the attitude. A bag of imported frames
    records none, so the replay leaves it out with a note, as for a photo folder; a bag with raw MAVLink
    keeps it."""
    from photogram_ros.io.bag import BagReader
    from photogram_ros.nodes.replay_session import ReplayOptions, bag_has_attitude, no_body_lever_arm
    bag = tmp_path / 'p3'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'import-frames', str(phantom3), '--out', str(bag),
                        '--max-frames', '5'], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    with BagReader(bag) as b:
        imported = b.topics()
    with BagReader(sample_bag) as b:
        recorded = b.topics()
    assert not bag_has_attitude(imported) and bag_has_attitude(recorded)
    opts = ReplayOptions(str(bag), str(tmp_path / 'out'), params_file=str(ROOT / 'config' / 'replay.yaml'))
    extra = {}
    assert no_body_lever_arm(opts, extra, ('tracker', 'bundle'), 'the bag records no attitude')
    assert extra['bundle']['lever_arm_body_frd_m'] == [0.0, 0.0, 0.0]
    assert 'the body lever arm [0.05, 0.0, -0.2] m is not applied: the bag records no attitude' in capsys.readouterr().out
