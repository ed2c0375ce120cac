"""`fixes --events` on a Timestamp.MRK whose last line was cut off: every whole event printed, the cut line named."""
from pathlib import Path

from photogram_ros.cli import main

MRK = Path(__file__).parent / 'data' / 'trajectories' / 'Timestamp.MRK'


def test_fixes_events_names_the_cut_line_and_prints_every_whole_event(tmp_path, capsys):
    whole = MRK.read_bytes()
    n_events = sum(1 for line in whole.decode().splitlines() if line.strip())
    cut = tmp_path / 'cut.MRK'
    cut.write_bytes(whole.rstrip(b'\n')[:-30])            # the file ends in the middle of its last line
    rc = main(['fixes', '--events', str(cut)])
    out, err = capsys.readouterr()
    rows = [line for line in out.splitlines() if line.strip()]
    assert rc == 0
    assert len(rows) == 1 + (n_events - 1)                 # the header, then every event but the cut one
    assert f'line {n_events}: cut off' in err and 'skipped' in err
