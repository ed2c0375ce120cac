"""PPK geotagging figures on simulated flights (issue #45): the shutter's delay, and DJI RTK photos' XMP weights.

1. Event delay: `simulate` a PPK survey flown at 12 m/s whose shutter opens 30 ms after the event marks the
   MRK writes, the .pos the true antenna track (its error model off) or the RTK-fixed error model; `geotag`
   with and without `--event-delay-ms 30`: the camera positions' error against the truth (median, 90 %,
   max; along-track part).
2. DJI RTK photos: `simulate --rtk-photos` (EXIF GPS = the RTK camera centre, XMP RtkFlag/RtkStd*); `triangulate`
   without GCPs (every target a check point) on (a) the XMP, (b) the same photos with a hand-made geo.txt of the
   same positions and sigmas, (c) a third of the photos FLOAT (flag 34, 0.5 / 0.8 m stated) at their true
   positions, (d) the same third FLOAT and 1 m off (the fixed photos' errors the same in all).

One JSON line per result, with the commit, whether the product code was clean, the cores and the load:
    .venv/bin/python bench/ppk_formats.py [--preset tiny] [--out bench/results/ppk_formats_<commit>.jsonl]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine import machine_info  # noqa: E402

from photogram_ros.core.exposure_positions import ExposureOptions  # noqa: E402
from photogram_ros.io.geotag import GeotagInput, geotag  # noqa: E402
from photogram_ros.sim.scenario import preset, simulate  # noqa: E402
from photogram_ros.sim.truth import GroundTruth  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def git(*args) -> str:
    return subprocess.run(['git', *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()


def delay_run(where: Path, sigma_scale: float) -> list[dict]:
    root = where / f'delay_{sigma_scale:g}'
    simulate(preset('tiny', fps=1.0, ppk=True, speed_mps=12.0, ppk_shutter_delay_ms=30.0, ppk_sigma_scale=sigma_scale),
             root)
    truth = GroundTruth.load(root)
    ppk = root / 'ppk'
    frame = {f'IMG_{f.index:04d}.JPG': f for f in truth.frames}
    rows = []
    for delay_ms in (0.0, 30.0):
        res = geotag(GeotagInput(str(ppk / 'flight.pos'), str(ppk / 'Timestamp.MRK'), str(ppk), str(root / 'geo.txt'),
                                 options=ExposureOptions(event_delay_s=delay_ms * 1e-3)))
        err = np.array([truth.origin.geodetic_to_enu(pe.lat_deg, pe.lon_deg, pe.h_m) - frame[n].map_T_cam[:3, 3]
                        for n, pe in res.rows])
        e = np.linalg.norm(err, axis=1)
        rows.append({'case': 'event_delay', 'speed_mps': 12.0, 'shutter_delay_ms': 30.0, 'event_delay_ms': delay_ms,
                     'track_error_scale': sigma_scale, 'photos': len(e), 'median_m': round(float(np.median(e)), 5),
                     'p90_m': round(float(np.percentile(e, 90)), 5), 'max_m': round(float(e.max()), 5)})
    return rows


def _triangulate(folder: Path, out: Path) -> dict:
    from photogram_ros.io.aerial_triangulation import TriangulateOptions
    from photogram_ros.io.triangulate_action import triangulate
    names = sorted({ln.split()[6] for ln in (folder / 'gcp_list.txt').read_text().splitlines()[1:]})
    triangulate(str(folder), str(out), TriangulateOptions(gcp=str(folder / 'gcp_list.txt'), check_names=tuple(names)))
    return json.loads((out / 'report.json').read_text())


def rtk_runs(where: Path, name: str) -> list[dict]:
    from photogram_ros.sim.photos import write_geo_txt_from_exif_and_rtk_xmp
    folders = {}
    for case, extra in (('rtk_xmp', {}), ('rtk_xmp_third_float_0m', {'rtk_float_every': 3, 'rtk_float_offset_m': 0.0}),
                        ('rtk_xmp_third_float_1m', {'rtk_float_every': 3, 'rtk_float_offset_m': 1.0})):
        simulate(preset(name, fps=1.0, rtk_photos=True, **extra), where / case)
        folders[case] = where / case / 'rtk'
    hand = where / 'rtk_hand' / 'rtk'
    shutil.copytree(folders['rtk_xmp'], hand)
    write_geo_txt_from_exif_and_rtk_xmp(hand)
    folders['rtk_hand_geo_txt'] = hand
    rows = []
    for case, folder in folders.items():
        rep = _triangulate(folder, where / f'tri_{case}')
        ck = rep['check']['rmse']
        rows.append({'case': case, 'preset': name, 'photos': len(list(folder.glob('*.JPG'))), 'check_n': ck['n'],
                     'check_h_m': round(ck['horizontal_m'], 4), 'check_v_m': round(ck['vertical_m'], 4),
                     'verdict': rep.get('verdict', {}).get('status'),
                     'rtk_flags': rep.get('matching', {}).get('rtk_flags'), 'gnss_noise': rep.get('gnss_noise')})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--preset', default='tiny', help='simulator preset of the RTK photo survey')
    ap.add_argument('--out', help='JSON lines file (default bench/results/ppk_formats_<commit>.jsonl)')
    ap.add_argument('--skip-rtk', action='store_true')
    ap.add_argument('--skip-delay', action='store_true')
    a = ap.parse_args()
    commit = git('rev-parse', '--short', 'HEAD')
    clean = not git('status', '--porcelain', 'photogram_ros', 'bench/ppk_formats.py')
    out = Path(a.out or ROOT / 'bench' / 'results' / f'ppk_formats_{commit}.jsonl')
    head = {'commit': commit, 'clean_tree': clean, 'machine': machine_info(), 'cores': os.cpu_count(),
            'load_avg_before': [round(x, 2) for x in os.getloadavg()]}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for s in (() if a.skip_delay else (0.0, 1.0)):
            rows += delay_run(Path(tmp), s)
        if not a.skip_rtk:
            rows += rtk_runs(Path(tmp), a.preset)
    head['load_avg_after'] = [round(x, 2) for x in os.getloadavg()]
    with open(out, 'a') as f:
        for r in rows:
            f.write(json.dumps({**head, **r}) + '\n')
            sys.stderr.write(json.dumps(r) + '\n')
    sys.stderr.write(f'wrote {out}\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
