"""How far an option travels: the figures of a parameter-flow sheet, written as result lines. Issue 46: `opt`
entering photogram_ros/io/triangulate_action.py `triangulate` makes at most 35 stays and 15 returns (the default
--entry); `replay --gcp` reaches stages/adjustment.py (--entry photogram_ros/commands/replay.py:run:a --reach
stages/adjustment.py: the first stay in each --reach room and the names it came in by).

A sheet is the text a static parameter-flow tracer prints for `io/triangulate_action.py:triangulate:opt`: a
summary line `S stays; R rooms; C climbs back up; T returns to a room I had left; ...` (with `CUT OFF after N
events` when the trip was cut at its event budget), then one line per stay, `K. floor F  ROOM  ...` (a room is a
file; `core/`, `bundle/` are the adjuster's layer). The tracer is not part of the project and is not run here:
each sheet is given as LABEL:COMMIT:EVENTS:PATH (the commit of the code it traced and its event budget), and
this script reads the figures out of it and writes one line per sheet, with the stays per layer and per room.

    .venv/bin/python bench/house_walk.py before:b33926f:400:SHEET after:HEAD:400:SHEET [...]
    .venv/bin/python bench/house_walk.py --entry photogram_ros/commands/replay.py:run:a \
        --reach stages/adjustment.py --out bench/results/house_walk_gcp_HEAD.jsonl before:e4ee88f:400:SHEET [...]
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
ARRIVAL = re.compile(r'in by `([^`]+)` as `([^`]+)`')
TRIANGULATE = 'photogram_ros/io/triangulate_action.py:triangulate:opt'
MODULES = ['photogram_ros/commands/triangulate.py', 'photogram_ros/io/triangulate_action.py',
           'photogram_ros/io/aerial_triangulation.py', 'photogram_ros/io/split_merge_action.py',
           'photogram_ros/io/photo_block.py']
# The rooms of the replay --gcp walk.
REPLAY_GCP = 'photogram_ros/commands/replay.py:run:a'
REPLAY_MODULES = ['photogram_ros/commands/replay.py', 'photogram_ros/commands/common_args.py',
                  'photogram_ros/io/control_file.py', 'photogram_ros/nodes/replay_session.py',
                  'photogram_ros/nodes/graph.py', 'photogram_ros/nodes/bundle_node.py',
                  'photogram_ros/stages/adjustment.py']


def layer(room: str) -> str:
    """The layer of a room as the sheet names it (a path cut to its last two parts)."""
    head = room.split('/')[0]
    return 'core' if head in ('core', 'bundle') else head if head in ('io', 'commands', 'stages', 'nodes') else 'other'


def read_sheet(text: str, reach=()) -> dict:
    """The figures of one sheet: stays, rooms, climbs, returns, whether it was cut off, stays per layer and room;
    for each room of `reach`, the first stay in it (1-based, None: never reached) and the function and name it came
    in by there."""
    m = SUMMARY.search(text)
    if m is None:
        raise SystemExit('no "S stays; R rooms; C climbs back up; T returns" line in the sheet')
    lines = [ln for ln in text.splitlines() if STAY.match(ln)]
    rooms = [STAY.match(ln).group(1) for ln in lines]
    stays, n_rooms, climbs, returns = (int(v) for v in m.groups())
    if len(rooms) != stays:
        raise SystemExit(f'the sheet says {stays} stays but lists {len(rooms)}')
    cut = CUT.search(text)
    reached = {}
    for room in reach:
        k = rooms.index(room) if room in rooms else None
        came = ARRIVAL.search(lines[k]) if k is not None else None
        reached[room] = {'first_stay': None if k is None else k + 1,
                         'in_by': came.group(1) if came else None, 'as': came.group(2) if came else None}
    return {'stays': stays, 'rooms': n_rooms, 'climbs': climbs, 'returns': returns,
            'cut_off_at_events': int(cut.group(1)) if cut else None,
            'stays_by_layer': dict(Counter(layer(r) for r in rooms).most_common()),
            'stays_by_room': dict(Counter(rooms).most_common()), **({'reaches': reached} if reach else {})}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('sheets', nargs='+', help='LABEL:COMMIT:EVENTS:PATH, one per sheet')
    ap.add_argument('--out', default=None, help='result file (default bench/results/house_walk_<HEAD>.jsonl)')
    ap.add_argument('--entry', default=TRIANGULATE, help='FILE:FUNCTION:PARAM the sheets enter at (default: '
                                                         'triangulate\'s options)')
    ap.add_argument('--reach', action='append', default=[], metavar='ROOM',
                    help='a room (as the sheet names it, e.g. stages/adjustment.py) whose first stay is recorded; the '
                         'goal of a sheet that is not triangulate\'s')
    a = ap.parse_args()
    goal = {'stays': 35, 'returns': 15} if a.entry == TRIANGULATE else {'reaches': a.reach}
    out = a.out or ROOT / 'bench' / 'results' / f'house_walk_{_git("rev-parse", "--short", "HEAD")}.jsonl'
    modules = {TRIANGULATE: MODULES, REPLAY_GCP: REPLAY_MODULES}.get(a.entry, [a.entry.split(':')[0]])
    with ResultWriter(out, 'house_walk', modules) as w:
        for spec in a.sheets:
            label, commit, events, path = spec.split(':', 3)
            row = {'label': label, 'entry': a.entry, 'code_commit': _git('rev-parse', commit), 'events': int(events),
                   **read_sheet(Path(path).read_text(), a.reach), 'goal': goal}
            w.write(row)
            print(f"{label} ({row['code_commit'][:7]}, {events} events): {row['stays']} stays, {row['returns']} "
                  f"returns, {row['rooms']} rooms; by layer {row['stays_by_layer']}"
                  + (f"; reaches {row['reaches']}" if a.reach else ''))
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
