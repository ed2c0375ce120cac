"""io/progress.py with a fake clock: when lines are said, their percent and ETA, the smoothed rate, the summary."""

import re

import pytest

from photogram_ros.io.progress import Progress, Steps, duration_text


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_lines_at_most_every_n_seconds_with_percent_and_eta():
    clock, lines = Clock(), []
    p = Progress('replay', 850, 'frames', lines.append, every_s=5.0, clock=clock)
    for k in range(1, 851):   # 2 frames a second
        clock.t += 0.5
        p.update(k)
        if k == 312:
            break
    # 156 s of work, a line at most every 5 s: 31 lines, never two within 5 s.
    assert len(lines) == 31
    assert lines[-1] == 'replay: 310/850 frames (36 %), 2.6 min elapsed, ETA 4.5 min'
    # The ETA is the frames left at the rate: 540 / 2 per second = 4.5 min.
    assert p.eta_s() == pytest.approx((850 - 312) / 2.0)
    assert p.finish() == 'replay: 312/850 frames (36 %) in 2.6 min'
    p.update(400)
    assert lines[-1] == 'replay: 312/850 frames (36 %) in 2.6 min'   # nothing said after the summary


def test_summary_says_100_percent_and_quiet_says_nothing():
    clock, lines = Clock(), []
    p = Progress('export: dense matching', 53, 'keyframes', lines.append, every_s=5.0, clock=clock)
    report = p.callback()
    for k in range(1, 54):
        clock.t += 0.2
        report(k, 53)
    assert lines[-1] == 'export: dense matching: 53/53 keyframes (100 %) in 11 s'
    assert sum('(100 %) in' in s for s in lines) == 1
    quiet = Progress('replay', 10, 'frames', None, every_s=0.0, clock=clock)
    for k in range(10):
        clock.t += 1.0
        assert quiet.update(k) is False
    quiet.finish()


def test_unknown_total_says_eta_unknown():
    clock, lines = Clock(), []
    p = Progress('replay', None, 'frames', lines.append, every_s=2.0, clock=clock)
    for k in range(1, 20):
        clock.t += 1.0
        p.update(k)
    assert lines and all(s.endswith('ETA unknown') for s in lines)
    assert re.fullmatch(r'replay: \d+ frames, \d+ s elapsed, ETA unknown', lines[-1])
    assert p.finish() == 'replay: 19 frames in 19 s'


def test_eta_unknown_before_a_rate_and_while_nothing_moves():
    clock, lines = Clock(), []
    p = Progress('triangulate: matching', 40, 'pairs', lines.append, every_s=0.0, clock=clock)
    p.update(0)
    assert lines[-1].endswith('ETA unknown')
    clock.t += 2.0
    p.update(0)   # a rate of 0: no end in sight
    assert lines[-1] == 'triangulate: matching: 0/40 pairs (0 %), 2 s elapsed, ETA unknown'


def test_smoothed_rate_follows_a_change_without_jumping():
    """10 pieces/s for 60 s, then 1 piece/s: the ETA moves towards the new rate over the time constant,
    not at once (one slow piece does not swing it) and not never (the average since the start would)."""
    clock = Clock()
    p = Progress('x', 10_000, 'pieces', None, clock=clock, tau_s=30.0, sample_s=1.0)
    done = 0
    for _ in range(60):
        clock.t += 1.0
        done += 10
        p.update(done)
    assert p.rate == pytest.approx(10.0)
    clock.t += 1.0
    done += 1
    p.update(done)
    assert 9.0 < p.rate < 10.0                 # one slow second moves it by about 1/30 of the change
    for _ in range(89):
        clock.t += 1.0
        done += 1
        p.update(done)
    assert 1.0 < p.rate < 1.5                  # after 3 time constants: near the new rate
    mean_since_start = done / (clock.t - p.t0)
    assert mean_since_start > 4.0              # where a plain average would still be


def test_steps_say_each_step_and_the_longest():
    clock, lines = Clock(), []
    s = Steps('export', 3, lines.append, clock=clock)
    s.start('LAS')
    clock.t += 2.0
    s.start('DSM')
    clock.t += 30.0
    p = s.progress('ortho', 20, 'keyframes', every_s=5.0)
    for k in range(1, 21):
        clock.t += 1.0
        p.update(k)
    p.finish()
    assert lines[:3] == ['export: LAS (step 1/3), 0 s elapsed', 'export: DSM (step 2/3), 2 s elapsed',
                         'export: ortho (step 3/3), 32 s elapsed']
    assert 'export: ortho: 5/20 keyframes (25 %), 5 s elapsed, ETA 15 s' in lines
    assert lines[-1] == 'export: ortho: 20/20 keyframes (100 %) in 20 s'
    assert s.finish() == 'export: 3 steps in 52 s (longest: DSM, 30 s)'


def test_duration_text():
    assert [duration_text(s) for s in (0.4, 59.4, 126.0, 3600 * 1.26)] == ['0 s', '59 s', '2.1 min', '1.3 h']


def test_triangulate_of_a_photo_folder_says_percents_of_photos_and_pairs(tmp_path, monkeypatch, capsys):
    """`triangulate` of a small simulated photo folder: features counted in photos, matching in pairs, the
    incremental adjustment in photos added, each with a percent and an ETA, each ending at 100 %; with
    --quiet none of it."""
    from photogram_ros import cli
    from photogram_ros.io import progress
    from photogram_ros.sim.scenario import preset, simulate
    simulate(preset('tiny', photos=True, fps=1.0, line_length_m=30.0), tmp_path / 'flight')
    photos = tmp_path / 'flight' / 'photos'
    n = len(list(photos.glob('*.JPG')))
    monkeypatch.setattr(progress, 'EVERY_S', 0.0)   # a line at every piece
    small = ['--max-image-px', '500', '--max-features', '1000']
    assert cli.main(['triangulate', str(photos), '--out', str(tmp_path / 'at'), *small]) == 0
    err = capsys.readouterr().err.splitlines()
    for what, unit, total in (('features', 'photos', n), ('matching', 'pairs', None),
                              ('aerial triangulation', 'photos added', n)):
        pat = rf'triangulate: {what}: (\d+)/(\d+) {unit} \((\d+) %\), \d+ s elapsed, ETA (\d+ s|[\d.]+ min|unknown).*'
        lines = [m for m in (re.fullmatch(pat, s) for s in err) if m]
        assert len(lines) >= 2, (what, err)
        if total is not None:
            assert all(int(m[2]) == total for m in lines)
        assert any('ETA unknown' not in m[0] for m in lines), what
        assert any(re.fullmatch(rf'triangulate: {what}: (\d+)/\1 {unit} \(100 %\) in \d+ s.*', s) for s in err), what
    assert any(re.fullmatch(r'triangulate: full adjustment \(step \d+\), \d+ s elapsed', s) for s in err)
    assert re.fullmatch(r'triangulate: \d+ steps in .*', [s for s in err if s.startswith('triangulate: ')][-1])
    assert cli.main(['triangulate', str(photos), '--out', str(tmp_path / 'quiet'), '--quiet', *small]) == 0
    assert not [s for s in capsys.readouterr().err.splitlines() if ' %' in s or 'elapsed' in s]
