"""The keyframe accounting (io/flight_verdict.keyframe_accounting) tells the truth: taken, oriented, not oriented,
with reasons that add up to the keyframes not oriented, on the console line, in report.json and the report."""

from photogram_ros.io.flight_verdict import keyframe_accounting, keyframes_line

# run.json counts of `replay` of seneca_part's every other photo (21 photos), 17 oriented at the end: the
# adjuster's in-flight reasons count 13 keyframes, 9 of which segment joins and the end's second chance oriented.
SENECA_EVERY_OTHER = {
    'tracker': {'frames_received': 21, 'frames_tracked': 21, 'keyframes': 21},
    'bundle': {'fixes': 21, 'keyframes_received': 21, 'keyframes_not_oriented': 11,
               'not_oriented_waiting_for_initialisation': 2, 'images': 21, 'keyframes_oriented': 10,
               'problems': 25, 'not_oriented_too_few_known_points': 9, 'keyframes_unplaced': 2,
               'keyframes_joined_from_a_segment': 8, 'keyframes_oriented_at_end': 2, 'full_adjustments': 1}}


def test_in_flight_reasons_of_keyframes_oriented_later_are_not_counted_as_not_oriented():
    acc = keyframe_accounting(SENECA_EVERY_OTHER, 17)
    assert (acc['keyframes_taken'], acc['keyframes_oriented'], acc['keyframes_not_oriented']) == (21, 17, 4)
    assert sum(acc['keyframes_not_oriented_by_reason'].values()) == 4, acc
    assert acc['keyframes_not_oriented_by_reason'] == {'not oriented by the bundle adjuster': 4}
    assert acc['keyframes_not_oriented_in_flight'] == 13
    assert acc['keyframes_not_oriented_in_flight_by_reason'] == {
        'not oriented: waiting for initialisation': 2, 'not oriented: too few known points': 9,
        'given up: before an early break (a line too short for its GNSS)': 2}
    assert acc['keyframes_oriented_after_the_window_gave_up'] == 9
    line = keyframes_line(acc)
    assert line == ('keyframes: 21 taken, 17 oriented, 4 not oriented: 4 by the bundle adjuster (in flight 13 were '
                    'not oriented, for: 2 waiting for initialisation, 9 too few known points, 2 given up before an '
                    'early break (a line too short for its GNSS); 9 of them oriented later by segment joins and the '
                    "final adjustment's second chance)"), line


def test_the_adjusters_end_of_flight_reasons_are_each_keyframes_final_one():
    counts = {'tracker': dict(SENECA_EVERY_OTHER['tracker'], keyframes=22),
              'bundle': dict(SENECA_EVERY_OTHER['bundle'], not_oriented_at_end_too_few_known_points=3,
                             not_oriented_at_end_given_up_after_being_oriented=1)}
    acc = keyframe_accounting(counts, 17)
    assert acc['keyframes_not_oriented'] == 5
    assert acc['keyframes_not_oriented_by_reason'] == {
        'never reached the bundle adjuster': 1, 'not oriented: too few known points': 3,
        'given up: before an early break (a line too short for its GNSS)': 1}, acc
    assert 'keyframes_oriented_after_the_window_gave_up' not in acc
    assert keyframes_line(acc) == ('keyframes: 22 taken, 17 oriented, 5 not oriented: 1 never reached the bundle '
                                   'adjuster; 3 too few known points; 1 given up before an early break (a line '
                                   'too short for its GNSS)')


def test_in_flight_reasons_that_add_up_are_the_reasons_and_the_rest_is_unaccounted():
    counts = {'tracker': {'keyframes': 10},
              'bundle': {'keyframes_received': 10, 'keyframes_oriented': 6, 'keyframes_not_oriented': 3,
                         'not_oriented_too_few_known_points': 3, 'keyframes_failed': 1}}
    acc = keyframe_accounting(counts, 5)
    assert acc['keyframes_not_oriented'] == 5
    assert acc['keyframes_not_oriented_by_reason'] == {
        'failed in the bundle adjuster (an error, see the problems)': 1, 'not oriented: too few known points': 3,
        'oriented in flight, no georeferenced pose in the map': 1}, acc
    assert keyframe_accounting(counts, 7)['keyframes_not_oriented_by_reason'] == {
        'failed in the bundle adjuster (an error, see the problems)': 1, 'not oriented by the bundle adjuster': 2}
    few = keyframe_accounting({'tracker': {'keyframes': 10}, 'bundle': {'keyframes_received': 10,
                                                                        'keyframes_oriented': 8}}, 8)
    assert few['keyframes_not_oriented_by_reason'] == {'unaccounted (no node counted why)': 2}
    assert keyframes_line(keyframe_accounting({'tracker': {'keyframes': 3}}, 3)) == \
        'keyframes: 3 taken, 3 oriented, 0 not oriented'


def test_end_of_flight_reasons_of_a_block_without_georeference():
    """The adjuster oriented 8 of 10 but the map has no georeferenced pose: those 8 are named, not unaccounted."""
    counts = {'tracker': {'keyframes': 10},
              'bundle': {'keyframes_received': 10, 'keyframes_oriented': 8, 'not_oriented_at_end_no_fix': 2}}
    acc = keyframe_accounting(counts, 0)
    assert acc['keyframes_not_oriented_by_reason'] == {
        'not oriented: no fix': 2, 'oriented by the bundle adjuster, no georeferenced pose in the map': 8}, acc
