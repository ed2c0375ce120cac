"""How far triangulate's options travel: the figures of a parameter-flow sheet of `opt` entering
photogram_ros/io/triangulate_action.py `triangulate`, written as result lines (issue 46: at most 35 stays and
15 returns).

A sheet is the text a static parameter-flow tracer prints for `io/triangulate_action.py:triangulate:opt`: a
summary line `S stays; R rooms; C climbs back up; T returns to a room I had left; ...` (with `CUT OFF after N
events` when the trip was cut at its event budget), then one line per stay, `K. floor F  ROOM  ...` (a room is a
file; `core/`, `bundle/` are the adjuster's layer). The tracer is not part of the project and is not run here:
each sheet is given as LABEL:COMMIT:EVENTS:PATH (the commit of the code it traced and its event budget), and
this script reads the figures out of it and writes one line per sheet, with the stays per layer and per room.

    .venv/bin/python bench/house_walk.py before:b33926f:400:SHEET after:HEAD:400:SHEET [...]
"""

from __future__ import annotations

import argparse
import re
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import ResultWriter, _git  # noqa: E402

SUMMARY = re.compile(r'(\d+) stays; (\d+) rooms; (\d+) climbs back up; (\d+) returns')
CUT = re.compile(r'CUT OFF after (\d+) events')
STAY = re.compile(r'^\s*\d+\.\s+floor\s+\d+\s+(\S+)')
MODULES = ['photogram_ros/commands/triangulate.py', 'photogram_ros/io/triangulate_action.py',
           'photogram_ros/io/aerial_triangulation.py', 'photogram_ros/io/split_merge_action.py',
           'photogram_ros/io/photo_block.py']


def layer(room: str) -> str:
    """The layer of a room as the sheet names it (a path cut to its last two parts)."""
    head = room.split('/')[0]
    return 'core' if head in ('core', 'bundle') else head if head in ('io', 'commands', 'stages', 'nodes') else 'other'


def read_sheet(text: str) -> dict:
    """The figures of one sheet: stays, rooms, climbs, returns, whether it was cut off, stays per layer and room."""
    m = SUMMARY.search(text)
    if m is None:
        raise SystemExit('no "S stays; R rooms; C climbs back up; T returns" line in the sheet')
    rooms = [STAY.match(ln).group(1) for ln in text.splitlines() if STAY.match(ln)]
    stays, n_rooms, climbs, returns = (int(v) for v in m.groups())
    if len(rooms) != stays:
        raise SystemExit(f'the sheet says {stays} stays but lists {len(rooms)}')
    cut = CUT.search(text)
    return {'stays': stays, 'rooms': n_rooms, 'climbs': climbs, 'returns': returns,
            'cut_off_at_events': int(cut.group(1)) if cut else None,
            'stays_by_layer': dict(Counter(layer(r) for r in rooms).most_common()),
            'stays_by_room': dict(Counter(rooms).most_common())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('sheets', nargs='+', help='LABEL:COMMIT:EVENTS:PATH, one per sheet')
    ap.add_argument('--out', default=None, help='result file (default bench/results/house_walk_<HEAD>.jsonl)')
    a = ap.parse_args()
    out = a.out or ROOT / 'bench' / 'results' / f'house_walk_{_git("rev-parse", "--short", "HEAD")}.jsonl'
    with ResultWriter(out, 'house_walk', MODULES) as w:
        for spec in a.sheets:
            label, commit, events, path = spec.split(':', 3)
            row = {'label': label, 'entry': 'photogram_ros/io/triangulate_action.py:triangulate:opt',
                   'code_commit': _git('rev-parse', commit), 'events': int(events),
                   **read_sheet(Path(path).read_text()), 'goal': {'stays': 35, 'returns': 15}}
            w.write(row)
            print(f"{label} ({row['code_commit'][:7]}, {events} events): {row['stays']} stays, {row['returns']} "
                  f"returns, {row['rooms']} rooms; by layer {row['stays_by_layer']}")
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
