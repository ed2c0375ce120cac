"""`photogram-ros triangulate` on the simulator's survey photos (geo.txt + ODM gcp_list.txt).

The camera is what a user of the photos gets: the EXIF focal length (principal point centred, no
distortion) and the final self-calibration `triangulate` makes for it. The simulator's truth beside the
folder is never read for it (its camera here is made wrong on purpose, and nothing changes).
"""

import csv
import json

import numpy as np
import pytest

from photogram_ros.cli import main
from photogram_ros.sim.scenario import preset, simulate
from photogram_ros.sim.truth import GroundTruth


def _wrong_truth_camera(flight) -> None:
    """The simulator's ground_truth.json in `flight` with its camera's focal length doubled."""
    doc = json.loads((flight / 'ground_truth.json').read_text())
    k = doc['camera']['camera_matrix']['data']
    k[0], k[4] = 2 * k[0], 2 * k[4]
    (flight / 'ground_truth.json').write_text(json.dumps(doc))


def _centre_rmse_m(rows, truth) -> float:
    err = [truth.origin.geodetic_to_enu(float(r['lat_deg']), float(r['lon_deg']), float(r['h_m']))
           - truth.frames[int(r['image'][4:8])].map_T_cam[:3, 3] for r in rows]
    return float(np.sqrt(np.mean(np.sum(np.square(err), axis=1))))


@pytest.mark.slow
def test_triangulate_simulated_photos(tmp_path):
    """Check points of the tiny survey (geo.txt of the flight's GNSS, 4 GCPs, 2 check points) with the
    EXIF camera. About every other geotag is 0.5 m behind its photo along the track (a photo between two
    5 Hz fixes), so the GNSS noise estimate weights the fixes by about 0.2 m horizontally, and the
    intrinsics are refined again under that weighting. `--self-calibrate auto` takes f, k1 and k2
    (4 GCPs) and the principal point (geotags stated at 1.4 cm) as candidates; the 4 GCPs lie too flat for this
    block to determine f (it trades off with the cameras' height), so auto holds f at the EXIF value (520.0 px,
    the true fx) and says so. Measured (7b9b009): auto check points 1.0 cm H / 1.1 cm V, camera centres 9.3 cm;
    k1, k2 only 0.9 / 1.1 cm, 12.1 cm. Two check points: a vertical RMSE below the geotags' 2.9 cm sigma is partly
    luck, so the verticals are gated at 1 cm at least."""
    simulate(preset('tiny', photos=True), tmp_path / 'flight')
    truth = GroundTruth.load(tmp_path / 'flight')
    _wrong_truth_camera(tmp_path / 'flight')
    photos = tmp_path / 'flight' / 'photos'
    n_photos = len(list(photos.glob('*.JPG')))
    figures = {}
    # The simulator's lever arm (0.05, 0, -0.20) m FRD is (0, -0.05, -0.20) in the nadir camera frame.
    for tag, extra in (('auto', []), ('k1k2', ['--self-calibrate', 'k1,k2'])):
        out = tmp_path / tag
        rc = main(['triangulate', str(photos), '--gcp', str(photos / 'gcp_list.txt'), '--out', str(out),
                   '--lever-arm=0,-0.05,-0.2', *extra])
        rep = json.loads((out / 'report.json').read_text())
        rows = list(csv.DictReader(open(out / 'poses.csv')))
        ck = rep['check']['rmse']
        figures[tag] = rc, rep, rows, ck
        print(f"triangulate ({tag}): exit {rc}, {len(rows)}/{n_photos} photos, reprojection "
              f"{rep['reprojection_rms_px']:.3f} px, check n={ck['n']} h {ck['horizontal_m'] * 100:.1f} cm "
              f"v {ck['vertical_m'] * 100:.1f} cm ({ck['horizontal_m'] / truth.gsd_m:.2f} / "
              f"{ck['vertical_m'] / truth.gsd_m:.2f} GSD), camera centres {_centre_rmse_m(rows, truth):.3f} m, "
              f"fx {rep['self_calibration']['fx']['before']:.1f} -> {rep['self_calibration']['fx']['after']:.1f} px")
        # The EXIF camera, not the (doubled) truth beside the folder.
        assert any(a.startswith('no calibration given: camera from the EXIF') for a in rep['assumptions'])
        assert rep['self_calibration']['fx']['before'] == pytest.approx(truth.camera.fx, rel=1e-4)
        assert len(rows) == n_photos and (out / 'sparse.las').stat().st_size > 10_000
        assert (out / 'report.md').exists()
    rc, rep, rows, ck = figures['auto']
    assert rc == 0 and rep['reprojection_rms_px'] < 1.5 * MEASURED['auto_rep_px']
    assert ck['n'] == 2 and ck['horizontal_m'] < 1.5 * MEASURED['auto_h_m']
    assert ck['vertical_m'] < max(1.5 * MEASURED['auto_v_m'], 0.01)
    assert rep['self_calibration']['fx']['after'] == rep['self_calibration']['fx']['before']   # held
    assert any(a.startswith('self-calibration (auto): f held at 520.0 px') for a in rep['assumptions'])
    assert _centre_rmse_m(rows, truth) < 1.5 * MEASURED['auto_centres_m']
    rc, rep, rows, ck = figures['k1k2']
    assert rc == 0 and rep['reprojection_rms_px'] < 1.5 * MEASURED['k1k2_rep_px']
    assert ck['n'] == 2 and ck['horizontal_m'] < 1.5 * MEASURED['k1k2_h_m'] and ck['vertical_m'] < max(1.5 * MEASURED['k1k2_v_m'], 0.01)
    assert _centre_rmse_m(rows, truth) < 1.5 * MEASURED['k1k2_centres_m']


MEASURED = dict(auto_rep_px=0.169, auto_h_m=0.010, auto_v_m=0.011, auto_centres_m=0.093,
                k1k2_rep_px=0.170, k1k2_h_m=0.009, k1k2_v_m=0.011, k1k2_centres_m=0.121)


# --- EXIF altitudes relative to take-off ---------------------------------------------

def _with_gps_altitude(jpeg: bytes, alt_m: float) -> bytes:
    """The JPEG with its EXIF GPSAltitude replaced, pixels untouched (the APP1 segment is swapped)."""
    import io

    from PIL import Image
    from PIL.TiffImagePlugin import IFDRational
    with Image.open(io.BytesIO(jpeg)) as im:
        exif = im.getexif()
    gps = exif.get_ifd(0x8825)
    gps[5] = 0 if alt_m >= 0 else 1                     # GPSAltitudeRef: 1 = below the reference
    gps[6] = IFDRational(int(round(abs(alt_m) * 1000)), 1000)
    return with_exif(jpeg, exif)


def with_exif(jpeg: bytes, exif) -> bytes:
    """The JPEG with its EXIF APP1 segment replaced by `exif` (a PIL Exif), pixels untouched."""
    import struct
    app1 = exif.tobytes()                                # starts with b'Exif\0\0'
    i = 2
    while jpeg[i:i + 2] != b'\xff\xe1' or jpeg[i + 4:i + 10] != b'Exif\x00\x00':
        i += 2 + struct.unpack('>H', jpeg[i + 2:i + 4])[0]
    n = struct.unpack('>H', jpeg[i + 2:i + 4])[0]
    return jpeg[:i] + b'\xff\xe1' + struct.pack('>H', len(app1) + 2) + app1 + jpeg[i + 2 + n:]


@pytest.fixture(scope='module')
def exif_survey(tmp_path_factory):
    """A small simulated survey as EXIF-only photo folders: MSL altitudes (as simulated) and the same
    photos with altitudes above the take-off point (about 10 s)."""
    import shutil

    from photogram_ros.core import geoid
    from photogram_ros.io.image_source import read_exif_gps
    flight = tmp_path_factory.mktemp('exif') / 'flight'
    truth = simulate(preset('tiny', photos=True, fps=1.0, line_length_m=30.0), flight)
    cfg = truth.config
    takeoff_msl_m = float(geoid.ellipsoid_to_msl_m(cfg['origin_lat_deg'], cfg['origin_lon_deg'], cfg['origin_h_m']))
    # Both beside the simulator's ground_truth.json (never read for the camera: the EXIF's is used),
    # neither with geo.txt: positions from EXIF only.
    msl, rel = flight / 'msl', flight / 'relative'
    msl.mkdir()
    rel.mkdir()
    for p in sorted((flight / 'photos').glob('*.JPG')):
        shutil.copy(p, msl / p.name)
        alt_rel_m = read_exif_gps(p).alt_msl_m - takeoff_msl_m
        (rel / p.name).write_bytes(_with_gps_altitude(p.read_bytes(), alt_rel_m))
        assert abs(read_exif_gps(rel / p.name).alt_msl_m - alt_rel_m) < 1e-3
    assert 30 < read_exif_gps(rel / p.name).alt_msl_m < 50 and takeoff_msl_m > 400
    return flight, truth, takeoff_msl_m


def _triangulate(folder, out, *options, gcp=None, rc=0):
    argv = ['triangulate', str(folder), '--out', str(out), '--lever-arm=0,-0.05,-0.2', *options]
    assert main(argv + (['--gcp', str(gcp)] if gcp else [])) == rc
    rep = json.loads((out / 'report.json').read_text())
    truth = GroundTruth.load(folder.parent)
    rows = list(csv.DictReader(open(out / 'poses.csv')))
    err = np.array([truth.origin.geodetic_to_enu(float(r['lat_deg']), float(r['lon_deg']), float(r['h_m']))
                    - truth.frames[int(r['image'][4:8])].map_T_cam[:3, 3] for r in rows])
    return rep, err


def _flagged(rep) -> bool:
    return any('look relative to the take-off point' in s for s in rep['assumptions'])


def test_triangulate_relative_exif_altitudes_with_the_takeoff_height_match_msl_ones(exif_survey, tmp_path, capsys):
    flight, truth, takeoff_msl_m = exif_survey
    rep0, err0 = _triangulate(flight / 'msl', tmp_path / 'msl')
    assert not _flagged(rep0) and 'look relative' not in capsys.readouterr().err     # (c) MSL photos pass
    rel = ['--exif-altitude', 'relative', '--takeoff-altitude-m', f'{takeoff_msl_m:.3f}']
    rep1, err1 = _triangulate(flight / 'relative', tmp_path / 'rel', *rel)
    assert not _flagged(rep1) and any('above the take-off point at' in s for s in rep1['assumptions'])
    rms0, rms1 = (float(np.sqrt(np.mean(np.sum(e ** 2, axis=1)))) for e in (err0, err1))
    print(f'camera centres, EXIF only: MSL {rms0:.3f} m, relative + take-off height {rms1:.3f} m '
          f'(heights {np.mean(err0[:, 2]):+.3f} / {np.mean(err1[:, 2]):+.3f} m)')
    assert len(err1) == len(err0) == rep0['keyframes']
    # Same heights to the EXIF's millimetre rounding; measured 0.100 m from the true centres.
    assert rms1 < 1.5 * 0.100 and abs(rms1 - rms0) < 0.01 and np.max(np.abs(err1[:, 2] - err0[:, 2])) < 0.01
    rep2, err2 = _triangulate(flight / 'relative', tmp_path / 'rel_gcp', *rel, gcp=flight / 'photos' / 'gcp_list.txt')
    ck = rep2['check']['rmse']
    print(f"with GCPs: check n={ck['n']} h {ck['horizontal_m'] * 100:.1f} cm v {ck['vertical_m'] * 100:.1f} cm, "
          f"cameras {np.sqrt(np.mean(np.sum(err2 ** 2, axis=1))):.3f} m")
    # Measured 1.1 cm H, 9.5 cm V; the cameras 0.78 m from the true centres (0.7 m high: the EXIF camera's
    # focal length refined with the 4 GCPs, 520 -> 530 px as in test_triangulate_simulated_photos).
    assert ck['n'] == 2 and ck['horizontal_m'] < 1.5 * 0.011 and ck['vertical_m'] < 1.5 * 0.095
    assert np.sqrt(np.mean(np.sum(err2 ** 2, axis=1))) < 1.5 * 0.781


def test_triangulate_flags_exif_altitudes_relative_to_takeoff(exif_survey, tmp_path, capsys):
    flight, _, takeoff_msl_m = exif_survey
    # Taken as MSL, the block sinks by the take-off height; the ground lands near 0 m MSL.
    rep, err = _triangulate(flight / 'relative', tmp_path / 'plain')
    assert abs(np.mean(err[:, 2]) + takeoff_msl_m) < 1.0
    note = next(s for s in rep['assumptions'] if 'look relative to the take-off point' in s)
    assert 'median tie point' in note and '--exif-altitude relative --takeoff-altitude-m' in note
    assert 'look relative to the take-off point' in capsys.readouterr().err
    # With GCPs the surveyed points are the ground, and the photos are below it. The check points then sit
    # hundreds of metres from the block: its verdict is FAILED (exit 4), naming them.
    rep, _ = _triangulate(flight / 'relative', tmp_path / 'gcp', gcp=flight / 'photos' / 'gcp_list.txt', rc=4)
    assert any('median GCP/check point' in s for s in rep['assumptions'] if 'look relative' in s)
    assert rep['verdict']['status'] == 'failed'
    assert any(f['check'] == 'check_points' for f in rep['verdict']['findings'])
    # Saying msl is the user's word: no second-guessing.
    rep, _ = _triangulate(flight / 'relative', tmp_path / 'said', '--exif-altitude', 'msl')
    assert not _flagged(rep)


def test_triangulate_takeoff_height_options_are_checked(tmp_path, capsys):
    assert main(['triangulate', str(tmp_path), '--out', str(tmp_path / 'o'), '--exif-altitude', 'relative']) == 2
    assert '--takeoff-altitude-m' in capsys.readouterr().err
    assert main(['triangulate', str(tmp_path), '--out', str(tmp_path / 'o'), '--takeoff-altitude-m', '440']) == 2
    assert '--exif-altitude relative' in capsys.readouterr().err


def test_triangulate_skips_empty_and_truncated_photos_and_names_them(exif_survey, tmp_path, capsys):
    """A 0-byte file and a truncated JPEG are skipped and named (the report's assumptions, a warning);
    the rest is oriented."""
    import shutil
    flight, _, _ = exif_survey
    folder = tmp_path / 'flight' / 'photos'
    folder.mkdir(parents=True)
    for name in ('ground_truth.json', 'ground_truth_dem.npz'):
        shutil.copy(flight / name, tmp_path / 'flight' / name)
    good = sorted((flight / 'msl').glob('*.JPG'))
    for p in good:
        shutil.copy(p, folder / p.name)
    (folder / 'EMPTY_000.JPG').write_bytes(b'')
    whole = good[0].read_bytes()
    (folder / 'CUT_0000.JPG').write_bytes(whole[:len(whole) // 2])
    rep, err = _triangulate(folder, tmp_path / 'at')
    out = capsys.readouterr()
    assert rep['keyframes'] == rep['registered'] == len(good) == len(err)
    note = next(s for s in rep['assumptions'] if 'files skipped' in s)
    assert 'EMPTY_000.JPG (empty file (0 bytes))' in note and 'CUT_0000.JPG (truncated or corrupt JPEG' in note
    assert 'EMPTY_000.JPG' in out.err and f'oriented {len(good)}/{len(good) + 2} images' in out.out


def test_truth_and_calibration_files_beside_the_photos_are_not_read_for_the_camera(exif_survey, tmp_path):
    """A photo folder beside a ground_truth.json whose camera is wrong (focal x2), holding a camera.yaml
    as wrong: the block's camera is the EXIF one (what a user gets), self-calibrated as an EXIF camera."""
    import shutil

    import yaml

    from photogram_ros.io.image_source import exif_intrinsics
    from photogram_ros.io.photo_block import read_photo_block
    flight, truth, _ = exif_survey
    folder = tmp_path / 'flight' / 'photos'
    folder.mkdir(parents=True)
    shutil.copy(flight / 'ground_truth.json', tmp_path / 'flight' / 'ground_truth.json')
    _wrong_truth_camera(tmp_path / 'flight')
    wrong = json.loads((tmp_path / 'flight' / 'ground_truth.json').read_text())['camera']['camera_matrix']['data']
    assert wrong[0] == pytest.approx(2 * truth.camera.fx)
    calib = yaml.safe_load((flight / 'photos' / 'camera.yaml').read_text())
    calib['camera_matrix']['data'][0] *= 2
    (folder / 'camera.yaml').write_text(yaml.safe_dump(calib))
    for p in sorted((flight / 'msl').glob('*.JPG')):
        shutil.copy(p, folder / p.name)
    block = read_photo_block(folder)
    exif = exif_intrinsics(next(folder.glob('*.JPG'))).camera
    assert block.camera_from_exif and block.camera.fx == exif.fx and tuple(block.camera.dist) == (0.0,) * 5
    assert abs(block.camera.fx / truth.camera.fx - 1) < 1e-4
    assert not any('truth' in a or 'camera.yaml' in a for a in block.assumptions)
    assert any(a.startswith('no calibration given: camera from the EXIF') for a in block.assumptions)
