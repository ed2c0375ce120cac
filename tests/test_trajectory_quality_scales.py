"""`--accept` on every trajectory format's own quality scale (issue #45), past fix and float: the float epochs
(150-157) of each file in tests/data/trajectories/ written again as that format's DGPS (code) and single
(autonomous) qualities, in its own words or numbers. Each reads onto the common scale (RTKLIB's Q: 4 dgps,
5 single), and `--accept dgps` keeps the DGPS epochs' exposures and leaves out the single ones, the same
exposures whatever the format."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from photogram_ros.core.exposure_positions import ExposureOptions
from photogram_ros.io.geotag import GeotagInput, geotag
from photogram_ros.io.trajectory_formats import read_trajectory

DATA = Path(__file__).parent / 'data' / 'trajectories'
MRK = DATA / 'Timestamp.MRK'


def _token(line: str, k: int, sep: str | None) -> tuple[int, int, str]:
    """Start, end and text of the k-th field of a line (whitespace-separated when sep is None)."""
    if sep is None:
        spans = [(m.start(), m.end()) for m in re.finditer(r'\S+', line)]
    else:                    # every field, empty ones included
        pos, spans = 0, []
        for f in line.split(sep):
            spans.append((pos, pos + len(f)))
            pos += len(f) + len(sep)
    a, b = spans[k]
    return a, b, line[a:b]


# file: (field index, separator, the file's float values, its DGPS value, its single value)
SCALES = {
    'rtklib_demo5_5hz.pos': (5, None, {'2'}, '4', '5'),
    'emlid_studio_5hz.pos': (5, None, {'2'}, '4', '5'),
    'grafnav_5hz_dms.txt': (-3, None, {'2', '3'}, '4', '6'),
    'inertial_explorer_5hz_utc.csv': (8, ',', {'2', '3'}, '5', '6'),
    'emlid_studio_5hz.csv': (-7, ',', {'FLOAT'}, 'DGPS', 'SINGLE'),
    'tbc_5hz.csv': (-2, ',', {'Float'}, 'Code', 'Autonomous'),
    'leica_infinity_5hz.csv': (-1, ';', {'Phase float'}, 'DGNSS', 'Navigated'),
}


def _rewritten(name: str, cls: str, out: Path) -> Path:
    k, sep, floats, dgps, single = SCALES[name]
    lines, n = [], 0
    for line in (DATA / name).read_text().splitlines():
        if line.strip() and not line.startswith('%'):
            try:
                a, b, word = _token(line, k, sep)
            except IndexError:
                word = ''
            if word in floats:
                line = line[:a] + (dgps if cls == 'dgps' else single) + line[b:]
                n += 1
        lines.append(line)
    assert n >= 5, f'{name}: {n} float epochs found'
    p = out / f'{cls}_{name}'
    p.write_text('\n'.join(lines) + '\n')
    return p


def _left_out(res) -> list[str]:
    return sorted(p.split('(event ')[1].split(')')[0] for p in res.problems if 'worse than' in p)


@pytest.mark.parametrize('name', sorted(SCALES))
def test_accept_dgps_keeps_dgps_and_leaves_out_single_on_each_format(name, tmp_path):
    fix_only = _left_out(geotag(GeotagInput(str(DATA / name), str(MRK), None, str(tmp_path / 'f.txt'),
                                            skip_unplaced=True, options=ExposureOptions(accept_q=1))))
    assert fix_only
    for cls, q in (('dgps', 4), ('single', 5)):
        p = _rewritten(name, cls, tmp_path)
        track = read_trajectory(p)
        assert set(np.unique(track.q).tolist()) == {1, q}, (name, cls, np.unique(track.q))
        res = geotag(GeotagInput(str(p), str(MRK), None, str(tmp_path / f'{cls}.txt'), skip_unplaced=True,
                                 options=ExposureOptions(accept_q=4)))
        assert _left_out(res) == ([] if cls == 'dgps' else fix_only), (name, cls)
        everything = geotag(GeotagInput(str(p), str(MRK), None, str(tmp_path / f'{cls}_all.txt'), skip_unplaced=True,
                                        options=ExposureOptions(accept_q=6)))
        assert _left_out(everything) == []
        # a dgps or single epoch's accuracy is at least its class's floor (0.5 m, 1.5 m horizontal)
        worst = max(pe.h_acc_m for _, pe in everything.rows)
        assert worst >= (0.5 if cls == 'dgps' else 1.5)


def test_the_command_line_accept_words(tmp_path, capsys):
    from photogram_ros.cli import main
    p = _rewritten('tbc_5hz.csv', 'single', tmp_path)
    rc = main(['geotag', '--pos', str(p), '--events', str(MRK), '--out', str(tmp_path / 'g.txt'), '--accept', 'dgps',
               '--skip-unplaced'])
    err = capsys.readouterr().err
    assert rc == 0 and 'Autonomous' in err
    kept = len((tmp_path / 'g.txt').read_text().splitlines()) - 1
    rc = main(['geotag', '--pos', str(p), '--events', str(MRK), '--out', str(tmp_path / 'g2.txt'), '--accept', 'single'])
    assert rc == 0 and len((tmp_path / 'g2.txt').read_text().splitlines()) - 1 == 30 > kept
