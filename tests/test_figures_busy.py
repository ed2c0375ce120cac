"""bench/render_figures.py on a 635-photo scale run that began beside other work: its wall time is labelled as no
speed figure, and its workers are not compared (a 1-worker run slowed by other jobs would make 2 workers look
faster than they are)."""

from bench import render_figures as rf


def _lines(load_1w, load_2w):
    def run(workers, load, wall):
        return {'cores': 2, 'run': {'workers': workers, 'mode': 'split', 'load_before': load, 'wall_s': wall,
                                    'oriented': 635, 'check_n': 4, 'check_h_m': 0.014, 'check_v_m': 0.03}}
    cmp_ = {'cores': 2, 'compare': 'workers 2 / workers 1', 'photos': 635, 'matching_speedup': 1.3, 'speedup': 2.4,
            'same_matches': True}
    return [run(1, load_1w, 4233.0), run(2, load_2w, 1760.0), cmp_]


def test_a_busy_run_is_no_speed_figure_and_its_workers_are_not_compared():
    lines = _lines(2.14, 1.6)
    one, two = rf._scale_cells(lines[0], lines)[0], rf._scale_cells(lines[1], lines)[0]
    assert 'at load 2.14 on 2 cores (other work beside it: not a speed figure)' in one
    assert 'not a speed figure' not in two
    assert '2 workers against 1 not compared (the 1-worker run began at load 2.14)' in two and 'faster' not in two
    cell = rf._dask_matching_cell(lines[2], lines)
    assert 'not compared' in cell and 'faster' not in cell


def test_quiet_runs_are_compared():
    lines = _lines(0.02, 1.11)
    two = rf._scale_cells(lines[1], lines)[0]
    assert two.endswith('; 2 workers 2.40x faster than 1 in the same run') and 'not a speed figure' not in two
    assert rf._dask_matching_cell(lines[2], lines).startswith('matching 1.30x faster on 2 workers than on 1')
