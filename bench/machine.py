"""The machine's figures, and the one writer of benchmark result files.

Every bench writes its results through `ResultWriter`: JSON lines, each carrying the exact commit the
code was at (`commit`, 40 hex digits), whether the working tree had uncommitted changes to the code a bench
runs (`clean`: the product, bench/machine.py and the bench's own script), the machine's cores and load average when
the line was written, the UTC time, and the modules (paths in the repository) the figure measures.
bench/render_figures.py renders the docs' tables from these files and marks a figure stale when one of its modules
changed after `commit`.

The modules are measured, not declared: importing this file from a bench script (bench/*.py run as the main
program) traces the photogram_ros files the bench process and every Python process it starts load or open
(bench/module_trace: a sitecustomize.py on the children's PYTHONPATH), and each line's `modules` are those files
(`module_trace.complete` true). When the trace is not complete (a process ended without writing its list, e.g.
killed with -9; children started before the trace; the package loaded from another checkout) the line keeps the
declared `modules` (most benches: the whole product) and `module_trace.why` says why.

    with ResultWriter('bench/results/stereo_middlebury.jsonl', 'stereo_middlebury',
                      modules=['photogram_ros/core/stereo.py']) as w:
        w.write({'scene': 'venus', 'bad2': 0.003})
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TRACE_SITE = ROOT / 'bench' / 'module_trace'
if str(TRACE_SITE) not in sys.path:
    sys.path.append(str(TRACE_SITE))
import photogram_module_trace as module_trace  # noqa: E402

WHOLE_PRODUCT = ('photogram_ros', 'config')     # a declared module list naming the whole product


def machine_info() -> dict:
    cpu = platform.processor() or ''
    try:
        with open('/proc/cpuinfo') as f:
            for line in f:
                if line.startswith('model name'):
                    cpu = line.split(':', 1)[1].strip()
                    break
    except OSError:
        pass
    import cv2
    import numpy
    return {'cpu': cpu, 'cores': os.cpu_count(), 'python': platform.python_version(), 'numpy': numpy.__version__,
            'opencv': cv2.__version__}


def _git(*args: str) -> str:
    return subprocess.run(['git', *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()


# The code a bench runs: the product, this file and the bench's own script (`__main__`); an uncommitted change
# there makes its lines not clean (tests, docs and the other benches do not run).
PRODUCT_CODE = ('photogram_ros', 'config', 'scripts', 'setup.py', 'bench/machine.py')


def _code() -> tuple:
    import __main__
    script = Path(getattr(__main__, '__file__', '') or '').resolve()
    own = (script.relative_to(ROOT).as_posix(),) if script.is_file() and script.is_relative_to(ROOT) else ()
    return PRODUCT_CODE + own


def tree_state() -> dict:
    """{'commit': HEAD's full hash, 'clean': no uncommitted change to the code it runs (_code()), 'dirty': those}."""
    try:
        commit = _git('rev-parse', 'HEAD')
        dirty = [line.split(None, 1)[1]
                 for line in _git('status', '--porcelain', '--untracked-files=no', '--', *_code()).splitlines()]
    except (OSError, subprocess.CalledProcessError):
        return {'commit': 'unknown', 'clean': False, 'dirty': ['not a git checkout']}
    return {'commit': commit, 'clean': not dirty, 'dirty': dirty[:20]}


def code_changed(a: str, b: str) -> bool:
    """Whether the code a bench runs differs between commits a and b."""
    try:
        return bool(_git('diff', '--name-only', a, b, '--', *_code()))
    except (OSError, subprocess.CalledProcessError):
        return True


def _children_now() -> list[int]:
    """Processes whose parent is this one (from /proc)."""
    me, out = str(os.getpid()), []
    for d in os.listdir('/proc'):
        if d.isdigit():
            try:
                with open(f'/proc/{d}/stat') as f:
                    if f.read().rsplit(')', 1)[1].split()[1] == me:
                        out.append(int(d))
            except (OSError, IndexError):
                continue
    return out


def start_module_trace() -> None:
    """Trace the photogram_ros files this process and the Python processes it starts from now on run (once). A
    process started with the trace on (its parent traced) is traced from its start; else the trace starts now and
    says so when children already ran (they were not traced)."""
    if module_trace.traced():
        return
    folder = os.environ.get(module_trace.TRACE_DIR_ENV)
    if not folder:
        folder = tempfile.mkdtemp(prefix='photogram_module_trace_')
        atexit_rm = folder
    else:
        atexit_rm = None
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    before = ru.ru_utime + ru.ru_stime > 0 or ru.ru_maxrss > 0 or _children_now()
    module_trace.install(folder, late=True)
    if before:
        module_trace.add_note('child processes ran before the trace started (bench/machine.py imported late)')
    if atexit_rm:
        import atexit
        atexit.register(shutil.rmtree, atexit_rm, True)


def executed_modules(declared: list[str]) -> tuple[list[str], dict]:
    """(the line's modules, its module_trace record): the repository files the bench and its children ran (plus
    the declared paths narrower than the whole product) when the trace is complete, else `declared`."""
    if not module_trace.traced():
        return list(declared), {'complete': False, 'why': 'not traced (bench/machine.py not imported by a bench '
                                                           'script: start_module_trace() not called)'}
    c = module_trace.collect()
    why = list(c['notes'])
    if c['unfinished']:
        why.append(f'{len(c["unfinished"])} process(es) ended without writing their modules (killed with -9?): '
                   + '; '.join(f'pid {u["pid"]} {u["argv"]}' for u in c['unfinished'][:3]))
    other = [r for r in c['roots'] if Path(r).resolve() != ROOT]
    if other or c['foreign']:
        why.append(f'photogram_ros loaded from another checkout: {(other or c["foreign"])[:3]}')
    info = {'complete': not why, 'processes': c['processes'], 'running': c['running']}
    if why:
        return list(declared), {**info, 'why': '; '.join(why) + ': the declared modules kept'}
    narrow = [m for m in declared if m not in WHOLE_PRODUCT]
    return sorted(set(c['files']) | set(narrow)), info


def _traced_bench() -> bool:
    import __main__
    main = Path(getattr(__main__, '__file__', '') or '').resolve()
    return main.parent == ROOT / 'bench' or bool(os.environ.get(module_trace.TRACE_DIR_ENV))


if _traced_bench():
    start_module_trace()


class ResultWriter:
    """Appends result lines to `path`, each stamped with the commit the bench started at, the clean-tree flag (false
    when the code had uncommitted changes at the start or at that line, or a new commit changed it), the cores,
    its load average (1, 5, 15 min) at that moment, the UTC time, the bench's name and `modules` (the
    repository paths the figures measure: a change to one of them after `commit` makes the figure stale; the
    traced files the bench ran when the trace is complete, see executed_modules).
    `fresh` truncates the file first; `echo` also prints each line on stdout (benches whose lines were read
    from their output)."""

    def __init__(self, path: str | Path, bench: str, modules: list[str], fresh: bool = True, echo: bool = False):
        if not modules:
            raise ValueError('a result names the modules it measures (paths in the repository)')
        self.path = Path(path)
        self.bench = bench
        self.modules = list(modules)
        self.echo = echo
        self.state = tree_state()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if fresh:
            self.path.write_text('')

    def stamp(self) -> dict:
        # The tree as it is at this line: a change made while a long bench runs marks the lines after it.
        now = tree_state()
        clean = self.state['clean'] and now['clean'] and (now['commit'] == self.state['commit']
                                                          or not code_changed(self.state['commit'], now['commit']))
        modules, trace = executed_modules(self.modules)
        return {'bench': self.bench, 'commit': self.state['commit'], 'clean': clean,
                'cores': os.cpu_count(), 'load_avg': [round(x, 2) for x in os.getloadavg()],
                'utc': datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ'),
                'modules': modules, 'modules_declared': self.modules, 'module_trace': trace}

    def write(self, row: dict) -> dict:
        """Append `row` (its own keys win over none of the stamp's: the stamp is authoritative)."""
        line = {**row, **self.stamp()}
        text = json.dumps(line, default=str)
        with open(self.path, 'a') as fh:
            fh.write(text + '\n')
        if self.echo:
            print(text, flush=True)
        return line

    @classmethod
    def for_bench(cls, out: str | Path | None, bench: str, modules: list[str], echo: bool = True) -> 'ResultWriter':
        """A bench's writer: `out` (its --out), else /tmp/<bench>.jsonl; says on stderr where the lines go."""
        import sys
        path = Path(out) if out else Path('/tmp') / f'{bench}.jsonl'
        print(f'{bench}: result lines to {path} (copy to bench/results/{bench}_COMMIT.jsonl to quote them)',
              file=sys.stderr, flush=True)
        return cls(path, bench, modules, echo=echo)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
