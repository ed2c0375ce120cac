"""Which photogram_ros files a bench really ran: every Python process of a bench writes the package files it
loaded (its `photogram_ros.*` modules) and the config/ and package files it opened, so that a figure goes stale
only when one of those changes (bench/render_figures.py), not with any change to the product.

A process is traced when this folder is on PYTHONPATH (its sitecustomize.py calls `install_from_env()`) and
TRACE_DIR_ENV names a folder D: the process writes D/<pid>.json and its children write under D/<pid>/ (this
process sets TRACE_DIR_ENV to that folder for them, and puts itself on the PYTHONPATH of every child started with
an explicit environment), so the files under D/<pid>/ are all of a process's descendants. bench/machine.py
calls `install()` in a bench's own process and reads the tree with `collect()`.

A process writes its file when it starts ("final": false), again every POLL_S seconds when its list grew, and
for the last time ("final": true) at exit, on SIGTERM when nothing else handles it (the default handler is
chained: the process still ends) and at the end of a forked multiprocessing child (a forked child writes only
then: one killed with -9 is not seen, its modules are mostly its parent's). A process killed with -9 (or
ended by os._exit) leaves a file that is not final: `collect()` reports it, and the result falls back to the
whole product.
"""

from __future__ import annotations

import atexit
import json
import os
import signal
import sys
import threading

TRACE_DIR_ENV = 'PHOTOGRAM_MODULE_TRACE_DIR'
TRACE_PID_ENV = 'PHOTOGRAM_MODULE_TRACE_PID'     # the pid of the process whose tracer set TRACE_DIR_ENV
SITE_DIR = os.path.dirname(os.path.abspath(__file__))
PACKAGE = 'photogram_ros'
POLL_S = 2.0

_state: dict = {}
_opened: set = set()


# --- this process --------------------------------------------------------------------------------------


def _start_ticks(pid: int) -> str:
    """The process's start time (clock ticks since boot, /proc/PID/stat field 22): a pid reused later differs."""
    try:
        with open(f'/proc/{pid}/stat') as f:
            return f.read().rsplit(')', 1)[1].split()[19]
    except (OSError, IndexError):
        return ''


def alive(pid: int, start: str) -> bool:
    """Whether process `pid` started at `start` still runs (a zombie has ended)."""
    try:
        with open(f'/proc/{pid}/stat') as f:
            rest = f.read().rsplit(')', 1)[1].split()
    except (OSError, IndexError):
        return False
    return rest[0] not in ('Z', 'X') and (not start or rest[19] == start)


def package_root() -> str | None:
    """The folder holding the loaded photogram_ros package (a checkout's root), or None before it is imported."""
    mod = sys.modules.get(PACKAGE)
    f = getattr(mod, '__file__', None)
    return os.path.dirname(os.path.dirname(os.path.abspath(f))) if f else None


def loaded_files() -> dict:
    """{'root': the package's checkout, 'files': its files this process loaded or opened (paths under root),
    'foreign': package files from elsewhere}."""
    root = package_root()
    paths = set()
    for name, mod in list(sys.modules.items()):
        if name == PACKAGE or name.startswith(PACKAGE + '.'):
            f = getattr(mod, '__file__', None)
            if f:
                paths.add(os.path.abspath(f))
    paths |= set(_opened)
    files, foreign = set(), set()
    for p in paths:
        rel = os.path.relpath(p, root) if root else p
        if root and not rel.startswith('..') and rel.split(os.sep)[0] in (PACKAGE, 'config'):
            files.add(rel.replace(os.sep, '/'))
        elif os.sep + PACKAGE + os.sep in p:
            foreign.add(p)
    return {'root': root, 'files': sorted(files), 'foreign': sorted(foreign)}


def _audit(event: str, args) -> None:
    # The package's data and the parameter files a process opens (config/*.yaml): paths with these folders.
    if event != 'open':
        return
    try:
        p = args[0]
        if isinstance(p, bytes):
            p = os.fsdecode(p)
        if isinstance(p, str) and ((os.sep + 'config' + os.sep) in p or (os.sep + PACKAGE + os.sep) in p
                                   or p.startswith('config' + os.sep)) and '__pycache__' not in p:
            _opened.add(os.path.abspath(p))
    except Exception:       # a trace must never break the process it watches
        pass


def _command_line() -> list[str]:
    try:
        with open('/proc/self/cmdline', 'rb') as f:
            return [os.fsdecode(a)[:200] for a in f.read().split(b'\0') if a][:8]
    except OSError:
        return sys.argv[:8]


def _write(final: bool, why: str = '') -> None:
    s = _state
    if not s or s.get('pid') != os.getpid():
        return
    try:
        got = loaded_files()
        key = (final, len(got['files']), len(got['foreign']))
        if key == s.get('written') and not final:
            return
        doc = {'pid': s['pid'], 'ppid': os.getppid(), 'start': s['start'], 'argv': s['argv'],
               'late': s['late'], 'final': final, 'why': why, **got}
        tmp = s['file'] + '.tmp'
        with open(tmp, 'w') as f:
            json.dump(doc, f)
        os.replace(tmp, s['file'])
        s['written'] = key
    except Exception:
        pass


def _on_term(signum, frame) -> None:
    _write(True, 'SIGTERM')
    prev = _state.get('prev_term')
    if callable(prev):
        prev(signum, frame)
        return
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    os.kill(os.getpid(), signal.SIGTERM)


def _poll() -> None:
    pid = os.getpid()
    while _state.get('pid') == pid:
        _write(False)
        threading.Event().wait(POLL_S)


def _after_fork() -> None:
    # A forked child is a child of the process that forked it: its file goes in that process's children's folder,
    # written at its end only (no thread, no write here: a child about to exec another program must not leave an
    # unfinished file behind; an exec'd Python writes its own, under the same pid).
    parent_children = _state.get('children')
    if parent_children:
        _begin(parent_children, late=False, eager=False)
        if 'multiprocessing' in sys.modules:
            try:
                # A multiprocessing child ends with os._exit after its finalizers; it clears those it inherited
                # first, then runs its after-fork hooks: register the finalizer from one of those.
                import multiprocessing.util as mpu
                _state['mp_hook'] = hook = _Hook()
                mpu.register_after_fork(hook, _Hook.register_finalizer)
            except Exception:
                pass


class _Hook:
    @staticmethod
    def register_finalizer(_self) -> None:
        import multiprocessing.util as mpu
        mpu.Finalize(None, _write, args=(True, 'multiprocessing child end'), exitpriority=0)


def _begin(folder: str, late: bool, eager: bool = True) -> None:
    pid = os.getpid()
    children = os.path.join(folder, str(pid))
    os.makedirs(children, exist_ok=True)
    _state.update(pid=pid, start=_start_ticks(pid), argv=_command_line(), file=os.path.join(folder, f'{pid}.json'), children=children,
                  late=late, written=None)
    os.environ[TRACE_DIR_ENV] = children
    os.environ[TRACE_PID_ENV] = str(pid)
    if eager:
        _write(False)
        threading.Thread(target=_poll, daemon=True, name='module-trace').start()


def _child_env(env):
    """An explicit child environment with the trace on: this folder on its PYTHONPATH, TRACE_DIR_ENV set."""
    if env is None or not _state:
        return env
    env = dict(env)
    env[TRACE_DIR_ENV] = _state['children']
    parts = [p for p in str(env.get('PYTHONPATH', '')).split(os.pathsep) if p]
    if SITE_DIR not in parts:
        env['PYTHONPATH'] = os.pathsep.join([SITE_DIR] + parts)
    return env


def _patch_popen() -> None:
    import subprocess
    if getattr(subprocess.Popen.__init__, '_module_trace', False):
        return
    init = subprocess.Popen.__init__

    def traced_init(self, *a, **k):
        if 'env' in k:
            k['env'] = _child_env(k['env'])
        init(self, *a, **k)
    traced_init._module_trace = True
    subprocess.Popen.__init__ = traced_init


def install(folder: str, late: bool) -> str:
    """Trace this process into `folder` (once) and its children under `folder`/<pid>; `late`: installed after the
    process started (by bench/machine.py), so children it started before are not traced. Returns the
    children's folder."""
    if _state.get('pid') == os.getpid():
        return _state['children']
    first = not _state
    _begin(folder, late)
    parts = [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]
    if SITE_DIR not in parts:
        os.environ['PYTHONPATH'] = os.pathsep.join([SITE_DIR] + parts)
    if first:
        sys.addaudithook(_audit)
        atexit.register(_write, True, 'exit')
        os.register_at_fork(after_in_child=_after_fork)
        _patch_popen()
        try:
            if threading.current_thread() is threading.main_thread() and \
                    signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
                _state['prev_term'] = signal.SIG_DFL
                signal.signal(signal.SIGTERM, _on_term)
        except (ValueError, OSError):
            pass
    return _state['children']


def install_from_env() -> None:
    folder = os.environ.get(TRACE_DIR_ENV)
    if folder:
        install(folder, late=False)


def traced() -> bool:
    """Whether this process is traced (its children's folder is set up)."""
    return _state.get('pid') == os.getpid()


def started_late() -> bool:
    return bool(_state.get('late'))


def add_note(text: str) -> None:
    """A reason this process's trace is not complete (collect() returns it in 'notes')."""
    _state.setdefault('notes', []).append(text)


# --- a process's descendants ---------------------------------------------------------------------------


def collect(folder: str | None = None) -> dict:
    """What this process and its descendants ran: {'root', 'files' (union), 'foreign', 'processes',
    'running', 'unfinished' (ended without a final list: [{'pid', 'argv'}]), 'late', 'notes' (add_note)}."""
    folder = folder or _state.get('children')
    own = loaded_files()
    files, foreign = set(own['files']), set(own['foreign'])
    roots = {own['root']} if own['root'] else set()
    n, running, unfinished = 1, 0, []
    for dirpath, _dirs, names in os.walk(folder or os.devnull):
        for name in names:
            if not name.endswith('.json'):
                continue
            try:
                with open(os.path.join(dirpath, name)) as f:
                    doc = json.load(f)
            except (OSError, ValueError):
                continue
            n += 1
            if not doc.get('final'):
                if alive(doc.get('pid', -1), doc.get('start', '')):
                    running += 1
                else:
                    unfinished.append({'pid': doc.get('pid'), 'argv': ' '.join(doc.get('argv') or [])[:160]})
            files |= set(doc.get('files') or [])
            foreign |= set(doc.get('foreign') or [])
            if doc.get('root') and doc.get('files'):
                roots.add(doc['root'])
    return {'roots': sorted(roots), 'files': sorted(files), 'foreign': sorted(foreign), 'processes': n,
            'running': running, 'unfinished': unfinished, 'late': started_late(), 'notes': list(_state.get('notes', []))}


def chain_next_sitecustomize(this_file: str) -> None:
    """Run the next sitecustomize.py on sys.path after `this_file`'s folder (a folder before ours shadows the
    rest; Python imports only the first)."""
    import importlib.util
    here = os.path.dirname(os.path.abspath(this_file))
    seen = False
    for p in list(sys.path):
        d = os.path.abspath(p or os.getcwd())
        if d == here:
            seen = True
            continue
        f = os.path.join(d, 'sitecustomize.py')
        if seen and os.path.isfile(f):
            spec = importlib.util.spec_from_file_location(f'_sitecustomize_{abs(hash(d))}', f)
            mod = importlib.util.module_from_spec(spec)
            sys.modules[spec.name] = mod
            spec.loader.exec_module(mod)
            return
