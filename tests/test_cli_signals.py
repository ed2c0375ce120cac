"""cli.main and a signal whose exception the command loses (raised inside a finaliser or a callback that
swallows it): the command still ends as stopped by that signal, not with its own exit 0."""
from __future__ import annotations

import os
import signal

import pytest

from photogram_ros import cli


@pytest.mark.parametrize('sig, status', [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_whose_exception_is_lost_still_stops_the_command(monkeypatch, capsys, sig, status):
    def command(argv, words):
        words.append('simulate')
        try:
            os.kill(os.getpid(), sig)     # the handler runs here and raises ...
            for _ in range(1000):         # (at the next bytecode at the latest)
                pass
        except BaseException:             # ... and the exception is lost, as in a finaliser
            pass
        return 0
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    monkeypatch.setattr(cli, '_main', command)
    try:
        assert cli.main([]) == status
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
    assert capsys.readouterr().err.strip().endswith(f'simulate: stopped by {sig.name}')


def test_a_ros_command_keeps_its_own_status_after_a_signal(monkeypatch):
    """run, replay ... take SIGINT as their stop and say how the flight ended: their status stands."""
    def command(argv, words):
        words.append('replay')
        try:
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):
                pass
        except KeyboardInterrupt:
            pass
        return 5
    previous = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(cli, '_main', command)
    try:
        assert cli.main([]) == 5
    finally:
        signal.signal(signal.SIGINT, previous[0])
        signal.signal(signal.SIGTERM, previous[1])
