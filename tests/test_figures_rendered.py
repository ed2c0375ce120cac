"""The figure tables of README.md and docs/measurements.md are what bench/render_figures.py renders from the
result files in bench/results (re-render: `.venv/bin/python bench/render_figures.py`)."""

import importlib.util
import json
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
needs_git = pytest.mark.skipif(shutil.which('git') is None or not (ROOT / '.git').exists(),
                               reason='the render reads the commits of the result files from git')


def _render():
    spec = importlib.util.spec_from_file_location('render_figures', ROOT / 'bench' / 'render_figures.py')
    mod = importlib.util.module_from_spec(spec)
    sys.modules['render_figures'] = mod
    spec.loader.exec_module(mod)
    return mod


@needs_git
def test_committed_docs_equal_the_rendered_tables():
    r = _render()
    differ = [doc for doc, (old, new) in r.render_all().items() if old != new]
    assert not differ, (f'{differ}: the figure tables differ from the result files; run '
                        '.venv/bin/python bench/render_figures.py and commit the documents')


@needs_git
def test_every_table_a_document_names_is_defined_and_every_table_is_used():
    r = _render()
    names = set()
    for doc in r.DOCUMENTS:
        names |= {m.group('name') for m in r.MARK.finditer((ROOT / doc).read_text())}
    assert names == set(r.TABLES)


def test_a_figure_is_taken_from_the_newest_file_and_marked_stale_when_its_modules_changed(tmp_path, monkeypatch):
    r = _render()
    head = r.full_commit('HEAD')
    first = r._git('rev-list', '--max-parents=0', 'HEAD').split()[0]
    old, new = tmp_path / 'x_old.jsonl', tmp_path / 'x_new.jsonl'
    old.write_text(json.dumps({'k': 1, 'v': 1.0, 'commit': first, 'clean': True, 'modules': ['photogram_ros']}) + '\n')
    new.write_text(json.dumps({'k': 1, 'v': 2.0, 'commit': head, 'clean': False, 'modules': ['photogram_ros']}) + '\n')
    monkeypatch.setattr(r, 'RESULTS', tmp_path)
    fig = r.Figure(('x',), 'x_*.jsonl', {'k': 1}, lambda x, _: [f'{x["v"]:.1f}'], ('photogram_ros',))
    src = r.newest(fig)
    assert src.path == new and src.line['v'] == 2.0
    assert 'modified tree' in r.source_cell(src, fig)
    old_only = r.Figure(('x',), 'x_old.jsonl', {'k': 1}, lambda x, _: [f'{x["v"]:.1f}'], ('photogram_ros',))
    assert '**stale**' in r.source_cell(r.newest(old_only), old_only)
    none = r.Figure(('y',), 'x_*.jsonl', {'k': 2}, command='bench/y.py')
    table = r.render_table(r.Table(('what', 'figure'), (fig, none)))
    assert '| x | 2.0 |' in table and '| y | — | no result file (measure: `bench/y.py`) |' in table


def test_the_check_lists_every_figure_with_its_file_and_whether_it_is_stale(tmp_path, monkeypatch):
    r = _render()
    head = r.full_commit('HEAD')
    first = r._git('rev-list', '--max-parents=0', 'HEAD').split()[0]
    (tmp_path / 'x_new.jsonl').write_text(json.dumps({'k': 1, 'commit': head, 'clean': True,
                                                      'modules': ['photogram_ros']}) + '\n')
    (tmp_path / 'y_old.jsonl').write_text(json.dumps({'k': 1, 'commit': first, 'clean': True,
                                                      'modules': ['photogram_ros']}) + '\n')
    monkeypatch.setattr(r, 'RESULTS', tmp_path)
    monkeypatch.setattr(r, 'changed_since', lambda commit, modules: 0 if commit == head else 3)
    fresh = r.figure_state(r.Figure(('x',), 'x_*.jsonl', {'k': 1}))
    stale = r.figure_state(r.Figure(('y',), 'y_*.jsonl', {'k': 1}))
    none = r.figure_state(r.Figure(('z',), 'z_*.jsonl', {'k': 1}, command='bench/z.py'))
    assert (fresh['state'], fresh['file'], fresh['commit']) == ('fresh', 'x_new.jsonl', head[:7])
    assert (stale['state'], stale['changed']) == ('stale', 3)
    assert none['state'] == 'no result file' and none['command'] == 'bench/z.py'
    text = r.listing_text([{'document': 'd.md', 'table': 't', 'figure': 'y', **stale},
                           {'document': 'd.md', 'table': 't', 'figure': 'z', **none}])
    assert 'STALE' in text and 'y_old.jsonl' in text and 'measure: bench/z.py' in text
    assert text.splitlines()[-1] == '2 figures: 1 no result file, 1 stale'


@needs_git
def test_the_listing_covers_every_figure_of_the_documents():
    r = _render()
    rows = r.listing()
    assert len(rows) == sum(len(r.TABLES[t].rows) for t in {x['table'] for x in rows})
    assert {x['state'] for x in rows} <= {'fresh', 'stale', 'modified tree', 'tree state not recorded',
                                          'no result file'}


# Figures bench/run_all.py does not re-measure, and why: they compare two trees (main, then a branch) in one run.
NOT_IN_RUN_ALL = {'inflight_chain_8a9c63c.jsonl': 'the code before the in-flight chain, kept as the comparison',
                  'inflight_20mp_pace_*.jsonl': 'main and a branch in the same run (--periods 1,0.7)'}


def test_every_rendered_figure_is_measured_by_a_bench_of_run_all():
    """Each figure's result files (a glob under bench/results) match the file one of run_all's benches writes
    (bench/results/<name>_<commit7>.jsonl), so one run of run_all can refresh every figure."""
    import fnmatch
    r = _render()
    sys.path.insert(0, str(ROOT))
    from bench.run_all import BENCHES
    made = [f'{b.name}_0123abc.jsonl' for b in BENCHES]
    missing = sorted({fig.results for t in r.TABLES.values() for fig in t.rows
                      if fig.results not in NOT_IN_RUN_ALL and not any(fnmatch.fnmatch(m, fig.results) for m in made)})
    assert not missing, f'no bench of bench/run_all.py writes {missing}'


@needs_git
def test_a_gate_reads_the_line_the_table_renders():
    """tests/figures.newest_figure: the newest result file by its commit, the same line render_figures renders."""
    r = _render()
    sys.path.insert(0, str(ROOT / 'tests'))
    from figures import newest_figure
    for fig in (r.MAVLINK, r.BRIGHTON_TRI, r.TOLEDO_AGREE):
        src = r.newest(fig)
        name, line = newest_figure(fig.results, **fig.where)
        assert (name, line) == (src.path.name, src.line)
    with pytest.raises(LookupError):
        newest_figure('real_surveys*.jsonl', survey='no such survey')
