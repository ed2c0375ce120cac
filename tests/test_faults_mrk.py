"""A cut-off last MRK line (issue 48: the card pulled or the battery gone while the drone wrote it) is skipped and
named, through read_events (fixes --events) as through read_mrk (geotag); a bad line elsewhere is still refused,
naming it."""

from __future__ import annotations

from pathlib import Path

import pytest

MRK = Path(__file__).parent / 'data' / 'trajectories' / 'Timestamp.MRK'


def test_a_cut_last_mrk_line_is_skipped_and_named_by_read_events(tmp_path):
    from photogram_ros.errors import DataError
    from photogram_ros.io.camera_events import mrk_cut_line, read_events
    text = MRK.read_text()
    whole = read_events(MRK)
    cut = tmp_path / 'Timestamp.MRK'
    cut.write_text(text[:-40])
    notes = []
    events = read_events(cut, notes=notes)
    n = len(text.splitlines())
    assert len(events) == len(whole) - 1 and [e.seq for e in events] == [e.seq for e in whole[:-1]]
    assert len(notes) == 1 and f'line {n}: cut off' in notes[0] and 'skipped' in notes[0], notes
    assert mrk_cut_line(cut)[0] == n and mrk_cut_line(MRK) is None
    lines = text.splitlines()
    lines[3] = lines[3][:20]
    cut.write_text('\n'.join(lines) + '\n')
    with pytest.raises(DataError, match='line 4'):
        read_events(cut)
