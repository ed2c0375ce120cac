"""Child processes of the tests: never left running when a test fails."""

from __future__ import annotations

import contextlib
import subprocess


@contextlib.contextmanager
def reaped(proc: subprocess.Popen):
    """The block's process; killed (and waited for) at the end of the block if it is still running,
    whatever ended the block (a failed assertion, a timeout)."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
