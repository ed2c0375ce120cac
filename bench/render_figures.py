"""Render the figure tables of docs/measurements.md and README.md from the result files in bench/results.

    .venv/bin/python bench/render_figures.py           # rewrite the tables in place
    .venv/bin/python bench/render_figures.py --check   # list every figure (its result file, fresh or stale);
                                                       # exit 1 and name the documents whose tables differ
    .venv/bin/python bench/render_figures.py --check --strict   # ... exit 1 also when a figure is stale or
                                                                # has no result file

A table sits between `<!-- figures:NAME -->` and `<!-- /figures:NAME -->` in a document; everything
outside the markers is hand-written and left alone. Each table is one entry of TABLES below: its columns and
its rows, one `Figure` a row. A Figure names the result files it reads (a glob under bench/results), which
of their lines it takes (`where`: key -> value) and how it writes them (`cells`: the chosen line -> the
row's cells). Of the files that hold such a line, the newest is used: the one whose line records the latest
commit (git's commit time; a file without a commit counts as oldest). The last cell of every row names that
file and the commit it was measured at, and says:
- **stale** when one of the figure's modules (the Figure's when its spec names them: a component figure
  names its component; else the line's `modules`, else the whole product; less the Figure's
  `ignore`, each said why in the spec) changed after that commit (git log, or an uncommitted change in the
  working tree). A line whose modules were traced (of them, those inside the Figure's modules when it names some) (`module_trace.complete`: the files the bench and its child
  processes ran, bench/machine.py; those of every line of its file) is stale when one of those files differs
  between its commit and HEAD (git diff) or in the working tree,
- "modified tree" when the line says the tree had uncommitted changes (`clean` false), and "tree state not
  recorded" for files written before bench/machine.py's ResultWriter,
- "no result file" (and no figure) when no file holds the line.

A new bench's figure is one Figure in one TABLES entry (and its markers in the document, once).
tests/test_figures_rendered.py fails when the committed documents differ from what this renders.
"""

from __future__ import annotations

import argparse
import functools
import json
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / 'bench' / 'results'
DOCUMENTS = ('README.md', 'docs/measurements.md')
PRODUCT = ('photogram_ros', 'config')        # the whole product code: what an end-to-end figure measures
NO_FILE = 'no result file'


# --- git -------------------------------------------------------------------------------------------------


def _git(*args: str) -> str:
    r = subprocess.run(['git', *args], cwd=ROOT, capture_output=True, text=True)
    return r.stdout.strip() if r.returncode == 0 else ''


@functools.lru_cache(maxsize=None)
def full_commit(rev: str) -> str:
    """The full hash of `rev` when it is a commit of this history, else ''."""
    return _git('rev-parse', '--verify', '--quiet', f'{rev}^{{commit}}') if rev else ''


@functools.lru_cache(maxsize=None)
def commit_time(commit: str) -> int:
    out = _git('log', '-1', '--format=%ct', commit) if commit else ''
    return int(out) if out else -1


@functools.lru_cache(maxsize=None)
def changed_since(commit: str, modules: tuple[str, ...]) -> int:
    """Commits after `commit` that change `modules`, plus 1 when the working tree changes them now."""
    n = _git('rev-list', '--count', f'{commit}..HEAD', '--', *modules)
    dirty = _git('status', '--porcelain', '--untracked-files=no', '--', *modules)
    return int(n or 0) + (1 if dirty else 0)


@functools.lru_cache(maxsize=None)
def files_changed(commit: str, files: tuple[str, ...]) -> tuple[str, ...]:
    """Those of `files` (pathspecs) that differ between `commit` and HEAD, or in the working tree now."""
    out = set(_git('diff', '--name-only', commit, 'HEAD', '--', *files).splitlines())
    out |= set(_git('diff', '--name-only', 'HEAD', '--', *files).splitlines())
    return tuple(sorted(x for x in out if x))


# --- result files ----------------------------------------------------------------------------------------


def read_lines(path: Path) -> list[dict]:
    rows = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if line:
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return rows


def line_commit(line: dict, path: Path) -> str:
    """The exact commit a line was measured at: its `commit` (the ResultWriter's full hash; older benches
    wrote 'PRODUCT (HEAD abc1234)': the HEAD is the tree that ran), else the file name's _<hex> suffix."""
    c = str(line.get('commit') or '')
    m = re.search(r'HEAD ([0-9a-f]{7,40})', c) or re.match(r'([0-9a-f]{7,40})\b', c) \
        or re.search(r'_([0-9a-f]{7,40})\.jsonl$', path.name)
    return full_commit(m.group(1)) if m else ''


def line_clean(line: dict) -> bool | None:
    if 'clean' in line:
        return bool(line['clean'])
    if 'clean_tree' in line:
        return bool(line['clean_tree'])
    return False if '+modified' in str(line.get('commit', '')) else None


def matches(line: dict, where: dict) -> bool:
    for k, v in where.items():
        x = line
        for part in k.split('.'):
            x = x.get(part) if isinstance(x, dict) else None
        if callable(v):
            if not v(x):
                return False
        elif x != v:
            return False
    return True


@dataclass(frozen=True)
class Figure:
    """One row of a rendered table: `label` (its first cells, hand-written: what was measured), the result
    files `results` (a glob under bench/results; '' for a figure no bench writes yet), the line taken
    (`where`: dotted keys, values or predicates; the last matching line of a file), `cells` ((that line, every
    line of its file) -> the figure's cells) and `modules` (what the figure measures: when given, they win over
    the line's own, which name what the bench runs; None: the line's, else the whole product)."""
    label: tuple
    results: str = ''
    where: dict = field(default_factory=dict)
    cells: Callable[[dict, list], list] | None = None
    modules: tuple | None = None
    command: str = ''
    tail: tuple = ()          # hand-written cells after the figure's (e.g. a link to the section)
    ignore: tuple = ()        # paths inside the modules whose change does not touch this figure (said in the spec)


@dataclass
class Source:
    path: Path
    line: dict
    lines: list
    commit: str
    clean: bool | None
    modules: tuple
    traced: bool = False      # `modules` are the files the bench ran (bench/machine.py's trace), not declared


def line_traced(line: dict) -> bool:
    t = line.get('module_trace')
    return isinstance(t, dict) and t.get('complete') is True and bool(line.get('modules'))


def traced_modules(ran: set, spec: tuple | None) -> tuple:
    """A traced figure's modules: the files its bench ran; those inside the Figure's own modules when it names
    some narrower than the whole product (a component's figure: what ran of its component, and its paths outside
    the product as they are)."""
    if not spec or tuple(spec) == PRODUCT:
        return tuple(sorted(ran))
    inside = {m for m in ran if any(m == p or m.startswith(p.rstrip('/') + '/') for p in spec)}
    inside |= {p for p in spec if p.split('/')[0] not in PRODUCT}
    return tuple(sorted(inside)) or tuple(spec)


def changes(src: Source, fig: Figure) -> tuple[int, tuple]:
    """(how many commits changed the figure's modules since its line's commit, +1 for the working tree; or, for a
    traced line, how many of the files it ran differ; those files)."""
    excluded = tuple(f':(exclude){p}' for p in fig.ignore)
    if src.traced:
        changed = files_changed(src.commit, src.modules + excluded)
        return len(changed), changed
    return changed_since(src.commit, src.modules + excluded), ()


def newest(fig: Figure) -> Source | None:
    best, best_key = None, None
    for path in sorted(RESULTS.glob(fig.results)) if fig.results else []:
        lines = read_lines(path)
        hits = [x for x in lines if matches(x, fig.where)]
        if not hits:
            continue
        line = hits[-1]
        commit = line_commit(line, path)
        key = (commit_time(commit), path.name)
        if best_key is None or key > best_key:
            best_key = key
            clean = line_clean(line)
            if clean is None and lines and 'clean_tree' in lines[0]:   # an older bench's header line says it
                clean = bool(lines[0]['clean_tree'])
            # A figure's cells may read any line of its file: a traced figure's modules are every line's (each
            # line's trace holds what the bench ran until then), when every line's trace is complete.
            recorded = [x for x in lines if 'modules' in x]
            traced = bool(recorded) and all(line_traced(x) for x in recorded)
            # (else the declared modules: a traced line beside an incomplete one is not measured alone)
            modules = tuple(fig.modules or line.get('modules_declared') or line.get('modules') or PRODUCT)
            if traced:
                modules = traced_modules({m for x in lines for m in x.get('modules') or ()}, fig.modules)
            best = Source(path, line, lines, commit, clean, modules, traced)
    return best


def source_cell(src: Source | None, fig: Figure) -> str:
    if src is None:
        return NO_FILE + (f' (measure: `{fig.command}`)' if fig.command else '')
    rel = src.path.relative_to(ROOT).as_posix() if src.path.is_relative_to(ROOT) else src.path.name
    if not src.commit:
        return f'`{rel}`, commit not in this history: **stale**'
    notes = []
    n, _ = changes(src, fig)
    if n:
        # Not the count of commits: the rendered text changes when a figure turns stale, not with every commit
        # after (`--check` lists the count, and a traced line's changed files).
        notes.append('**stale**: a file it ran changed since' if src.traced
                     else f'**stale**: {", ".join(src.modules)} changed since')
    if src.clean is False:
        notes.append('modified tree')
    elif src.clean is None:
        notes.append('tree state not recorded')
    return f'`{rel}` @ {src.commit[:7]}' + (f' ({"; ".join(notes)})' if notes else '')


def figure_state(fig: Figure) -> dict:
    """Where a figure comes from: {'file', 'commit', 'state'}; state is 'fresh', 'stale' (a module it measures
    changed since its commit, or the commit is not in this history), 'modified tree' (fresh, but measured on a
    tree with uncommitted changes), 'tree state not recorded' (fresh, from a file written before the
    ResultWriter) or 'no result file'; 'changed' counts the commits (+1 for the working tree) since."""
    src = newest(fig)
    if src is None:
        return {'file': None, 'commit': None, 'state': NO_FILE, 'changed': None, 'command': fig.command}
    rel = src.path.relative_to(ROOT).as_posix() if src.path.is_relative_to(ROOT) else src.path.name
    if not src.commit:
        return {'file': rel, 'commit': None, 'state': 'stale', 'changed': None, 'command': fig.command}
    n, files = changes(src, fig)
    state = ('stale' if n else 'modified tree' if src.clean is False else
             'tree state not recorded' if src.clean is None else 'fresh')
    return {'file': rel, 'commit': src.commit[:7], 'state': state, 'changed': n, 'command': fig.command,
            'traced': len(src.modules) if src.traced else None, 'changed_files': list(files)}


def listing() -> list[dict]:
    """Every figure of every table a document renders: {'document', 'table', 'figure' (its label), **figure_state}."""
    out = []
    for doc in DOCUMENTS:
        for m in MARK.finditer((ROOT / doc).read_text()):
            name = m.group('name')
            for fig in TABLES[name].rows if name in TABLES else ():
                out.append({'document': doc, 'table': name, 'figure': ' / '.join(str(c) for c in fig.label if c),
                            **figure_state(fig)})
    return out


def listing_text(rows: list[dict]) -> str:
    lines = []
    for r in rows:
        where = (f"{r['file']} @ {r['commit']}" if r['commit'] else (r['file'] or '')) or \
            (f"measure: {r['command']}" if r['command'] else '')
        more = f" ({r['changed']} commit{'s' if r['changed'] != 1 else ''} since)" if r.get('changed') else ''
        if r.get('traced'):
            more = (f" ({r['changed']} of the {r['traced']} files it ran changed: "
                    f"{', '.join(r['changed_files'][:4])}{' ...' if r['changed'] > 4 else ''})" if r.get('changed')
                    else f" ({r['traced']} files it ran, none changed)")
        lines.append(f"{r['state'].upper():24} {r['document']}#{r['table']}: {r['figure'][:90]} <- {where}{more}")
    counts = {}
    for r in rows:
        counts[r['state']] = counts.get(r['state'], 0) + 1
    lines.append(f'{len(rows)} figures: ' + ', '.join(f'{v} {k}' for k, v in sorted(counts.items())))
    return '\n'.join(lines)


def _esc(v) -> str:
    return str(v).replace('|', '\\|').replace('\n', ' ')


@dataclass(frozen=True)
class Table:
    columns: tuple            # the header, without the last column (the result file)
    rows: tuple               # Figure


def render_table(t: Table) -> str:
    width = len(t.columns)
    out = ['| ' + ' | '.join(t.columns) + ' | result file |', '|' + '---|' * (width + 1)]
    for fig in t.rows:
        src = newest(fig)
        label = [str(c) for c in fig.label]
        body = list(fig.cells(src.line, src.lines)) if src is not None and fig.cells is not None else []
        cells = label + (body or ['—'] * max(0, width - len(label) - len(fig.tail))) + [str(c) for c in fig.tail]
        # Cells beyond the table's width join the last one; missing cells are dashes.
        cells = cells[:width - 1] + ['; '.join(c for c in cells[width - 1:] if c)] if len(cells) > width else \
            cells + ['—'] * (width - len(cells))
        out.append('| ' + ' | '.join(_esc(c) for c in cells + [source_cell(src, fig)]) + ' |')
    return '\n'.join(out)


# --- formatting helpers for the specs --------------------------------------------------------------------


def f(v, fmt: str = '.2f', unit: str = '') -> str:
    if v is None:
        return 'n/a'
    try:
        return format(v, fmt) + unit
    except (TypeError, ValueError):
        return str(v)


def pct(v) -> str:
    return 'n/a' if v is None else f'{100 * v:.0f} %'


def cm(v) -> str:
    return 'n/a' if v is None else f'{100 * v:.1f} cm'


def verdict(line: dict, most: int = 260) -> str:
    v = line.get('verdict')
    text = v.get('summary', '') if isinstance(v, dict) else str(v or '')
    if isinstance(v, dict) and v.get('decided_by') and 'decided by' not in text:
        text = f'[decided by {", ".join(v["decided_by"])}] {text}'
    if not isinstance(v, dict) and line.get('last_line'):
        text = f'{text.upper()} ({line["last_line"]})' if text else line['last_line']
    return text if len(text) <= most else text[:most].rsplit(' ', 1)[0] + ' …'


def survey_cells(x: dict, _lines=None) -> list:
    """A real-survey row: oriented, after a robust similarity H / V, rigid H / V, nadir, reprojection, peer."""
    peer = x.get('peer') or {}
    if 'median_abs_dz_m' in peer:
        hull = x.get('peer_in_hull') or {}
        p = (f'ODM against our {"DSM" if x["pipeline"] == "replay" else "sparse cloud"} after a constant offset: '
             f'median |dz| {cm(peer["median_abs_dz_m"])}'
             + (f', {cm(hull["median_abs_dz_m"])} inside the camera centres\' hull' if hull else ''))
    elif 'peer_h_m' in peer:
        p = (f'pycolmap {peer["peer_h_m"]:.2f} / {peer["peer_v_m"]:.2f} m after its similarity; per photo '
             f'{peer["diff_h_m"]:.2f} m H apart')
    else:
        p = '—'
    measured = x.get('dsm_footprint_measured_share', x.get('dsm_measured_hull_share'))
    one_pair = x.get('dsm_footprint_one_pair_share')
    of_tri = (f'; {x["replay_oriented_of_triangulated"]}/{x["keyframes_triangulated"]} of the keyframes whose photos '
              f'triangulate oriented' + ('' if x.get('share_exact') else ' (at least)')
              if x.get('share_of_triangulated') is not None else '')
    return [f'{x.get("oriented")}/{x.get("given")}' + (' keyframes' if x.get('pipeline') == 'replay' else '') + of_tri,
            f'{f(x.get("sim_h_m"))} / {f(x.get("sim_v_m"))} m', f'{f(x.get("rigid_h_m"))} / {f(x.get("rigid_v_m"))} m',
            f'{pct(x.get("nadir_share"))} (median {f(x.get("tilt_median_deg"), ".1f")}°)',
            f'{f(x.get("reprojection_px"), ".3f")} px' + (f'; DSM: {pct(measured)} of the camera centres\' hull '
                                                          'measured by stereo' if measured is not None else '')
            + (f' ({pct(one_pair)} by one pair only)' if one_pair is not None else '') + _mapping_failed(x), p]


def _mapping_failed(x: dict) -> str:
    """A replay that made no map says so in its row, with its first reason (its exit status)."""
    m = x.get('mapping') or {}
    if m.get('mapped') is not False:
        return ''
    why = (m.get('failures') or ['no reason given'])[0]
    return f'; **MAPPING FAILED** (exit {x.get("exit")}): {why}'


def agreement_cells(x: dict, _lines=None) -> list:
    return [f'{x["n"]}', f'{x["rms_3d_m"]:.2f} m RMS 3D ({x["h_m"]:.2f} m H / {x["v_m"]:.2f} m V), max '
            f'{x["max_3d_m"]:.2f} m']


def stereo_cells(x: dict, lines: list) -> list:
    plain = next((y for y in lines if y.get('scene') == x['scene'] and y.get('method') == 'plain_sgbm'), {})
    return [f'bad-2 {x["bad2"]:.4f} at density {x["density"]:.2f}; plain SGBM in the same run '
            f'{f(plain.get("bad2"), ".4f")} at {f(plain.get("density"))}']


# --- the tables ------------------------------------------------------------------------------------------

REAL = 'real_surveys*.jsonl'
REAL_CMD = 'ROS_DOMAIN_ID=N .venv/bin/python bench/real_surveys.py --variants --noisy brighton,toledo --out OUT'
STEREO_CMD = '.venv/bin/python bench/stereo_middlebury.py ../shared/data/stereo/{tsukuba,venus,cones,teddy} --out F'
BAL_CMD = '.venv/bin/python bench/bundle_bal.py ../shared/data/bal/problem-49-7776-pre.txt --peers --out F'
SCALE = 'photo_triangulation_scale*.jsonl'
SCALE_CMD = '.venv/bin/python bench/photo_triangulation_scale.py --photos 600 --modes split --counts 1 2 --split-photos 320'


# The block check runs after a block is oriented and only writes its verdict (no real set is split into sub-blocks,
# whose merge reads their verdicts): a change to it leaves the orientation figures as they are, not the verdicts.
AFTER_ORIENTATION = ('photogram_ros/core/block_check.py',)


def _survey(label, survey, pipeline):
    return Figure((label, pipeline), REAL, {'survey': survey, 'pipeline': pipeline}, survey_cells, PRODUCT, REAL_CMD,
                  ignore=AFTER_ORIENTATION)


def _verdict(label, survey, pipeline):
    return Figure((label, pipeline), REAL, {'survey': survey, 'pipeline': pipeline}, lambda x, _: [verdict(x)],
                  PRODUCT, REAL_CMD)


def _agreement(label, survey):
    return Figure((label,), REAL, {'survey': survey, 'pipeline': 'replay vs triangulate'}, agreement_cells, PRODUCT,
                  REAL_CMD, ignore=AFTER_ORIENTATION)


def _stereo(scene):
    return Figure((f'stereo on Middlebury {scene} (the module\'s default)',), 'stereo_middlebury*.jsonl',
                  {'scene': scene, 'method': 'ours'}, stereo_cells,
                  ('photogram_ros/core/stereo.py', 'photogram_ros/core/stereo_eval.py'), STEREO_CMD)


def _none(*label, command='', tail=()):
    """A row no bench writes a result file for (yet): its figure is not quoted."""
    return Figure(tuple(label), '', command=command, tail=tuple(tail))


def _readme(label, fig: Figure, cells, more: str) -> Figure:
    """A README headline row: the figure's line, said in one cell, and the docs section."""
    return Figure((label,), fig.results, fig.where, lambda x, lines: [cells(x, lines)], fig.modules, fig.command,
                  (more,), fig.ignore)


def _busy(load, cores) -> bool:
    """A run that began with the machine's cores already loaded (other work beside it): its wall time is not a
    speed figure."""
    return load is not None and cores is not None and load >= cores


def _busy_runs(lines: list) -> list:
    """The runs of a scale bench's file that began on a loaded machine (`_busy`)."""
    return [y['run'] for y in lines if isinstance(y.get('run'), dict) and y['run'].get('mode') in (None, 'split')
            and _busy(y['run'].get('load_before'), y.get('cores'))]


def _dask_matching_cell(x: dict, lines: list) -> str:
    busy = _busy_runs(lines)
    if busy:
        return (f'2 workers against 1 not compared: the {busy[0]["workers"]}-worker run began at load '
                f'{busy[0]["load_before"]} ({x["photos"]} simulated photos), same matches: {x.get("same_matches")}')
    return (f'matching {x["matching_speedup"]:.2f}x faster on 2 workers than on 1 ({x["photos"]} simulated photos, '
            f'same run), same matches: {x.get("same_matches")}')


def _scale_cells(x: dict, lines: list) -> list:
    r = x['run']
    cores = x.get('cores')
    cmp_ = next((y for y in lines if y.get('compare')), {})
    busy = _busy_runs(lines)
    wall = (f'{r["wall_s"]:.0f} s wall on {r["workers"]} worker(s) at load {r["load_before"]}'
            + (f' on {cores} cores (other work beside it: not a speed figure)' if _busy(r['load_before'], cores) else ''))
    speed = ''
    if cmp_.get('speedup') and r['workers'] == 2:
        speed = (f'; 2 workers against 1 not compared (the {busy[0]["workers"]}-worker run began at load '
                 f'{busy[0]["load_before"]})' if busy else f'; 2 workers {cmp_["speedup"]:.2f}x faster than 1 in the same run')
    return [f'{r["oriented"]}/635 oriented, check points {cm(r["check_h_m"])} / '
            f'{cm(r["check_v_m"])} (n={r["check_n"]}), ' + wall + speed]


def _split_cells(x: dict, lines: list) -> list:
    r = x['run']
    return [f'{r["oriented"]} oriented, check points {cm(r["check_h_m"])} / {cm(r["check_v_m"])}, {r["wall_s"]:.0f} s wall']


def _control_cells(x: dict, _lines) -> list:
    w, wo = x['with'], x['without']
    return [f'{x["keyframes"]} keyframes, {x["gcps"]} GCPs: live check points (median) {cm(w["live_check_median_m"][0])} '
            f'/ {cm(w["live_check_median_m"][1])} against {cm(wo["live_check_median_m"][0])} / '
            f'{cm(wo["live_check_median_m"][1])} without the control adjustment, for {x["time_ratio"]:.2f}x the '
            'stage\'s time (same run' + (f', load average {x["load_avg"][0]:.0f}' if x.get('load_avg') else '') + ')']


PPK_CMD = '.venv/bin/python bench/ppk_survey.py --out F'
# bench/control_adjustment_cost.py: simulated keyframes through stages/adjustment.AdjustmentStage (no ROS nodes).
CONTROL_MODULES = ('photogram_ros/core', 'photogram_ros/stages', 'photogram_ros/sim', 'photogram_ros/params.py', 'config')


def _ppk(label, case):
    return Figure((label,), 'ppk_survey*.jsonl', {'case': case},
                  lambda x, _: [f'check points {cm(x["check_h_m"])} H / {cm(x["check_v_m"])} V '
                                f'({x["check_h_gsd"]:.2f} / {x["check_v_gsd"]:.2f} GSD), {x["check_n"]} targets'],
                  None, PPK_CMD)


PPK_POSITIONS = Figure(('PPK photo survey (`simulate --ppk`, `geotag`; tiny preset): camera positions',),
                       'ppk_survey*.jsonl', {'case': 'camera_positions'},
                       lambda x, _: [f'geotags {cm(x["median_m"])} median from the true camera centres (max '
                                     f'{cm(x["max_m"])}); against the MRK offsets: ArduPilot CAM + lever arm '
                                     f'{1000 * x["cam_bin_vs_mrk_max_m"]:.1f} mm, .tlog '
                                     f'{1000 * x["tlog_vs_mrk_max_m"]:.1f} mm, EXIF times '
                                     f'{1000 * x["exif_vs_mrk_max_m"]:.1f} mm (max)'], None, PPK_CMD)


def _ground_cells(x: dict, _lines) -> list:
    eq = max(x['check_diff_h_m'], x['check_diff_v_m'], x['gcp_diff_h_m'], x['gcp_diff_v_m'])
    return [f'final check points on the page **{cm(x["page_check_h_m"])} / {cm(x["page_check_v_m"])}** '
            f'({x["page_check_n"]}), GCP residuals {cm(x["page_gcp_h_m"])} / {cm(x["page_gcp_v_m"])}, equal to the '
            f'report\'s to {"under 0.001 mm" if eq < 1e-6 else f"{1000 * eq:.3f} mm"}; in flight from the final georeference on at most '
            f'{cm(x["live_check_h_max_m"])} H over {x["live_final_polls"]} polls; {x["nogo_polls"]} NO-GO of '
            f'{x["polls"]} polls, final {x["final_verdict"]}']


GROUND = Figure(('plain sample flight with its targets file at `--rate 1` beside the ground station',),
                'ground_flight*.jsonl', {'bench': 'ground_flight'}, _ground_cells, ('photogram_ros',),
                'ROS_DOMAIN_ID=N .venv/bin/python bench/ground_flight.py --out F')


BRIGHTON_TRI = _survey('', 'brighton', 'triangulate')
BRIGHTON_REP = _survey('', 'brighton', 'replay')
TOLEDO_TRI = _survey('', 'toledo', 'triangulate')
TOLEDO_AGREE = _agreement('', 'toledo')
SENECA_TRI = _survey('', 'seneca', 'triangulate')
PHANTOM3 = _survey('', 'phantom3', 'replay')
BAL_SCIPY = Figure(('BAL problem-49-7776 (real photos): ours against SciPy',), 'bundle_bal*.jsonl',
                   {'problem': 'problem-49-7776-pre.txt', 'solver': 'scipy_least_squares_trf'},
                   lambda x, _: [f'{x["time_ratio_peer_over_ours"]:.1f}x faster than SciPy\'s least_squares (trf, '
                                 f'sparse finite differences; same run), final cost {x["cost_ratio_ours_over_peer"]:.3f}x '
                                 'SciPy\'s'], ('photogram_ros/core/bundle', 'photogram_ros/io/bal.py'), BAL_CMD)
BAL_CERES = Figure(('BAL problem-49-7776: ours against Ceres (pycolmap)',), 'bundle_bal*.jsonl',
                   {'problem': 'problem-49-7776-pre.txt', 'solver': 'ceres_pycolmap', 'seconds': lambda v: v is not None},
                   lambda x, _: [f'{x["time_ratio_ours_over_peer"]:.2f}x Ceres\'s time (same run), final cost '
                                 f'{x["cost_ratio_ours_over_peer"]:.3f}x Ceres\'s'],
                   ('photogram_ros/core/bundle', 'photogram_ros/io/bal.py'),
                   'pip install -r bench/requirements-peers.txt; ' + BAL_CMD)
SCALE_W2 = Figure(('635 simulated photos, split-merge (2 sub-blocks), 2 workers',), SCALE,
                  {'run.mode': 'split', 'run.workers': 2, 'run.oriented': lambda v: v is not None and v > 600},
                  _scale_cells, PRODUCT, SCALE_CMD)
# The real sets' rows of bench/real_surveys.py: (label, survey, pipeline).
REAL_ROWS = (
    ('brighton_beach (18 DJI FC300S, EXIF only)', 'brighton', 'triangulate'), ('brighton_beach', 'brighton', 'replay'),
    ('toledo (42 DJI FC350, EXIF only)', 'toledo', 'triangulate'), ('toledo', 'toledo', 'replay'),
    ('seneca_part (41 NIR photos, fixed wing)', 'seneca', 'triangulate'), ('seneca_part', 'seneca', 'replay'),
    ('phantom3_village (100 video frames, `import-frames` then `replay`)', 'phantom3', 'replay'),
    ('toledo, every other photo', 'toledo_half', 'triangulate'), ('toledo, every other photo', 'toledo_half', 'replay'),
    ('brighton_beach, every other photo', 'brighton_half', 'triangulate'),
    ('brighton_beach, every other photo', 'brighton_half', 'replay'),
    ('seneca_part, every other photo', 'seneca_half', 'triangulate'),
    ('seneca_part, every other photo', 'seneca_half', 'replay'),
    ('toledo, four geotags moved 80 m', 'toledo_moved4', 'triangulate'),
    ('toledo (42) and brighton (18) in one folder', 'two_sites', 'triangulate'),
    ('brighton_beach, geotags scattered 17 m', 'brighton_noisy', 'triangulate'),
    ('toledo, geotags scattered 17 m', 'toledo_noisy', 'triangulate'))


def _mavlink_cells(x: dict, lines: list) -> list:
    """Per log: the node's parser and parser + ingest against a bare pymavlink recv_match loop (same run)."""
    out = []
    for y in lines:
        if y.get('method') == 'node_parser':
            ingest = next((z for z in lines if z.get('log') == y['log'] and z.get('method') == 'node_parser_plus_ingest'), {})
            out.append(f'{y["log"]} ({y["messages"]} messages{"" if y.get("same_count") else ", counts differ"}): parser '
                       f'{y["ratio_vs_bare"]:.2f}x, parser + ingest {f(ingest.get("ratio_vs_bare"))}x')
    return ['time against a bare pymavlink recv_match loop in the same run (best of 3): ' + '; '.join(out)]


MAVLINK = Figure(('MAVLink parsing against pymavlink',), 'mavlink_parse*.jsonl', {'method': 'node_parser'}, _mavlink_cells,
                 ('photogram_ros/io/mavlink.py', 'photogram_ros/io/mavlink_framing.py', 'photogram_ros/io/mavlink_ingest.py'),
                 '.venv/bin/python bench/mavlink_parse.py --out F')


BLOCK_VERDICTS = 'block_verdicts*.jsonl'
BLOCK_VERDICTS_CMD = 'ROS_DOMAIN_ID=N .venv/bin/python bench/block_verdicts.py --out OUT'
# bench/block_verdicts.py: (label, set, variant) of its `triangulate` rows.
BLOCK_VERDICT_ROWS = tuple(
    (f'{label}, {what}', s, v) for s, label in (('brighton', 'brighton_beach'), ('toledo', 'toledo'))
    for v, what in (('clean', 'every photo'), ('half', 'every other photo'), ('moved', 'geotags moved 80 m'),
                    ('foreign', '3 photos of another camera added'),
                    ('heights', 'heights wandering 100 m' + (' and a wandering 15 m bias' if s == 'toledo' else '')),
                    ('noisy', 'geotags scattered 17 m')))


def _shape_text(x: dict) -> str:
    share = x.get('shape_share')
    if share is None:
        return ''
    return (f'shape {100 * share:.2f} % of the block\'s size ({x["shape_rms_m"]:.2f} m RMS over {x["shape_n"]} '
            f'cameras) from {x.get("reference")}')


def _block_verdict_cells(x: dict, _lines) -> list:
    shape = _shape_text(x)
    return [verdict(x, 200) + (f'; {shape}' if shape else '')]


def _broken_cells(x: dict, lines: list) -> list:
    """Every tipped and folded block of the set (its clean, noisy and wandering-heights runs, each with its own
    geotags, the clean one also with them scattered 17 m): how many FAILED, by which checks."""
    rows = [y for y in lines if y.get('set') == x['set'] and y.get('kind') in ('tipped', 'folded')]
    failed = [y for y in rows if (y.get('verdict') or {}).get('status') == 'failed']
    by = sorted({c for y in failed for c in (y.get('verdict') or {}).get('decided_by', [])})
    return [f'**{len(failed)} of {len(rows)} FAILED** (decided by {", ".join(by)}): tipped 30° and 85° whole, folded '
            '30° along its last strips; from the clean, wandering-heights and noisy-geotag blocks']


def _held_out_cells(x: dict, _lines) -> list:
    return [f'{x["oriented"]}/{x["photos"]} oriented; {_shape_text(x)}; {verdict(x, 160)}']


def _block_verdict(label, survey, variant):
    return Figure((label, 'triangulate'), BLOCK_VERDICTS, {'set': survey, 'variant': variant, 'kind': 'triangulate'},
                  _block_verdict_cells, PRODUCT, BLOCK_VERDICTS_CMD)


def _broken(label, survey):
    return Figure((label, 'the block check'), BLOCK_VERDICTS, {'set': survey, 'kind': 'folded'}, _broken_cells,
                  PRODUCT, BLOCK_VERDICTS_CMD)


# issue #43's share, from bench/real_surveys.py's replay rows (the full sets and their every-other variants):
# of the keyframes whose photos `triangulate` oriented, how many `replay` oriented.
CHAIN_SETS = (('seneca_part (41 NIR photos, fixed wing)', 'seneca'), ('brighton_beach (18 photos)', 'brighton'),
              ('toledo (42 photos)', 'toledo'))


def _chain_cells(x: dict, _lines) -> list:
    share = x.get('share_of_triangulated')
    if 'replay_oriented' not in x:
        return ['—'] * 4
    return [f'{x["photos"]}', f'{x["triangulate_oriented"]}', f'{x["replay_oriented"]}/{x["replay_keyframes"]}',
            '—' if share is None else f'**{x["replay_oriented_of_triangulated"]}/{x["keyframes_triangulated"]} '
            f'({share * 100:.0f} %)**' + ('' if x.get('share_exact', True) else ' (lower bound)')
            + _mapping_failed(x)]


def _chain(label, survey, variant):
    return Figure((label, 'every photo' if variant == 'all' else 'every other photo'), REAL,
                  {'survey': survey if variant == 'all' else f'{survey}_half', 'pipeline': 'replay',
                   'replay_oriented': lambda v: v is not None}, _chain_cells, PRODUCT, REAL_CMD,
                  ignore=AFTER_ORIENTATION)


# The video's frames as geotagged photos through triangulate and its bag through replay: bench/inflight_chain.py.
CHAIN = 'inflight_chain_[0-9a-f]*.jsonl'
CHAIN_CMD = 'ROS_DOMAIN_ID=N .venv/bin/python bench/inflight_chain.py --only phantom3 --out WORK'


def _chain_video_cells(x: dict, _lines) -> list:
    share = x.get('share')
    return [f'{x["photos"]}', f'{x["triangulate_oriented"]}', f'{x["replay_oriented"]}/{x["replay_keyframes"]}',
            '—' if share is None else f'**{x["replay_oriented_of_triangulated"]}/{x["keyframes_triangulated"]} '
            f'({share * 100:.0f} %)**' + ('' if x.get('share_exact', True) else ' (lower bound)')]


def _chain_video(variant):
    return Figure(('phantom3_village (100 video frames)', 'every frame' if variant == 'all' else 'every other frame'),
                  CHAIN, {'set': 'phantom3', 'variant': variant}, _chain_video_cells, PRODUCT, CHAIN_CMD)


BUDGET = 'stage_budget*.jsonl'
BUDGET_CMD = '.venv/bin/python bench/stage_budget.py --out F'
BUDGET_ROWS = (('tracking (KLT, detection; 1/8 decode)', 'tracking', 'photo'),
               ('descriptor matching', 'descriptor_matching', 'photo'),
               ('pose (resection)', 'pose_resection', 'photo'),
               ('window adjustment', 'window_adjustment', 'photo'),
               ('keyframe image decode, full size', 'decode_full_keyframe', 'call'),
               ('keyframe image decode at the map cell (1/4)', 'decode_keyframe_reduced', 'call'),
               ('targets (ArUco) as the node searches them', 'targets_as_node', 'call'),
               ('stereo pair, reduced keyframe images', 'stereo_pair_reduced_images', 'call'),
               ('fusion', 'fusion', 'call'),
               ('ortho tiles', 'tiles', 'call'),
               ('keyframe image message, full 20 MP raw', 'message_image_full_raw', 'call'),
               ('keyframe image message, reduced', 'message_image_reduced_raw', 'call'))


def _budget_cells(x: dict, lines: list) -> list:
    per = x['cpu_s_per_photo'] if x.get('cpu_s_per_photo') is not None else x.get('cpu_s_per_call')
    stage = x['stage']
    # The floor is measured once per stage family ('decode', 'stereo_pair', 'messages', ...): the longest whose
    # name starts this stage's.
    floors = sorted(((y['stage'], y['floor_cpu_s_per_call']) for y in lines if y.get('floor_cpu_s_per_call') is not None
                     and stage.startswith(y['stage'].rstrip('s'))), key=lambda t: -len(t[0]))
    floor = floors[0][1] if floors else None
    return [f'{per:.3f} s a photo ({x["cpu_s_per_call"]:.3f} s a call, {x["calls"]} calls)' if per is not None else '—',
            '—' if floor is None else f'{floor:.4f} s a call']


# What each stage's figure measures: the code bench/stage_budget.py calls for it (a component's figure goes stale
# with its component, not with the rest of the product).
_CORE = 'photogram_ros/core/'
BUDGET_MODULES = {
    'tracking': (_CORE + 'tracker.py', _CORE + 'klt.py', _CORE + 'keyframes.py', _CORE + 'keyframe_image.py'),
    'descriptor_matching': (_CORE + 'photo_matching.py',),
    'pose_resection': ('photogram_ros/core', 'photogram_ros/stages/adjustment.py'),
    'window_adjustment': ('photogram_ros/core', 'photogram_ros/stages/adjustment.py'),
    'decode_full_keyframe': (_CORE + 'keyframe_image.py',),
    'decode_keyframe_reduced': (_CORE + 'keyframe_image.py', _CORE + 'gsd.py'),
    'targets_as_node': (_CORE + 'control.py', _CORE + 'evaluation.py', _CORE + 'keyframe_image.py'),
    'stereo_pair_reduced_images': (_CORE + 'stereo.py', _CORE + 'gsd.py', _CORE + 'keyframe_image.py'),
    'fusion': (_CORE + 'fusion.py', 'photogram_ros/stages/map.py'),
    'tiles': (_CORE + 'ortho_tiles.py', 'photogram_ros/stages/map.py'),
    'message_image_full_raw': ('photogram_ros/msgs.py',),
    'message_image_reduced_raw': ('photogram_ros/msgs.py', _CORE + 'keyframe_image.py'),
}


def _budget(label, stage, _per):
    return Figure((label,), BUDGET, {'stage': stage}, _budget_cells, BUDGET_MODULES[stage], BUDGET_CMD)


SIM_20MP = 'inflight_20mp_[0-9a-f]*.jsonl'
SIM_20MP_CMD = ('ROS_DOMAIN_ID=N .venv/bin/python bench/inflight_20mp.py --flight sim --photos 317 --periods 1,0.7 '
                '--export-dsm --set ... (config/companion.yaml pace keys) --out F (bench/run_all.py --only inflight_20mp)')


def _sim_cells(x: dict, _lines) -> list:
    pose, last, cloud = x['lag_exposure_to_pose_s'], x['lag_exposure_to_pose_last_minute_s'], \
        x['lag_exposure_to_fused_cloud_s']
    rss = (x.get('peak_rss_mb') or 0) + (x.get('child_peak_rss_mb') or 0)
    return [f'{x["oriented"]}/{x["keyframes"]} keyframes oriented, {x["dropped_otherwise"]} dropped; pose lag p50/p95 '
            f'{pose["p50"]:.1f}/{pose["p95"]:.1f} s (last minute {last["p50"]:.1f}/{last["p95"]:.1f} s); first pose '
            f'{x["first_pose_after_first_photo_s"]:.0f} s after the first photo; fused cloud p95 {cloud["p95"]:.0f} s; '
            f'peak RSS {x.get("peak_rss_mb", 0):.0f} + {x.get("child_peak_rss_mb", 0):.0f} = {rss:.0f} MB; shed: '
            f'{x["shed"]["stereo_keyframes_shed"]} keyframes\' pairs, {x["shed"]["ortho_batches_deferred"]} ortho '
            f'batches; load {x.get("load_avg_before", ["?"])[0]}']


def _sim_20mp(period='1s'):
    return Figure((f'the simulated survey: 317 photos at 20 MP, one every {period.rstrip("s")} s, through the graph',),
                  SIM_20MP, {'bench': 'inflight_20mp', 'flight': 'sim', 'config': period}, _sim_cells, PRODUCT,
                  SIM_20MP_CMD)


def _shed_cells(x: dict, _lines) -> list:
    said = x.get('shed', {}).get('said_on_diagnostics') or []
    return [f'`export --densify` of the {x["config"]} flight\'s stored map against the {x["reference"]} flight\'s: DSM '
            f'median |dz| {x["median_abs_dz_gsd"]:.2f} GSD ({cm(x["median_abs_dz_m"])}; p90 {cm(x["p90_abs_dz_m"])}) '
            f'over {x["cells_compared"]:,} cells; shed in flight: {x["shed"]["stereo_keyframes_shed"]} keyframes\' '
            f'pairs, {x["shed"]["ortho_batches_deferred"]} ortho batches, said on /diagnostics: '
            + ('; '.join(f'"{s}"' for s in said) if said else 'nothing (nothing shed)')]


SHED_DSM = Figure(('the same at 0.7 s: what was shed, made up after landing',), SIM_20MP,
                  {'bench': 'inflight_20mp_dsm', 'config': '0.7s'}, _shed_cells, PRODUCT, SIM_20MP_CMD)


# --- figures of the benches converted to the ResultWriter (bench/run_all.py runs each) ----------------------


def _g(x: dict, path: str):
    """x's value at a dotted path, else None."""
    for part in path.split('.'):
        x = x.get(part) if isinstance(x, dict) else None
    return x


SAMPLE = 'sample_flight*.jsonl'
SAMPLE_CMD = 'ROS_DOMAIN_ID=N .venv/bin/python bench/sample_flight.py --out F'


def _check_points(x: dict, key: str = 'check_points') -> str:
    r = _g(x, f'{key}.rmse') or {}
    return (f'{cm(r.get("horizontal_m"))} H / {cm(r.get("z_m"))} V RMSE over {r.get("count")} targets'
            if r.get('count') else 'none measured')


def _sample_cells(x: dict, _lines) -> list:
    tr = x.get('trajectory_vs_truth') or {}
    return [f'check points {_check_points(x)}; keyframes {x.get("keyframes_oriented")}/{x.get("keyframes_taken")} '
            f'oriented; keyframe camera centres {cm(tr.get("rmse_horizontal_m"))} H / {cm(tr.get("rmse_vertical_m"))} '
            f'V RMSE from the truth (max {cm(tr.get("max_m"))}, {tr.get("count")} keyframes)']


def _surface(e: dict | None) -> str:
    e = e or {}
    return (f'median |dz| {cm(e.get("median_abs_m"))} ({f(e.get("median_abs_gsd"), ".1f")} GSD), p90 '
            f'{cm(e.get("p90_abs_m"))}' if e.get('count') else 'n/a')


def _sample_dsm_cells(x: dict, _lines) -> list:
    ov = x.get('overlap') or {}
    return [f'DSM against the true DEM {_surface(x.get("dsm_vs_truth"))}; its cells measured by stereo '
            f'{_surface(x.get("dsm_vs_truth_measured"))}; away from walls {_surface(x.get("dsm_vs_truth_away_from_walls"))}; '
            f'DTM away from buildings {_surface(x.get("dtm_vs_truth_away_from_buildings"))}; DSM over '
            f'{pct(x.get("dsm_completeness"))} of the flown area ({pct(x.get("dsm_measured_completeness"))} measured); '
            f'photos a DSM cell: median {f(ov.get("median_photos"), ".0f")}']


def _sample_gcp_cells(x: dict, _lines) -> list:
    return [f'check points {_check_points(x)}; GCP residuals (the fit) {_check_points(x, "gcp_residuals")}; '
            f'keyframes {x.get("keyframes_oriented")}/{x.get("keyframes_taken")} oriented']


def _sample_speed_cells(x: dict, _lines) -> list:
    r = x.get('replay') or {}
    return [f'{r.get("frames")} frames ({f(r.get("bag_s"), ".0f")} s of flight) in {f(r.get("wall_s"), ".0f")} s: '
            f'real-time factor {f(r.get("real_time_factor"))} (load average {x.get("load_avg", ["?"])[0]})']


SAMPLE_RTK = Figure(('sample flight end to end (RTK, no GCPs): check points, keyframes oriented, camera centres',),
                    SAMPLE, {'run': 'rtk', 'exit': 0}, _sample_cells, PRODUCT, SAMPLE_CMD)
SAMPLE_DSM = Figure(('dense cloud, DSM and DTM of the sample flight against the true DEM; overlap',), SAMPLE,
                    {'run': 'rtk', 'exit': 0}, _sample_dsm_cells, PRODUCT, SAMPLE_CMD)
SAMPLE_GCP = Figure(('sample flight with its targets file (RTK + 5 GCPs)',), SAMPLE, {'run': 'gcp', 'exit': 0},
                    _sample_gcp_cells, PRODUCT, SAMPLE_CMD)
SAMPLE_SPEED = Figure(('replay of the sample bag',), SAMPLE, {'run': 'rtk', 'exit': 0}, _sample_speed_cells, PRODUCT,
                      SAMPLE_CMD)

HELD_OUT = 'held_out_proxies*.jsonl'
HELD_OUT_CMD = 'ROS_DOMAIN_ID=N .venv/bin/python bench/held_out_proxies.py --out OUT'
HELD_OUT_KINDS = ('alt_walk', 'alt_walk_h', 'missing_third', 'optimistic')


def _held_out_proxy_cells(x: dict, lines: list) -> list:
    out = []
    for y in lines:
        if y.get('kind') in HELD_OUT_KINDS and y.get('pipeline') == 'triangulate':
            out.append(f'{y["set"]} {y["kind"]}: {y.get("oriented")}/{y.get("photos")}, shape '
                       f'{f(y.get("shape_rms_3d_m"))} m RMS 3D from the unperturbed block, '
                       f'{f(y.get("true_rigid_h_m"))} m H from the true positions (the geotags allow '
                       f'{f(y.get("allowed_h_m"))} m), {str(y.get("verdict") or "n/a").upper()}')
    return ['; '.join(out)]


HELD_OUT_PROXIES = Figure(('toledo and brighton with consumer-camera geotags made from their own (heights wandering '
                           '~100 m, a wandering 15 m bias, a third missing, stated sigmas too small) through '
                           '`triangulate`',), HELD_OUT,
                          {'kind': lambda v: v in HELD_OUT_KINDS, 'pipeline': 'triangulate'}, _held_out_proxy_cells,
                          PRODUCT, HELD_OUT_CMD)


def _held_out_readme(x: dict, lines: list) -> str:
    rows = [y for y in lines if y.get('kind') in HELD_OUT_KINDS and y.get('pipeline') == 'triangulate']
    failed = sum(str(y.get('verdict') or '').lower() == 'failed' for y in rows)
    oriented = sum((y.get('oriented') or 0) == y.get('photos') for y in rows)
    replays = [f'`replay` {y["set"]} {y["kind"]}: {y.get("oriented")}/{y.get("photos")}'
               + (f' (exit {y["exit"]})' if y.get('exit') else '')
               for y in lines if y.get('kind') in HELD_OUT_KINDS and y.get('pipeline') == 'replay']
    return (f'{oriented} of {len(rows)} proxy blocks fully oriented, {failed} FAILED'
            + ''.join(f'; {r}' for r in replays))


PHOTO_TRI = 'photo_triangulation_[0-9a-f]*.jsonl'


def _photo_tri_cells(x: dict, lines: list) -> list:
    out = []
    for y in lines:
        if y.get('ours'):
            o, b = y['ours'], y.get('baseline') or {}
            out.append(f'{Path(str(y.get("data"))).name}: {o.get("photos")} photos, {o.get("oriented")} oriented, '
                       f'matching {f(o.get("matching_photos_per_s"))} photos/s against {f(b.get("photos_per_s"))} for '
                       f'a bare OpenCV SIFT + ratio + RANSAC loop ({f(y.get("matching_speed_ratio"))}x), whole '
                       f'`triangulate` {f(o.get("triangulate_photos_per_s"))} photos/s')
    return ['; '.join(out)]


PHOTO_TRI_FIG = Figure(('photo-survey speed (`triangulate PHOTOS`) against a bare OpenCV baseline',), PHOTO_TRI,
                       {'ours': lambda v: v is not None}, _photo_tri_cells, PRODUCT,
                       '.venv/bin/python bench/photo_triangulation.py --out F')
DASK = Figure(('Dask matching (`--workers 2` against `--workers 1`)',), 'photo_triangulation_*.jsonl',
              {'compare': 'workers 2 / workers 1', 'matching_speedup': lambda v: v is not None},
              lambda x, lines: [_dask_matching_cell(x, lines)],
              PRODUCT, '.venv/bin/python bench/photo_triangulation_scale.py --photos 100 --matching-only --counts 1 2 '
              '--out F')


def _target_cells(x: dict, lines: list) -> list:
    out = [f'{y["set"]} ({y["image"]}): {y["new_ms_median"]:.1f} ms a frame (median) against '
           f'{y["baseline_ms_median"]:.1f} ms for the whole-image full-resolution search ({y["ratio_median"]:.1f}x), '
           f'{y["detections_new"]} / {y["detections_baseline"]} detections'
           for y in lines if y.get('new_ms_median') is not None]
    tk = next((y for y in lines if y.get('set') == 'tracker_keyframes'), None)
    if tk:
        out.append(f'on the tracker\'s keyframes {tk["detection_ms_median"]:.1f} ms a keyframe, '
                   f'{100 * tk["overhead_vs_tracker"]:.0f} % of the tracker\'s own time')
    return ['; '.join(out)]


TARGETS = Figure(('target detection',), 'target_detection*.jsonl', {'set': 'sample_bag'}, _target_cells,
                 ('photogram_ros/core/evaluation.py', 'photogram_ros/core/control.py'),
                 '.venv/bin/python bench/target_detection.py --out F')


def _ground_stream_cells(x: dict, _lines) -> list:
    return [f'{x["ortho_tiles"]} ortho tiles of {x["ortho_mean_tile_kb"]:.0f} kB: {x["ortho_mb_per_flight_min"]:.2f} MB '
            f'a flight minute against {x["baseline_cloud_mb_per_flight_min"]:.2f} MB for the downsampled cloud '
            f'({x["ratio_ortho_to_cloud"]:.2f}x; the sample flight at rate {x["rate"]})']


GROUND_STREAM = Figure(('tile stream and the cost in map_node',), 'ground_stream*.jsonl',
                       {'ortho_tiles': lambda v: v is not None}, _ground_stream_cells, PRODUCT,
                       'ROS_DOMAIN_ID=N .venv/bin/python bench/ground_stream.py --out F')


def _tracker_cells(x: dict, lines: list) -> list:
    return ['; '.join(f'{y["size"]}: {y["tracker_fps"]:.0f} fps against {y["baseline_fps"]:.0f} fps for a bare '
                      f'goodFeaturesToTrack + pyramidal KLT loop ({y["time_ratio_tracker_over_baseline"]:.2f}x its time; '
                      f'{y["frames"]} frames, one core), {y["keyframes"]} keyframes'
                      for y in lines if y.get('tracker_fps') is not None)]


TRACKER = Figure(('tracker: frame rate',), 'tracker_fps*.jsonl', {'tracker_fps': lambda v: v is not None},
                 _tracker_cells, ('photogram_ros/core/tracker.py', 'photogram_ros/core/klt.py',
                                  'photogram_ros/core/keyframes.py', 'photogram_ros/core/photo_matching.py'),
                 '.venv/bin/python bench/tracker_fps.py --out F')


def _stereo_speed_cells(x: dict, lines: list) -> list:
    return ['; '.join(f'{y["image"]}: the module {y["full_ms"]:.0f} ms a pair against {y["bare_padded_sgbm_ms"]:.0f} ms '
                      f'for SGBM alone on the same padded pair ({y["overhead_ratio"]:.2f}x wall, '
                      f'{y["overhead_ratio_cpu"]:.2f}x CPU)' for y in lines if y.get('kind') == 'stereo_speed')]


STEREO_SPEED = Figure(('stereo speed: the module against a bare SGBM compute',), 'stereo_speed*.jsonl',
                      {'kind': 'stereo_speed'}, _stereo_speed_cells,
                      ('photogram_ros/core/stereo.py', 'photogram_ros/core/gsd.py'),
                      '.venv/bin/python bench/stereo_speed.py --out F')


def _fusion_cells(x: dict, lines: list) -> list:
    by = {y.get('method'): y for y in lines}
    fu, st, base = by.get('fusion', {}), by.get('fusion+store', {}), by.get('baseline', {})
    return [f'{f(fu.get("points_per_s", 0) / 1e6, ".1f")} M points/s ({f(st.get("points_per_s", 0) / 1e6, ".1f")} M with '
            f'the tile store) against {f(base.get("points_per_s", 0) / 1e6, ".1f")} M for a bare numpy binning of the '
            f'same points ({f(fu.get("ratio_to_baseline"))}x its rate; {fu.get("points")} points, best of '
            f'{fu.get("repeats")})']


FUSION = Figure(('map fusion',), 'fusion_throughput*.jsonl', {'method': 'fusion'}, _fusion_cells,
                ('photogram_ros/core/fusion.py', 'photogram_ros/io/map_store.py'),
                '.venv/bin/python bench/fusion_throughput.py --out F')
WINDOW = Figure(('sliding-window update',), 'window_latency*.jsonl', {'kind': 'summary'},
                lambda x, _: [f'median {x["median_ms"]:.0f} ms, p95 {x["p95_ms"]:.0f} ms an update over '
                              f'{x["keyframes"]} keyframes (window {x["window"]}; last 100 over the first '
                              f'{x["flatness_last_over_first_block"]:.2f}x); one full adjustment of the block '
                              f'{x["baseline_full_adjustment_s"]:.1f} s = {x["ratio_full_over_window_median"]:.0f} '
                              'window updates (same run)'],
                ('photogram_ros/core/incremental.py', 'photogram_ros/core/window.py', 'photogram_ros/core/bundle',
                 'photogram_ros/core/resection.py', 'photogram_ros/core/triangulation.py'),
                '.venv/bin/python bench/window_latency.py --out F')
PLAYER = Figure(('bag player',), 'replay_throughput*.jsonl', {'msgs_per_s': lambda v: v is not None},
                lambda x, _: [f'{x["msgs_per_s"]} messages/s ({x["MB_per_s"]} MB/s, {x["real_time_factor"]}x real '
                              f'time) to another process, {x["received_by_other_process"]}/{x["messages"]} received; '
                              f'reading the bag alone {x["baseline_read_msgs_per_s"]} messages/s '
                              f'({x["ratio_to_baseline"]}x the time)'],
                ('photogram_ros/io/bag.py', 'photogram_ros/io/bag_storage.py', 'photogram_ros/nodes/player_node.py'),
                'ROS_DOMAIN_ID=N .venv/bin/python bench/replay_throughput.py --out F')


def _e2e_cells(x: dict, lines: list) -> list:
    runs = [y for y in lines if y.get('kind') == 'e2e_realtime']
    return ['; '.join(f'config {y["config"]}: {y["frames"]} frames ({y["bag_s"]:.0f} s of flight) in {y["wall_s"]:.0f} s, '
                      f'real-time factor {y["real_time_factor"]:.2f} (target {y.get("target_real_time_factor")}), '
                      f'{y["keyframes"]} keyframes' for y in runs)]


E2E = Figure(('real time (a 5 fps, 640×480 survey through `replay`)',), 'e2e_realtime*.jsonl', {'kind': 'e2e_realtime'},
             _e2e_cells, PRODUCT, 'ROS_DOMAIN_ID=N .venv/bin/python bench/e2e_realtime.py --out F')


TABLES: dict[str, Table] = {
    'simulated': Table(('what', 'figure'), (
        SAMPLE_RTK, SAMPLE_DSM, SAMPLE_GCP,
        Figure(('control adjustment in flight: the sample flight as keyframes through the adjustment stage',),
               'control_adjustment_cost*.jsonl', {'preset': 'sample'}, _control_cells, CONTROL_MODULES,
               '.venv/bin/python bench/control_adjustment_cost.py'),
        Figure(('control adjustment in flight: the survey preset',), 'control_adjustment_cost*.jsonl', {'preset': 'survey'},
               _control_cells, CONTROL_MODULES, '.venv/bin/python bench/control_adjustment_cost.py'),
        PPK_POSITIONS,
        _ppk('PPK photo survey: `triangulate` on the PPK geotags with the photos\' EXIF camera', 'triangulate_ppk_exif_camera'),
        _ppk('... with the camera\'s calibration (`--camera camera.yaml`)', 'triangulate_ppk_calibrated'),
        _ppk('... the same photos on their EXIF GPS alone', 'triangulate_exif_gps'))),
    'real-surveys': Table(
        ('survey', 'pipeline', 'oriented', 'cameras − GNSS after a robust similarity, H / V', 'rigid H / V',
         'within 15° of nadir', 'reprojection', 'peer'), tuple(_survey(*r) for r in REAL_ROWS)),
    'real-agreement': Table(
        ('survey', 'photos in both', '`replay`\'s cameras against `triangulate`\'s'),
        (_agreement('brighton_beach', 'brighton'), _agreement('toledo', 'toledo'), _agreement('seneca_part', 'seneca'))),
    # brighton's and toledo's `triangulate` verdicts, and their variants', come from bench/block_verdicts.py (its
    # runs keep the block check's inputs, so its rows are re-judged on the block check of the code now).
    'real-verdicts': Table(('survey', 'pipeline', 'verdict'),
                           tuple(_verdict(*r) for r in REAL_ROWS[:7] if not (r[1] in ('brighton', 'toledo')
                                                                              and r[2] == 'triangulate'))
                           + tuple(_block_verdict(*r) for r in BLOCK_VERDICT_ROWS)
                           + (_broken('brighton_beach, tipped or folded', 'brighton'),
                              _broken('toledo, tipped or folded', 'toledo'))),
    'held-out': Table(('what', 'figure'), (
        Figure(('brighton_beach with its EXIF heights wandering 100 m peak to peak (held_out_proxies alt_walk) through '
                '`triangulate`',), BLOCK_VERDICTS, {'set': 'brighton', 'variant': 'heights', 'kind': 'triangulate'},
               _held_out_cells, PRODUCT, BLOCK_VERDICTS_CMD),
        Figure(('toledo with its EXIF heights wandering 100 m and a wandering 15 m horizontal bias (held_out_proxies '
                'alt_walk_h) through `triangulate`',), BLOCK_VERDICTS,
               {'set': 'toledo', 'variant': 'heights', 'kind': 'triangulate'}, _held_out_cells, PRODUCT,
               BLOCK_VERDICTS_CMD),
        HELD_OUT_PROXIES)),
    'real-more': Table(('what', 'figure'), (
        PHOTO_TRI_FIG, DASK,
        Figure(('104 simulated photos, one block',), 'split_merge_paths*.jsonl', {'run.split_photos': 0}, _split_cells,
               PRODUCT, '.venv/bin/python bench/split_merge_paths.py --photos 100 --split-photos 60'),
        Figure(('104 simulated photos, split-merge in 2 sub-blocks',), 'split_merge_paths*.jsonl', {'run.split_photos': 60},
               _split_cells, PRODUCT, '.venv/bin/python bench/split_merge_paths.py --photos 100 --split-photos 60'),
        Figure(('635 simulated photos, split-merge (2 sub-blocks), 1 worker',), SCALE,
               {'run.mode': 'split', 'run.workers': 1, 'run.oriented': lambda v: v is not None and v > 600}, _scale_cells,
               PRODUCT, SCALE_CMD),
        SCALE_W2,
        Figure(('635 simulated photos, one block',), SCALE,
               {'run.mode': 'single', 'run.oriented': lambda v: v is not None and v > 600}, _scale_cells, PRODUCT,
               SCALE_CMD.replace('--modes split', '--modes single')))),
    'control': Table(('what', 'figure'), (TARGETS,)),
    'ground': Table(('what', 'figure'), (GROUND, GROUND_STREAM)),
    # BAL against Ceres needs pycolmap (bench/requirements-peers.txt), which the project's virtualenv does not hold:
    # its row comes back when a result file holds a Ceres line (bench/bundle_bal.py --peers with pycolmap installed).
    'components': Table(('what', 'figure'), (
        (BAL_SCIPY,) + ((BAL_CERES,) if newest(BAL_CERES) else ()) + (
            _stereo('tsukuba'), _stereo('venus'), _stereo('cones'), _stereo('teddy'), TRACKER, STEREO_SPEED, MAVLINK,
            FUSION))),
    'inflight-chain': Table(('survey', 'photos used', 'photos', '`triangulate` oriented', '`replay` keyframes oriented',
                             '`replay` oriented among the keyframes whose photo `triangulate` oriented'),
                            tuple(_chain(label, sv, v) for label, sv in CHAIN_SETS for v in ('all', 'half'))
                            + (_chain_video('all'), _chain_video('half'))),
    'stage-budget': Table(('stage (20 MP, toledo upscaled)', 'CPU', 'floor (the least the stage can cost)'),
                          tuple(_budget(*r) for r in BUDGET_ROWS)),
    'inflight-20mp': Table(('what', 'figure'), (_sim_20mp(), _sim_20mp('0.7s'), SHED_DSM)),
    'speed': Table(('what', 'figure'), (
        SAMPLE_SPEED, WINDOW, PLAYER, E2E,
        Figure(('20 MP photos in flight',), SIM_20MP, {'bench': 'inflight_20mp', 'flight': 'sim', 'config': '1s'},
               _sim_cells, PRODUCT, SIM_20MP_CMD))),
    'readme-headline': Table(('what', 'figure', 'more'), (
        _readme('real fixed-wing survey in flight (seneca_part, 41 near-infrared photos, `replay`)',
                _chain('seneca_part', 'seneca', 'all'),
                lambda x, _: f'**{x["replay_oriented_of_triangulated"]}/{x["keyframes_triangulated"]} of the keyframes '
                f'whose photos `triangulate` orients** ({x["replay_oriented"]}/{x["replay_keyframes"]} keyframes)'
                + _mapping_failed(x),
                '[real surveys](docs/measurements.md#real-surveys)'),
        _readme('the same, every other photo (half the forward overlap)', _chain('seneca_part', 'seneca', 'half'),
                lambda x, _: f'{x["replay_oriented_of_triangulated"]}/{x["keyframes_triangulated"]} of `triangulate`\'s '
                f'({x["replay_oriented"]}/{x["replay_keyframes"]} keyframes)' + _mapping_failed(x), 'same'),
        _readme('real DJI survey offline (brighton_beach, 18 photos, no calibration, no GCPs)', BRIGHTON_TRI,
                lambda x, _: f'**{x["oriented"]}/{x["given"]} oriented**, reprojection {x["reprojection_px"]:.2f} px, '
                f'cameras {x["sim_h_m"]:.2f} m H / {x["sim_v_m"]:.2f} m V from their own GPS after a similarity',
                '[real surveys](docs/measurements.md#real-surveys)'),
        _readme('the same photos in flight (`replay`)', BRIGHTON_REP,
                lambda x, _: f'**{x["oriented"]}/{x["given"]} keyframes oriented**; DSM '
                f'{pct(x.get("dsm_footprint_measured_share", x["dsm_measured_hull_share"]))} of the camera centres\' '
                'hull measured by stereo, '
                f'**{cm(x["peer_in_hull"]["median_abs_dz_m"])}** median from OpenDroneMap\'s cloud inside that hull',
                'same'),
        _readme('real DJI survey (toledo, 42 photos, EXIF only)', TOLEDO_TRI,
                lambda x, _: f'**{x["oriented"]}/{x["given"]} oriented, cameras {x["sim_h_m"]:.2f} m H from their own '
                f'GPS**, {pct(x["nadir_share"])} within 15° of nadir', 'same'),
        _readme('toledo in flight against offline', TOLEDO_AGREE,
                lambda x, _: f'`replay`\'s cameras {x["rms_3d_m"]:.2f} m RMS from `triangulate`\'s over {x["n"]} photos',
                'same'),
        _readme('real fixed-wing survey (seneca_part, 41 near-infrared photos)', SENECA_TRI,
                lambda x, _: f'**{x["oriented"]}/{x["given"]} oriented**, cameras {x["sim_h_m"]:.2f} m H from their GPS',
                'same'),
        _readme('real drone video (phantom3_village, 1080p, 100 frames)', PHANTOM3,
                lambda x, _: f'**{x["oriented"]}/{x["given"]} keyframes oriented**, cameras {x["sim_h_m"]:.2f} m H '
                'after a similarity to the published trajectory', 'same'),
        _readme('bundle adjustment (BAL problem-49)', BAL_SCIPY,
                lambda x, _: f'**{x["time_ratio_peer_over_ours"]:.1f}x faster than SciPy\'s least_squares**, final cost '
                f'{x["cost_ratio_ours_over_peer"]:.3f}x', '[components](docs/measurements.md#components)'),
        _readme('stereo on Middlebury venus', _stereo('venus'), lambda x, lines: stereo_cells(x, lines)[0], 'same'),
        _readme('635 simulated photos, split-merge on 2 workers', SCALE_W2, lambda x, lines: _scale_cells(x, lines)[0],
                '[real surveys](docs/measurements.md#real-surveys)'),
        _readme('sample flight end to end (RTK, no GCPs); its DSM', SAMPLE_RTK,
                lambda x, lines: f'{_sample_cells(x, lines)[0]}; DSM {_surface(x.get("dsm_vs_truth"))} from the true DEM',
                '[simulated](docs/measurements.md#accuracy-on-simulated-flights)'),
        _readme('PPK photo survey (`geotag`, no GCPs)', _ppk('', 'triangulate_ppk_calibrated'),
                lambda x, _: f'check points **{cm(x["check_h_m"])} / {cm(x["check_v_m"])}** with the camera\'s '
                'calibration', 'same'),
        _readme('consumer geotags that wander (held-out proxies)', HELD_OUT_PROXIES, _held_out_readme,
                '[real surveys](docs/measurements.md#real-surveys)'),
        _readme('ground station (the sample flight at real speed)', GROUND,
                lambda x, lines: _ground_cells(x, lines)[0], '[ground station](docs/measurements.md#survey-quality-at-the-ground-station)'),
        _readme('real time', E2E, lambda x, lines: _e2e_cells(x, lines)[0],
                '[speed](docs/measurements.md#speed-real-time-and-memory)'))),
}


# --- documents -------------------------------------------------------------------------------------------

MARK = re.compile(r'(<!-- figures:(?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /figures:(?P=name) -->)', re.S)


def render_text(text: str) -> str:
    def sub(m):
        name = m.group('name')
        if name not in TABLES:
            raise KeyError(f'a document names the table "{name}", which bench/render_figures.py does not define')
        return m.group(1) + render_table(TABLES[name]) + '\n' + m.group(4)
    return MARK.sub(sub, text)


def render_all() -> dict[str, tuple[str, str]]:
    """{document: (committed text, rendered text)}."""
    out = {}
    for doc in DOCUMENTS:
        text = (ROOT / doc).read_text()
        out[doc] = (text, render_text(text))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--check', action='store_true', help='do not write: list every figure with its result file and '
                                                         'whether it is stale; exit 1 when a document differs')
    ap.add_argument('--strict', action='store_true', help='with --check: exit 1 also when a figure is stale or has '
                                                          'no result file')
    ap.add_argument('--json', action='store_true', help='with --check: the listing as JSON lines')
    a = ap.parse_args(argv)
    not_fresh = []
    if a.check:
        rows = listing()
        print('\n'.join(json.dumps(r) for r in rows) if a.json else listing_text(rows))
        not_fresh = [r for r in rows if r['state'] in ('stale', NO_FILE)]
    bad = []
    for doc, (old, new) in render_all().items():
        if old != new:
            bad.append(doc)
            if not a.check:
                (ROOT / doc).write_text(new)
    if a.check and bad:
        print(f'rendered tables differ in {", ".join(bad)}: run .venv/bin/python bench/render_figures.py')
        return 1
    if a.check and a.strict and not_fresh:
        print(f'{len(not_fresh)} figures are stale or have no result file')
        return 1
    print(('rewrote ' + ', '.join(bad)) if bad else 'every rendered table is up to date')
    return 0


if __name__ == '__main__':
    sys.exit(main())
