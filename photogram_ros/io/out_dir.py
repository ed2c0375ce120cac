"""Output folders: one writer at a time, and no silent reuse.

A command that writes a folder (`replay --out`, `run`'s map folder and `--out`) claims it first
(`claim_output`):

- the path must be a folder that exists or can be created (a file, or a path below a file or in a
  read-only place, is a ConfigError naming it);
- it is locked for as long as the process lives: `.photogram-ros.lock` in it holds an exclusive
  flock(2) and says which process (pid, command, start time). The kernel releases the lock when the
  process ends, however it ends (kill -9 included), so a lock is never stale; a second command into a
  locked folder is refused with the owner's pid;
- a folder that already holds something is refused unless the caller says what to do with it:
  'resume' (continue the map in it; products are replaced) or 'overwrite' (delete what a previous
  photogram_ros run wrote there first). A folder that is not one of ours (no lock file, no map) is
  never deleted, nor written into by a 'resume'.
"""

from __future__ import annotations

import datetime
import errno
import fcntl
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from photogram_ros.errors import ConfigError

LOCK_NAME = '.photogram-ros.lock'
MODES = ('new', 'resume', 'overwrite')


@dataclass
class OutputLock:
    """A claimed folder; `close()` (or the process's end) releases it. `previous`: what was there."""

    path: Path
    fd: int
    previous: list

    def close(self) -> None:
        if self.fd >= 0:
            try:
                os.ftruncate(self.fd, 0)
                os.write(self.fd, json.dumps({**self._owner(), 'finished': _now()}).encode())
            except OSError:
                pass
            os.close(self.fd)   # releases the flock
            self.fd = -1

    def _owner(self) -> dict:
        try:
            return json.loads((self.path / LOCK_NAME).read_text() or '{}')
        except (OSError, ValueError):
            return {}

    def __enter__(self) -> 'OutputLock':
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')


def usable_folder(path, what: str = '--out') -> Path:
    """`path` as a folder that exists now (created if needed); a ConfigError saying why it cannot be."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(f'{what} {p} is a file, not a folder: choose a folder name')
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        why = exc.strerror or str(exc)
        if isinstance(exc, (FileExistsError, NotADirectoryError)) or exc.errno in (errno.EEXIST, errno.ENOTDIR):
            why = 'a part of the path is a file'
        raise ConfigError(f'{what} {p} cannot be created ({why}): choose a folder you can write') from None
    if not os.access(p, os.W_OK | os.X_OK):
        raise ConfigError(f'{what} {p} is not writable: choose a folder you can write')
    return p


def _open_and_lock(lock: Path, what: str, p: Path) -> tuple[int, bool, bool]:
    """(fd, whether this call created the lock file, whether it holds the flock). A lock file that a
    refused claim removed after this one opened it is not the folder's lock any more (another
    process may create and lock a new one): the claim then opens the file the path names now."""
    for _ in range(20):
        created = not lock.exists()
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise ConfigError(f'{what} {p}: cannot create its lock file ({exc.strerror or exc})') from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return fd, created, False
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if same:
            return fd, created, True
        os.close(fd)
    raise ConfigError(f'{what} {p}: its lock file keeps changing: another photogram-ros is claiming it; try again')


def claim_output(path, mode: str = 'new', command: str = '', what: str = '--out') -> OutputLock:
    """Lock `path` (created if needed) for this process and apply `mode` to what it already holds:
    'new' refuses a folder with anything in it, 'resume' keeps it, 'overwrite' deletes a previous
    photogram_ros run's files first. ConfigError (exit 2) with the reason otherwise."""
    if mode not in MODES:
        raise ConfigError(f'output mode {mode!r}: choose one of {MODES}')
    p = usable_folder(path, what)
    lock = p / LOCK_NAME
    try:   # a lock file with an owner in it: a photogram-ros run wrote this folder
        ours_before = bool(lock.read_text().strip())
    except OSError:
        ours_before = False
    fd, created, taken = _open_and_lock(lock, what, p)
    if not taken:
        try:
            owner = json.loads(os.pread(fd, 4096, 0).decode() or '{}')
        except (OSError, ValueError):
            owner = {}
        os.close(fd)
        who = f"pid {owner.get('pid', '?')}" + (f", {owner['command']}" if owner.get('command') else '') + \
            (f" since {owner['started']}" if owner.get('started') else '')
        raise ConfigError(f'{what} {p} is being written by another photogram-ros ({who}): wait for it to end, '
                          'or choose another folder') from None
    previous = sorted(e.name for e in p.iterdir() if e.name != LOCK_NAME)
    try:
        if previous and mode == 'new':
            shown = ', '.join(previous[:5]) + (', ...' if len(previous) > 5 else '')
            raise ConfigError(f'{what} {p} holds a previous run ({shown}): --resume continues its map, '
                              '--overwrite replaces it, or choose a new folder')
        ours = ours_before or (p / 'map.json').exists() or (p / 'map' / 'map.json').exists()
        if previous and mode != 'new' and not ours:
            doing = 'not deleting it' if mode == 'overwrite' else 'it holds no map to resume'
            raise ConfigError(f'{what} {p} is not a photogram-ros output folder (it holds {", ".join(previous[:5])}'
                              f'{", ..." if len(previous) > 5 else ""}): {doing}; choose a new folder')
        if previous and mode == 'overwrite':
            for name in previous:
                e = p / name
                if e.is_dir() and not e.is_symlink():
                    shutil.rmtree(e)
                else:
                    e.unlink()
    except BaseException:
        if created:
            lock.unlink(missing_ok=True)
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.write(fd, json.dumps({'pid': os.getpid(), 'command': command or 'photogram-ros',
                             'started': _now()}).encode())
    return OutputLock(p, fd, previous if mode != 'overwrite' else [])
