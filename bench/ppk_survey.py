"""A simulated PPK photo survey end to end, measured: `simulate --ppk` -> `geotag` -> `triangulate` without GCPs.

    .venv/bin/python bench/ppk_survey.py --out bench/results/ppk_survey_COMMIT.jsonl [--work DIR]

One line per case (bench/machine.py's ResultWriter):
- camera_positions: the geotags `geotag` writes from the 5 Hz RTKLIB track and the MRK against the true
  camera centres (median, max, m); the ArduPilot log's CAM + lever arm, the .tlog's CAMERA_FEEDBACK and the
  photos' EXIF times against the MRK offsets (max, m);
- triangulate_ppk_exif_camera, triangulate_ppk_calibrated, triangulate_exif_gps: check-point RMSE (H, V, m,
  and in GSD) of `triangulate` on the PPK geo.txt with the photos' EXIF camera, with the camera's calibration,
  and on the photos' EXIF GPS alone. Every target is a check point (no GCP is used).
tests/test_ppk_survey.py runs the same functions and gates them at 1.5x the result file.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import ResultWriter  # noqa: E402

MODULES = ['photogram_ros/io/geotag.py', 'photogram_ros/core/exposure_positions.py', 'photogram_ros/io/camera_events.py',
           'photogram_ros/io/photo_block.py', 'photogram_ros/io/aerial_triangulation.py', 'photogram_ros/core',
           'photogram_ros/sim']


def simulate_flight(root: Path):
    """The tiny preset at 1 fps with a PPK drone's files; returns (root, GroundTruth)."""
    from photogram_ros.sim.scenario import preset, simulate
    from photogram_ros.sim.truth import GroundTruth
    simulate(preset('tiny', fps=1.0, ppk=True), root)
    return root, GroundTruth.load(root)


def geotag_ppk(root: Path):
    """`geotag` on what the PPK drone left: geo.txt beside its photos (the GeotagResult)."""
    from photogram_ros.io.geotag import GeotagInput, geotag
    ppk = root / 'ppk'
    return geotag(GeotagInput(str(ppk / 'flight.pos'), str(ppk / 'Timestamp.MRK'), str(ppk), str(ppk / 'geo.txt')))


def camera_positions(root: Path, truth, scratch: Path) -> dict:
    """The geo.txt positions against the true camera centres, and the other event sources against the MRK's."""
    from photogram_ros.core.exposure_positions import ExposureOptions
    from photogram_ros.io.geotag import GeotagInput, geotag
    from photogram_ros.io.photo_block import read_geo_txt
    ppk = root / 'ppk'
    geo = read_geo_txt(ppk / 'geo.txt')
    frame = {f'IMG_{f.index:04d}.JPG': f for f in truth.frames}
    err = np.array([truth.origin.geodetic_to_enu(*g[:3]) - frame[n].map_T_cam[:3, 3] for n, g in geo.items()])
    out = {'photos': len(geo), 'median_m': float(np.median(np.linalg.norm(err, axis=1))),
           'max_m': float(np.abs(err).max())}
    opts = ExposureOptions(lever_arm_frd_m=tuple(truth.lever_arm_frd_m))
    for key, events in (('cam_bin', ppk / 'flight.bin'), ('tlog', root / 'flight.tlog'), ('exif', 'exif')):
        r = geotag(GeotagInput(str(ppk / 'flight.pos'), str(events), str(ppk), str(scratch / f'geo_{key}.txt'),
                               options=opts))
        d = [float(np.linalg.norm(truth.origin.geodetic_to_enu(pe.lat_deg, pe.lon_deg, pe.h_m)
                                  - truth.origin.geodetic_to_enu(*geo[n][:3]))) for n, pe in r.rows]
        out[f'{key}_vs_mrk_max_m'] = max(d)
        out[f'{key}_rows'] = len(d)
        out[f'{key}_no_photo'] = sum('has no photo' in p for p in r.problems)
    return out


def triangulate_checks(folder: Path, out: Path, gsd_m: float, camera: Path | None = None) -> dict:
    """`triangulate` with every target a check point: its check-point RMSE."""
    from photogram_ros.io.aerial_triangulation import TriangulateOptions
    from photogram_ros.io.triangulate_action import triangulate
    names = sorted({ln.split()[6] for ln in (folder / 'gcp_list.txt').read_text().splitlines()[1:]})
    opt = TriangulateOptions(gcp=str(folder / 'gcp_list.txt'), check_names=tuple(names),
                             camera=str(camera) if camera else None)
    triangulate(str(folder), str(out), opt)
    ck = json.loads((out / 'report.json').read_text())['check']['rmse']
    return {'check_n': ck['n'], 'check_h_m': ck['horizontal_m'], 'check_v_m': ck['vertical_m'],
            'check_h_gsd': ck['horizontal_m'] / gsd_m, 'check_v_gsd': ck['vertical_m'] / gsd_m}


def triangulations(root: Path, truth, scratch: Path) -> dict:
    """{case: check figures} for the PPK geo.txt with the EXIF camera, with the calibration, and EXIF GPS alone."""
    ppk = root / 'ppk'
    exif_dir = scratch / 'exif' / 'ppk'
    shutil.copytree(ppk, exif_dir, ignore=shutil.ignore_patterns('geo.txt', 'geo.csv'))
    return {'triangulate_ppk_exif_camera': triangulate_checks(ppk, scratch / 'tri_ppk', truth.gsd_m),
            'triangulate_ppk_calibrated': triangulate_checks(ppk, scratch / 'tri_cal', truth.gsd_m, ppk / 'camera.yaml'),
            'triangulate_exif_gps': triangulate_checks(exif_dir, scratch / 'tri_exif', truth.gsd_m)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--out', default='/tmp/ppk_survey.jsonl', help='result file (JSON lines)')
    ap.add_argument('--work', default=None, help='scratch folder (default: a temporary one)')
    a = ap.parse_args(argv)
    writer = ResultWriter(a.out, 'ppk_survey', MODULES)
    work = Path(a.work or tempfile.mkdtemp(prefix='ppk_survey_'))
    root, truth = simulate_flight(work / 'flight')
    geotag_ppk(root)
    print(json.dumps(writer.write({'case': 'camera_positions', **camera_positions(root, truth, work)})), flush=True)
    for case, fig in triangulations(root, truth, work).items():
        print(json.dumps(writer.write({'case': case, **fig})), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
