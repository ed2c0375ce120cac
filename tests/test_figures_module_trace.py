"""The modules a result records are the ones its bench ran (bench/machine.py with bench/module_trace): traced in the
bench process and every Python process it starts; a figure then goes stale only when one of those files changed
(bench/render_figures.py), and a result whose trace is incomplete (a child killed with -9) keeps the whole
product."""

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from test_figures_rendered import _render

ROOT = Path(__file__).resolve().parents[1]
needs_git = pytest.mark.skipif(shutil.which('git') is None, reason='the staleness reads git')


# A bench in miniature: the trace started as a bench script's import of bench/machine.py starts it, children
# started with and without an explicit environment, one stopped with SIGTERM, then one killed with -9.
BENCH = textwrap.dedent('''
    import os, subprocess, sys, time
    sys.path.insert(0, {root!r})
    from bench import machine
    machine.start_module_trace()
    import photogram_ros.errors
    py, out = sys.executable, sys.argv[1]
    subprocess.run([py, '-c', 'import photogram_ros.package_files; open("config/replay.yaml").read()'],
                   cwd={root!r}, env=dict(os.environ, PYTHONPATH={root!r}), check=True)
    p = subprocess.Popen([py, '-c', 'import photogram_ros.params, time; print(1, flush=True); time.sleep(60)'],
                         cwd={root!r}, stdout=subprocess.PIPE)
    assert p.stdout.readline().strip() == b'1'
    p.terminate()
    p.wait()
    w = machine.ResultWriter(out, 'mini', ['photogram_ros', 'config'])
    w.write({{'step': 'all ended'}})
    p = subprocess.Popen([py, '-c', 'import photogram_ros.core.geodesy, time; print(1, flush=True); time.sleep(60)'],
                         cwd={root!r}, stdout=subprocess.PIPE)
    assert p.stdout.readline().strip() == b'1'
    time.sleep(0.5)
    p.kill()
    p.wait()
    w.write({{'step': 'one killed'}})
''')


@pytest.fixture(scope='module')
def mini_lines(tmp_path_factory):
    d = tmp_path_factory.mktemp('trace')
    (d / 'mini.py').write_text(BENCH.format(root=str(ROOT)))
    env = {k: v for k, v in os.environ.items() if not k.startswith('PHOTOGRAM_MODULE_TRACE')}
    env['PYTHONPATH'] = str(ROOT)
    subprocess.run([sys.executable, str(d / 'mini.py'), str(d / 'mini.jsonl')], env=env, check=True, timeout=120,
                   cwd=d)
    return [json.loads(x) for x in (d / 'mini.jsonl').read_text().splitlines()]


def test_a_result_records_the_files_its_bench_and_its_children_ran(mini_lines):
    line = mini_lines[0]
    assert line['module_trace']['complete'] is True, line['module_trace']
    assert line['module_trace']['processes'] == 3
    mods = set(line['modules'])
    # its own process, a child whose explicit environment dropped the trace, a child stopped with SIGTERM
    assert {'photogram_ros/__init__.py', 'photogram_ros/errors.py', 'photogram_ros/package_files.py',
            'config/replay.yaml', 'photogram_ros/params.py'} <= mods
    assert not any(m.startswith('photogram_ros/core/') or m.startswith('photogram_ros/nodes/') for m in mods)
    assert line['modules_declared'] == ['photogram_ros', 'config']


def test_a_child_killed_with_minus_9_falls_back_to_the_whole_product(mini_lines):
    line = mini_lines[1]
    assert line['module_trace']['complete'] is False
    assert 'killed with -9' in line['module_trace']['why'] and 'photogram_ros.core.geodesy' in line['module_trace']['why']
    assert line['modules'] == ['photogram_ros', 'config']


def _repo(tmp_path):
    def git(*a):
        return subprocess.run(['git', *a], cwd=tmp_path, check=True, capture_output=True, text=True).stdout.strip()
    git('init', '-q')
    git('config', 'user.email', 't@example.com')
    git('config', 'user.name', 't')
    for rel in ('photogram_ros/__init__.py', 'photogram_ros/a.py', 'photogram_ros/b.py', 'config/replay.yaml'):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text('x = 1\n')
    git('add', '-A')
    git('commit', '-q', '-m', 'first')
    return git


def _commit_change(tmp_path, git, rel):
    (tmp_path / rel).write_text((tmp_path / rel).read_text() + 'y = 2\n')
    git('commit', '-q', '-am', f'change {rel}')


@needs_git
def test_a_traced_figure_stays_fresh_after_an_unrelated_change_and_goes_stale_when_a_file_it_ran_changes(
        tmp_path, monkeypatch):
    r = _render()
    git = _repo(tmp_path)
    measured = git('rev-parse', 'HEAD')
    results = tmp_path / 'bench' / 'results'
    results.mkdir(parents=True)
    base = {'k': 1, 'commit': measured, 'clean': True}
    trace = {'complete': True, 'processes': 2, 'running': 0}
    (results / 'traced_x.jsonl').write_text(
        json.dumps({**base, 'modules': ['photogram_ros/__init__.py', 'config/replay.yaml'], 'module_trace': trace})
        + '\n' + json.dumps({**base, 'k': 2, 'modules': ['photogram_ros/__init__.py', 'photogram_ros/a.py'],
                             'module_trace': trace}) + '\n')
    (results / 'declared_x.jsonl').write_text(json.dumps({**base, 'modules': ['photogram_ros', 'config']}) + '\n')
    (results / 'old_x.jsonl').write_text(json.dumps(base) + '\n')      # before ResultWriter named modules
    # a traced line beside one whose trace is incomplete: the file's figures keep the whole product
    (results / 'mixed_x.jsonl').write_text(
        json.dumps({**base, 'modules': ['photogram_ros/__init__.py'], 'module_trace': trace,
                    'modules_declared': ['photogram_ros', 'config']}) + '\n'
        + json.dumps({**base, 'k': 2, 'modules': ['photogram_ros', 'config'], 'module_trace': {'complete': False}})
        + '\n')
    (results / 'killed_x.jsonl').write_text(json.dumps(
        {**base, 'modules': ['photogram_ros', 'config'],
         'module_trace': {'complete': False, 'why': '1 process(es) ended without writing their modules'}}) + '\n')
    monkeypatch.setattr(r, 'ROOT', tmp_path)
    monkeypatch.setattr(r, 'RESULTS', results)
    traced, declared, killed, mixed, old = (r.Figure(('x',), f'{n}_x.jsonl', {'k': 1})
                                            for n in ('traced', 'declared', 'killed', 'mixed', 'old'))

    def state(fig):        # the render caches git's answers for one run; here the repository moves between calls
        r.files_changed.cache_clear()
        r.changed_since.cache_clear()
        return r.figure_state(fig)

    _commit_change(tmp_path, git, 'photogram_ros/b.py')      # a product change the traced bench did not run
    assert state(traced)['state'] == 'fresh'
    assert state(traced)['traced'] == 3
    assert 'stale' not in r.source_cell(r.newest(traced), traced)
    # a Figure naming the whole product (an end-to-end figure) takes the trace; one naming its component, what
    # ran of it
    assert state(r.Figure(('x',), 'traced_x.jsonl', {'k': 1}, modules=r.PRODUCT))['state'] == 'fresh'
    component = r.Figure(('x',), 'traced_x.jsonl', {'k': 1}, modules=('photogram_ros/a.py', 'photogram_ros/b.py'))
    assert state(component)['state'] == 'fresh'       # of its component, a.py ran, b.py did not
    assert r.newest(component).modules == ('photogram_ros/a.py',)
    # without a (complete) trace: the whole product, stale as before
    assert state(declared)['state'] == 'stale'
    assert state(killed)['state'] == 'stale'
    assert state(mixed)['state'] == 'stale'
    assert state(old)['state'] == 'stale' and not r.newest(old).traced
    assert '**stale**: photogram_ros, config changed since' in r.source_cell(r.newest(killed), killed)

    (tmp_path / 'photogram_ros' / 'a.py').write_text('x = 3\n')   # uncommitted change to a file it ran
    assert state(traced)['state'] == 'stale'
    git('checkout', '--', 'photogram_ros/a.py')
    assert state(traced)['state'] == 'fresh'

    _commit_change(tmp_path, git, 'photogram_ros/a.py')
    assert state(component)['state'] == 'stale'
    st = state(traced)
    assert (st['state'], st['changed_files']) == ('stale', ['photogram_ros/a.py'])
    assert '**stale**: a file it ran changed since' in r.source_cell(r.newest(traced), traced)
    assert '1 of the 3 files it ran changed: photogram_ros/a.py' in r.listing_text(
        [{'document': 'd.md', 'table': 't', 'figure': 'x', **st}])


def test_the_trace_runs_a_sitecustomize_it_shadows(tmp_path):
    """bench/module_trace/sitecustomize.py first on PYTHONPATH still runs the next one (as Python would have)."""
    other = tmp_path / 'other'
    other.mkdir()
    (other / 'sitecustomize.py').write_text('import os\nos.environ["OTHER_SITE_RAN"] = "1"\n')
    env = {k: v for k, v in os.environ.items() if not k.startswith('PHOTOGRAM_MODULE_TRACE')}
    env.update(PYTHONPATH=os.pathsep.join([str(ROOT / 'bench' / 'module_trace'), str(other), str(ROOT)]),
               PHOTOGRAM_MODULE_TRACE_DIR=str(tmp_path / 'trace'))
    out = subprocess.run([sys.executable, '-c', 'import os, photogram_ros.errors; print(os.environ.get("OTHER_SITE_RAN"))'],
                         env=env, capture_output=True, text=True, check=True, timeout=60)
    assert out.stdout.strip() == '1', out.stderr
    docs = [json.loads(p.read_text()) for p in (tmp_path / 'trace').glob('*.json')]
    assert len(docs) == 1 and docs[0]['final'] and 'photogram_ros/errors.py' in docs[0]['files']


def test_a_forked_multiprocessing_child_adds_the_modules_it_imported(tmp_path):
    script = tmp_path / 'pool.py'
    script.write_text(textwrap.dedent(f'''
        import json, multiprocessing as mp, sys
        sys.path.insert(0, {str(ROOT)!r})
        from bench import machine
        machine.start_module_trace()

        def work(_):
            import photogram_ros.core.geodesy  # noqa: F401
            return 1

        if __name__ == '__main__':
            with mp.get_context('fork').Pool(2) as p:
                p.map(work, range(4))
            print(json.dumps(machine.executed_modules(['photogram_ros', 'config'])))
    '''))
    env = {k: v for k, v in os.environ.items() if not k.startswith('PHOTOGRAM_MODULE_TRACE')}
    env['PYTHONPATH'] = str(ROOT)
    out = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=120,
                         check=True)
    modules, trace = json.loads(out.stdout.splitlines()[-1])
    assert trace['complete'] and trace['processes'] == 3, trace
    assert 'photogram_ros/core/geodesy.py' in modules
