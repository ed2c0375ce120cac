"""The machine's figures, and the one writer of benchmark result files.

Every bench writes its results through `ResultWriter`: JSON lines, each carrying the exact commit the
code was at (`commit`, 40 hex digits), whether the working tree had uncommitted changes to the code a bench
runs (`clean`: the product, bench/machine.py and the bench's own script), the machine's cores and load average when the line was written, the UTC time, and
the modules (paths in the repository) the figure measures. bench/render_figures.py renders the docs'
tables from these files and marks a figure stale when one of its modules changed (git log) after `commit`.

    with ResultWriter('bench/results/stereo_middlebury.jsonl', 'stereo_middlebury',
                      modules=['photogram_ros/core/stereo.py']) as w:
        w.write({'scene': 'venus', 'bad2': 0.003})
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


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


class ResultWriter:
    """Appends result lines to `path`, each stamped with the commit the bench started at, the clean-tree flag (false
    when the code had uncommitted changes at the start or at that line, or a new commit changed it), the cores,
    its load average (1, 5, 15 min) at that moment, the UTC time, the bench's name and `modules` (the
    repository paths the figures measure: a change to one of them after `commit` makes the figure stale).
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
        return {'bench': self.bench, 'commit': self.state['commit'], 'clean': clean,
                'cores': os.cpu_count(), 'load_avg': [round(x, 2) for x in os.getloadavg()],
                'utc': datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ'),
                'modules': self.modules}

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
