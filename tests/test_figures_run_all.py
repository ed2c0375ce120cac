"""bench/run_all.py reaches every bench the documents name, and runs a named group of them."""

import fnmatch
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import run_all  # noqa: E402
from test_figures_rendered import NOT_IN_RUN_ALL  # noqa: E402

# bench/ files the documents name that are not benches: the render, the result writer, a timing hook, this runner.
NOT_BENCHES = {'render_figures', 'machine', 'replay_probe', 'run_all'}
DOCS = [ROOT / 'README.md', *sorted((ROOT / 'docs').glob('*.md'))]


def _docs_text() -> str:
    return '\n'.join(p.read_text() for p in DOCS)


def test_every_bench_and_result_file_a_document_names_is_reachable_from_run_all():
    text = _docs_text()
    scripts = {b.argv[0] for b in run_all.BENCHES}
    named = set(re.findall(r'bench/([a-z_0-9]+)\.py', text)) - NOT_BENCHES
    assert named, 'the documents name no bench: the pattern is wrong'
    assert not sorted(n for n in named if f'bench/{n}.py' not in scripts), 'a bench the documents name is not in run_all'
    files = set(re.findall(r'bench/results/([a-z_0-9]+_[0-9a-f]{7}\.jsonl)', text))
    assert files
    unreached = sorted(f for f in files if not any(fnmatch.fnmatch(f, g) for g in NOT_IN_RUN_ALL)
                       and not any(fnmatch.fnmatch(f, f'{b.name}_*.jsonl') for b in run_all.BENCHES))
    assert not unreached, f'no bench of run_all writes {unreached}'


def test_a_group_names_benches_of_run_all_and_selects_them_in_order():
    for g, names in run_all.GROUPS.items():
        assert set(names) <= set(run_all.BY_NAME), g
    chosen = [b.name for b in run_all.select('long_short', 'ground_flight')]
    assert chosen == [n for n in run_all.GROUPS['long_short'] if n != 'ground_flight']
    assert [b.name for b in run_all.select('faults,bundle_bal,faults', '')] == ['faults_stop', 'faults_odd_photo', 'faults_strays', 'bundle_bal']
    text = run_all.groups_text({'bundle_bal': 7.5})
    assert 'bundle_bal 8,' in text.splitlines()[1] and text.splitlines()[1].startswith('components')
