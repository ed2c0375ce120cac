"""The stereo worker's batch order (stereo_node along_pairs_first): every keyframe's along-line pair before the
across-line ones, each kind oldest first; as planned without it."""

from photogram_ros.core.pairs import PlannedPair
from photogram_ros.nodes.stereo_node import PairJob, batch_order


def _job(b, other, along):
    pair = PlannedPair(other=other, baseline_ratio=0.22, overlap=0.7, along=along, depth_range_m=(50.0, 90.0),
                       from_tie_points=True)
    return ('a', b, PairJob(pair, None, None, None))


def test_along_pairs_first_puts_each_keyframes_along_pair_before_the_across_ones():
    todo = [_job(3, 2, True), _job(3, 1, False), _job(4, 3, True), _job(4, 0, False), _job(5, 4, True)]
    assert batch_order(todo, False) == todo
    assert [(b, j.pair.other) for _, b, j in batch_order(todo, True)] == [(3, 2), (4, 3), (5, 4), (3, 1), (4, 0)]
