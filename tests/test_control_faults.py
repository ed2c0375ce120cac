"""Control files with the faults of a real field survey, on a simulated photo flight.

The simulator writes geotagged photos and a correct OpenDroneMap gcp_list.txt; each test writes the
file a surveyor might really hand over (every row of one photo naming the wrong photo, rows naming
photos of another flight, a pixel outside the image, placeholder heights 0 / 400 m, one GCP) and
asserts that each fault is named in report.json and that the block is not strained: the spread of
the GNSS residuals (about their mean) within 1.2x of the same photos adjusted without GCPs. The
camera is the simulator's calibration (camera.yaml beside the photos, `--camera`), held fixed: the
faults are judged against a block whose camera is right (with the EXIF camera the final
self-calibration of f with the GCPs moves the block's depth itself; tests/test_triangulate_command.py).
"""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.control import ControlRow, vet_control
from photogram_ros.core.incremental import ControlPoint
from photogram_ros.sim.scenario import preset, simulate
from photogram_ros.sim.truth import GroundTruth

LEVER = (0.0, -0.05, -0.2)     # the simulator's FRD lever arm in the nadir camera frame
MAX_STRAIN = 1.2


# --- the vetting alone, against an exact oracle ---------------------------------------------------

def _pose(R, c):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, c
    return T


def test_vet_control_names_each_fault_against_exact_cameras():
    cam = PinholeCamera(640, 480, 520.0, 520.0, 319.5, 239.5, (0, 0, 0, 0, 0))
    R = np.diag([1.0, -1.0, -1.0])
    centres = {f'IMG_{k}.JPG': np.array([x, y, 40.0]) for k, (x, y) in enumerate(
        [(0, 0), (8, 0), (16, 0), (24, 0), (0, 30), (8, 30), (16, 30)])}
    poses = {n: _pose(R, c) for n, c in centres.items()}
    pts = {'GCP1': np.array([10.0, 2.0, 0.0]), 'GCP2': np.array([12.0, 28.0, 0.3]), 'GCP3': np.array([4.0, 1.0, 0.1])}

    def uv(name, img):
        pc = (pts[name] - poses[img][:3, 3]) @ poses[img][:3, :3]
        return cam.normalized_to_pixel((pc[:2] / pc[2])[None])[0]
    rows = [ControlRow(i + 2, img, n, uv(n, img)) for i, (n, img) in enumerate(
        [('GCP1', 'IMG_0.JPG'), ('GCP1', 'IMG_1.JPG'), ('GCP1', 'IMG_2.JPG'), ('GCP2', 'IMG_4.JPG'),
         ('GCP2', 'IMG_5.JPG'), ('GCP2', 'IMG_6.JPG'), ('GCP3', 'IMG_0.JPG'), ('GCP3', 'IMG_1.JPG')])]
    # IMG_3's rows are IMG_1's (the wrong photo named); another flight's photo; a pixel off the image.
    rows += [ControlRow(20, 'IMG_3.JPG', 'GCP1', uv('GCP1', 'IMG_1.JPG')),
             ControlRow(21, 'DJI_0042.JPG', 'GCP2', np.array([100.0, 100.0])),
             ControlRow(22, 'IMG_6.JPG', 'GCP3', np.array([700.0, 100.0]))]
    survey = dict(pts, GCP2=pts['GCP2'] + [0, 0, 400.0])     # a placeholder-like height, 400 m off
    control = [ControlPoint(n, survey[n], np.array([0.02, 0.02, 0.03]), 'gcp') for n in pts]
    vet = vet_control(cam, poses, set(poses), rows, control, np.array([0.3, 0.3, 0.5]))
    fate = {(f.row.image, f.row.name): f for f in vet.rows}
    assert fate[('IMG_3.JPG', 'GCP1')].fate == 'outlier' and fate[('IMG_3.JPG', 'GCP1')].likely_wrong_photo
    assert fate[('IMG_3.JPG', 'GCP1')].residual_m == pytest.approx(16.0, abs=0.5)     # IMG_1 is 16 m from IMG_3
    assert 'IMG_3.JPG' in vet.wrong_photos
    assert fate[('DJI_0042.JPG', 'GCP2')].fate == 'photo_not_in_set'
    assert fate[('IMG_6.JPG', 'GCP3')].fate == 'pixel_outside_image'
    assert all(fate[(img, 'GCP1')].fate == 'used' and fate[(img, 'GCP1')].residual_px < 1e-3
               for img in ('IMG_0.JPG', 'IMG_1.JPG', 'IMG_2.JPG'))
    assert vet.points['GCP1'].use == 'full' and vet.points['GCP3'].use == 'full'
    g2 = vet.points['GCP2']
    assert g2.use == 'horizontal' and g2.vertical == 'contradicted' and g2.d_v_m == pytest.approx(-400.0, abs=0.1)
    assert g2.horizontal == 'agrees' and vet.height_suspect == 'control_heights'
    cps = {c.name: c for c in vet.control_points(control)}
    assert cps['GCP2'].sigma_m[2] >= 1e3 and cps['GCP1'].sigma_m[2] == 0.03
    assert set(vet.accepted_uv()) == {'IMG_0.JPG', 'IMG_1.JPG', 'IMG_2.JPG', 'IMG_4.JPG', 'IMG_5.JPG', 'IMG_6.JPG'}


# --- real-looking files on a simulated flight -------------------------------------------------------

@pytest.fixture(scope='module')
def flight(tmp_path_factory):
    """A small simulated survey (RTK fixed GNSS, 5 GCPs, 3 check points), its photos read and matched once."""
    from photogram_ros.io.photo_block import read_photo_block
    root = tmp_path_factory.mktemp('ctrl') / 'flight'
    simulate(preset('tiny', photos=True, fps=1.0, n_gcp=5, n_check=3, gnss_mode='rtk_fixed'), root)
    photos = root / 'photos'
    block = read_photo_block(photos, photos / 'camera.yaml')
    lines = (photos / 'gcp_list.txt').read_text().splitlines()
    rows = [ln.split() for ln in lines[1:]]
    return root, photos, block, lines[0], rows, GroundTruth.load(root)


def _run(flight, tmp_path, rows=None, tag='run', heights='horizontal'):
    from photogram_ros.core.control import ControlVettingOptions
    from photogram_ros.io.aerial_triangulation import TriangulateOptions, adjust_block
    root, photos, block, crs, _, _ = flight
    opt = TriangulateOptions(lever_arm_cam_m=LEVER, vetting=ControlVettingOptions(contradicted_heights=heights))
    if rows is not None:
        p = tmp_path / f'{tag}_gcp_list.txt'
        p.write_text('\n'.join([crs] + [' '.join(r) for r in rows]) + '\n')
        opt.gcp = str(p)
    res = adjust_block(copy.deepcopy(block), tmp_path / tag, opt)
    rep = json.loads((tmp_path / tag / 'report.json').read_text())
    assert 'NaN' not in (tmp_path / tag / 'report.json').read_text()
    assert 'inf' not in (tmp_path / tag / 'report.md').read_text().replace('info', '')
    return res, rep


@pytest.fixture(scope='module')
def baseline(flight, tmp_path_factory):
    """The same photos without any control: the GNSS residuals' spread an unstrained block has."""
    _, rep = _run(flight, tmp_path_factory.mktemp('base'))
    return rep['gnss']['rmse']['spread_m']


def _assert_not_strained(rep, baseline):
    spread = rep['gnss']['rmse']['spread_m']
    print(f"GNSS residual spread {spread * 100:.2f} cm, without GCPs {baseline * 100:.2f} cm "
          f"({spread / baseline:.2f}x)")
    assert spread <= MAX_STRAIN * baseline
    assert rep['gnss']['strain_ratio'] <= MAX_STRAIN


def _with_heights(rows, z, names=None):
    return [[*r[:2], f'{z:.3f}', *r[3:]] if (names is None or r[6] in names) else list(r) for r in rows]


def test_field_file_wrong_photo_other_flight_placeholder_400(flight, baseline, tmp_path):
    _, _, block, _, rows, truth = flight
    count = {}
    for r in rows:
        count[r[6]] = count.get(r[6], 0) + 1
    by_img = {}
    for r in rows:
        by_img.setdefault(r[5], []).append(r)
    # The photo whose rows are moved: at least two rows, each of a point seen 3+ times (it keeps two).
    wrong_src = max((img for img, rs in by_img.items() if len(rs) >= 2 and all(count[r[6]] >= 3 for r in rs)),
                    key=lambda img: len(by_img[img]))
    names = {r[6] for r in by_img[wrong_src]}
    pos = {rec.name: rec.fix for rec in block.records}
    # ... to the photo farthest from it that has none of its points (as a slip in the photo list gives).
    from photogram_ros.core.geodesy import LocalFrame
    o = LocalFrame(pos[wrong_src].lat_deg, pos[wrong_src].lon_deg, 0.0)
    cand = [img for img in pos if not names & {r[6] for r in by_img.get(img, [])}]
    wrong = max(cand, key=lambda img: np.hypot(*o.geodetic_to_enu(pos[img].lat_deg, pos[img].lon_deg, 0.0)[:2]))
    field = [[*r[:5], wrong, r[6]] if r[5] == wrong_src else list(r) for r in rows]
    gcp = [r for r in rows if r[6].startswith('GCP')]
    off = next(img for img in pos if img != wrong and gcp[2][6] not in {r[6] for r in by_img.get(img, [])})
    field += [[*gcp[0][:3], '1012.5', '633.0', 'DJI_0412.JPG', gcp[0][6]],        # another flight's photos
              [*gcp[1][:3], '2010.0', '95.5', 'DJI_0413.JPG', gcp[1][6]],
              [*gcp[2][:3], '655.0', '101.0', off, gcp[2][6]]]                      # off the 640-px image
    field = _with_heights(field, 400.0, {r[6] for r in gcp})
    res, rep = _run(flight, tmp_path, field, 'field')
    c = rep['control']
    fates = c['row_fates']
    print(json.dumps(c['faults'], indent=1))
    assert sum(fates.values()) == len(field)                       # every row has a fate
    lines = {i + 2 for i, r in enumerate(rows) if r[5] == wrong_src}
    moved = [r for r in c['rows'] if r['line'] in lines]
    assert len(moved) >= 2 and all(r['image'] == wrong for r in moved)
    assert moved and all(r['fate'] == 'outlier' and r['likely_wrong_photo'] and r['residual_m'] > 5 for r in moved)
    assert wrong in c['wrong_photos'] and any(wrong in f and 'wrong photo' in f for f in c['faults'])
    assert fates['photo_not_in_set'] == 2 and any('DJI_0412.JPG' in f and 'not in the set' in f for f in c['faults'])
    assert fates['pixel_outside_image'] == 1
    gcps = {n: p for n, p in c['points'].items() if p['role'] == 'gcp'}
    usable = [p for p in gcps.values() if p['usable_rows'] >= 2]
    assert usable and all(p['use'] == 'horizontal' and p['vertical'] == 'contradicted' for p in usable)
    assert all('placeholder' in p['reason'] and '400.000' in p['reason'] for p in usable)
    assert c['height_suspect'] == 'control_heights'
    assert not any('look relative' in a for a in rep['assumptions'])     # the EXIF is not blamed
    # The GCP residual table shows no vertical for GCPs used horizontally only; every GCP is listed.
    assert {g['name'] for g in rep['gcp']['points']} == set(gcps)
    assert rep['gcp']['rmse'].get('n_vertical', 0) == 0
    _assert_not_strained(rep, baseline)
    ck = rep['check']['rmse']
    assert ck['n'] == 3 and ck['horizontal_m'] < 2 * truth.gsd_m and ck['vertical_m'] < 3 * truth.gsd_m
    assert rep['check']['ce90_le90']['n'] == 3


def test_placeholder_heights_zero(flight, baseline, tmp_path):
    _, _, _, _, rows, truth = flight
    res, rep = _run(flight, tmp_path, _with_heights(rows, 0.0, {r[6] for r in rows if r[6].startswith('GCP')}), 'zero')
    c = rep['control']
    gcps = [p for p in c['points'].values() if p['role'] == 'gcp']
    assert all(p['use'] == 'horizontal' and 'exactly 0 m' in p['reason'] for p in gcps)
    assert c['height_suspect'] == 'control_heights'
    # Before: the GCPs at 0 m put the ground 48 m below sea level and the EXIF altitudes were blamed.
    assert not any('look relative' in a for a in rep['assumptions'])
    _assert_not_strained(rep, baseline)
    assert rep['check']['rmse']['vertical_m'] < 3 * truth.gsd_m


def test_placeholder_heights_used_as_given_strain_the_block(flight, baseline, tmp_path):
    """The oracle of the strain test: the same 400 m heights used as given (`--gcp-heights use`, the old
    behaviour) bend the block, and the report still names the heights."""
    _, _, _, _, rows, _ = flight
    res, rep = _run(flight, tmp_path, _with_heights(rows, 400.0, {r[6] for r in rows if r[6].startswith('GCP')}),
                    'as_given', heights='use')
    ck = rep['check']['rmse']
    print(f"heights used as given: GNSS spread {rep['gnss']['rmse']['spread_m']:.3f} m "
          f"({rep['gnss']['strain_ratio']:.2f}x), estimated GNSS bias {rep['gnss']['estimated_bias_enu_m']} m, "
          f"check points {ck['horizontal_m']:.3f} m H, {ck['vertical_m']:.3f} m V")
    # With the GNSS bias free beside them, the GCPs' heights take the block 97 m up (a vertical bias of 97 m:
    # fixes in another height datum look like that), the terrain under 400 m heights strains it (the fixes'
    # spread 42x) and the check points are 97 m off: the block check says FAILED.
    assert rep['gnss']['strain_ratio'] > MAX_STRAIN
    assert max(rep['gcp']['rmse']['vertical_m'], rep['check']['rmse']['vertical_m']) > 10.0
    assert rep['verdict']['status'] == 'failed', rep['verdict']
    assert all(p['use'] == 'full' and 'used as given' in p['reason'] for p in rep['control']['points'].values()
               if p['role'] == 'gcp')


def test_one_gcp_says_its_residual_shows_nothing(flight, baseline, tmp_path):
    _, _, _, _, rows, truth = flight
    one = max((r[6] for r in rows if r[6].startswith('GCP')), key=lambda n: sum(r[6] == n for r in rows))
    res, rep = _run(flight, tmp_path, [r for r in rows if r[6] == one or r[6].startswith('CHK')], 'one')
    used = [g for g in rep['gcp']['points'] if g['residual_m'] is not None]
    assert [g['name'] for g in used] == [one] and used[0]['use'] == 'full'
    assert any('one GCP' in t and 'shows nothing' in t for t in rep['gcp']['redundancy'])
    md = (tmp_path / 'one' / 'report.md').read_text()
    assert 'shows nothing' in md and 'CE90' in md
    _assert_not_strained(rep, baseline)
    assert rep['check']['rmse']['n'] == 3


def test_correct_file_uses_every_row(flight, baseline, tmp_path):
    _, _, _, _, rows, truth = flight
    res, rep = _run(flight, tmp_path, rows, 'clean')
    c = rep['control']
    assert c['row_fates']['used'] == len(rows) and not c['faults']
    assert all(p['use'] in ('full', 'check') for p in c['points'].values())
    assert all(p['horizontal'] == 'agrees' and p['vertical'] == 'agrees' for p in c['points'].values())
    _assert_not_strained(rep, baseline)
    ck = rep['check']['rmse']
    assert ck['n'] == 3 and ck['horizontal_m'] < truth.gsd_m and ck['vertical_m'] < 2 * truth.gsd_m


def test_single_line_survey_takes_its_gcps_as_given_and_says_so(tmp_path):
    """One straight line of photos: its GNSS leaves the roll about the line undetermined, so the GNSS-only
    block cannot judge the control (it would reject good GCPs); the GCPs are used as given, with a note."""
    from photogram_ros.io.photo_block import read_photo_block
    root = tmp_path / 'line'
    simulate(preset('tiny', photos=True, fps=1.0, n_lines=1, line_length_m=60.0, n_gcp=5, n_check=3,
                    gnss_mode='rtk_fixed'), root)
    block = read_photo_block(root / 'photos', root / 'photos' / 'camera.yaml')
    lines = (root / 'photos' / 'gcp_list.txt').read_text().splitlines()
    flight = (root, root / 'photos', block, lines[0], [ln.split() for ln in lines[1:]], GroundTruth.load(root))
    _, rep = _run(flight, tmp_path, flight[4], tag='gcp')
    c = rep['control']
    print(c['faults'])
    assert any('could not be checked' in f for f in c['faults'])
    assert all(p['use'] in ('full', 'check') for p in c['points'].values())
    assert c['row_fates']['used'] == len(flight[4])
    assert rep['check']['rmse']['n'] == 3
