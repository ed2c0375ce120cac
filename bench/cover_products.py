"""Products against what the photos saw, on the real surveys flown with one stereo pair per spot.

`photogram-ros replay` on seneca_part (41 photos of a fixed-wing, ~60 % forward overlap: one pair per spot),
every other photo of it (real_surveys.half_overlap_block: half the forward overlap) and brighton (18 photos,
OpenDroneMap's cloud as the peer), each measured by bench/real_surveys.measure: the DSM over the camera centres'
hull unclipped by the raster (bench/cover_footprint.py: measured by any pairs, by one pair only), the export's
own footprint shares (export.json dsm.footprint), what one pair says of the interpolated cells
(dsm.one_pair_check), the verdict (report.json mapping) and, for brighton, the DSM against ODM's.

    python bench/cover_products.py [--only seneca_half,seneca,brighton] [--out DIR]

About 4 minutes on 2 loaded cores. Lines go to bench/results/cover_products_<commit>.jsonl.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import real_surveys as rs  # noqa: E402
from bench.machine import ResultWriter, tree_state  # noqa: E402

SURVEYS = ('seneca_half', 'seneca', 'brighton')
KEEP = ('survey', 'pipeline', 'command', 'exit', 'wall_s', 'photos', 'oriented', 'given', 'keyframes_taken',
        'mapping', 'dsm_hull_share', 'dsm_measured_hull_share', 'dsm_raster_share', 'dsm_hull_cells',
        'footprint_hull_cells', 'footprint_hull_in_raster', 'dsm_footprint_valid_share',
        'dsm_footprint_measured_share', 'dsm_footprint_one_pair_share', 'export_footprint', 'dsm_one_pair',
        'peer', 'peer_in_hull', 'peer_in_hull_measured', 'last_line', 'stderr_last')


def run(survey: str, out: Path) -> dict:
    if survey == 'seneca_half':
        folder = out / 'blocks' / 'seneca_half'
        ref = rs.half_overlap_block(rs.SENECA / 'images', folder)
        return rs.run_photos(survey, 'replay', folder, out, None, reference=ref)
    src, peer = {'seneca': (rs.SENECA, None), 'brighton': (rs.BRIGHTON, 'odm')}[survey]
    return rs.run_photos(survey, 'replay', src / 'images', out, peer)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--only', default=','.join(SURVEYS), help='surveys, comma separated')
    ap.add_argument('--out', default='/tmp/cover_products', help='output folder')
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    commit = tree_state()['commit'][:7]
    writer = ResultWriter(ROOT / 'bench' / 'results' / f'cover_products_{commit}.jsonl', 'cover_products',
                          rs.MODULES + ['bench/cover_products.py', 'bench/cover_footprint.py'])
    for survey in [s.strip() for s in a.only.split(',') if s.strip()]:
        row = run(survey, out)
        line = {k: row[k] for k in KEEP if k in row}
        writer.write(line)
        m = row.get('mapping') or {}
        print(f"{survey}: exit {row.get('exit')}, mapped {m.get('mapped')}, camera hull unclipped "
              f"{rs._f(row.get('dsm_footprint_measured_share'), '.1%')} measured, "
              f"{rs._f(row.get('dsm_footprint_one_pair_share'), '.1%')} by one pair; "
              f"failures {m.get('failures')}; warnings {m.get('warnings')}", flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
