"""A keyframe counted not oriented when it came and oriented by a later step (it waited) leaves the
not-oriented counters again: oriented + not oriented stays the keyframes processed (a replay's backpressure
and the flight report count on it)."""

from types import SimpleNamespace

from photogram_ros.stages.adjustment_counts import NotOrientedCounts
from photogram_ros.stages.report import DiagnosticsLog


def test_a_waiting_keyframe_oriented_later_is_counted_once():
    diag = DiagnosticsLog()
    counts = NotOrientedCounts(diag)
    kfs = {0: SimpleNamespace(stamp_ns=100), 1: SimpleNamespace(stamp_ns=200), 2: SimpleNamespace(stamp_ns=300)}
    block = SimpleNamespace(registered=[], keyframe=lambda kid: kfs[kid])
    counts.count('waiting for initialisation', 100)
    counts.count('too few known points (12 of 30)', 200)
    c = diag.counts()
    assert c['keyframes_not_oriented'] == 2 and c['not_oriented_too_few_known_points'] == 1
    block.registered = [2, 0]            # a step orients keyframe 2 and the one that waited since 100
    counts.oriented_since(block, 2)
    c = diag.counts()
    assert c['keyframes_not_oriented'] == 1 and c['not_oriented_waiting_for_initialisation'] == 0
    assert c['not_oriented_too_few_known_points'] == 1
    counts.oriented_since(block, 2)      # counted out once only
    assert diag.counts()['keyframes_not_oriented'] == 1


def test_at_the_end_each_keyframe_still_not_oriented_is_counted_under_its_final_reason():
    """The flight report's per-keyframe reasons (io/flight_verdict AT_END_PREFIX): the reason a keyframe was
    counted under in flight, or given up after being oriented when it never was counted not oriented."""
    diag = DiagnosticsLog()
    counts = NotOrientedCounts(diag)
    counts.count('too few known points (3 of 30)', 100)
    counts.count('waiting for initialisation', 200)
    kfs = [SimpleNamespace(stamp_ns=100, map_T_cam=None), SimpleNamespace(stamp_ns=200, map_T_cam=object()),
           SimpleNamespace(stamp_ns=300, map_T_cam=None)]    # 200 oriented later; 300 oriented once, given up
    counts.at_end(SimpleNamespace(keyframes=lambda: kfs))
    c = diag.counts()
    assert c['not_oriented_at_end_too_few_known_points'] == 1
    assert c['not_oriented_at_end_given_up_after_being_oriented'] == 1
    assert 'not_oriented_at_end_waiting_for_initialisation' not in c
