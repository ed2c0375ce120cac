"""The end of flight's memory bound (issue 48): `run --end-max-rss-mb` cuts the end-of-flight steps short when the
mapping processes' RSS goes above it, as `--end-timeout-s` does past its time (tests/test_faults_stop.py)."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace


def test_the_end_of_flight_is_cut_short_above_its_memory_bound():
    """finish_within_bounds with a 1 MB bound (any Python process is above it): the step running is cut short,
    the steps left are skipped, said with the option's name, and no final adjustment is claimed."""
    from photogram_ros.commands.run import finish_within_bounds
    from photogram_ros.nodes.graph import Graph

    release = threading.Event()
    said: list[str] = []

    class Node:
        def __init__(self, hang=False):
            self.hang, self.called = hang, 0

        def flush(self):
            self.called += 1
            if self.hang:
                release.wait(30)

        finish = finish_coverage = flush

    nodes = {'tracker': Node(hang=True), 'bundle': Node(), 'stereo': Node(), 'map': Node()}
    graph = SimpleNamespace(spec=SimpleNamespace(roles=tuple(nodes)), child=None, nodes=nodes,
                            counts=lambda: {}, problems=lambda role: [], drain=lambda **kw: {})
    graph.finish_flight = lambda **kw: Graph.finish_flight(graph, **kw)
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
    from photogram_ros.nodes.graph import Graph

    class Node:
        called = 0

        def flush(self):
            self.called += 1

        finish = finish_coverage = flush

    nodes = {'tracker': Node(), 'bundle': Node(), 'stereo': Node(), 'map': Node()}
    graph = SimpleNamespace(spec=SimpleNamespace(roles=tuple(nodes)), child=None, nodes=nodes,
                            counts=lambda: {}, problems=lambda role: [], drain=lambda **kw: {})
    graph.finish_flight = lambda **kw: Graph.finish_flight(graph, **kw)
    skip = threading.Event()
    end = finish_within_bounds(graph, skip, timeout_s=600.0, max_rss_mb=0.0, say=[].append)
    assert not skip.is_set() and end.final_adjustment != 'failed', end
    assert all(n.called for n in nodes.values()), {r: n.called for r, n in nodes.items()}
