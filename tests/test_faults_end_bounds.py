"""The end of flight's memory bound (issue 48): `run --end-max-rss-mb` cuts the end-of-flight steps short when the
mapping processes' RSS goes above it, as `--end-timeout-s` does past its time (tests/test_faults_stop.py)."""

from __future__ import annotations

import threading
import time

from test_faults_stop import end_of_flight_graph


def test_the_end_of_flight_is_cut_short_above_its_memory_bound():
    """finish_within_bounds with a 1 MB bound (any Python process is above it): the step running is cut short,
    the steps left are skipped, said with the option's name, and no final adjustment is claimed."""
    from photogram_ros.commands.run import finish_within_bounds

    release = threading.Event()
    said: list[str] = []
    graph, nodes = end_of_flight_graph(release)
    skip = threading.Event()
    t0 = time.monotonic()
    end = finish_within_bounds(graph, skip, timeout_s=600.0, max_rss_mb=1.0, say=said.append)
    release.set()
    assert time.monotonic() - t0 < 25.0   # cut at the first look (0.5 s) and the running step's 10 s grace
    assert skip.is_set() and end.final_adjustment == 'failed', (end, said)
    assert any('above --end-max-rss-mb 1' in s for s in said), said
    time.sleep(0.2)
    assert nodes['bundle'].called == 0 and nodes['stereo'].called == 0


def test_no_memory_bound_lets_the_steps_run():
    """--end-max-rss-mb 0 (the default): no bound; the steps all run and the final adjustment is not failed."""
    from photogram_ros.commands.run import finish_within_bounds

    graph, nodes = end_of_flight_graph()
    skip = threading.Event()
    end = finish_within_bounds(graph, skip, timeout_s=600.0, max_rss_mb=0.0, say=[].append)
    assert not skip.is_set() and end.final_adjustment != 'failed', end
    assert all(n.called for n in nodes.values()), {r: n.called for r, n in nodes.items()}
