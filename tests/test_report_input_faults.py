"""The flight report names the input faults the nodes counted (io/flight_report.input_faults)."""
from photogram_ros.io.flight_report import input_faults, shed_in_flight


def test_only_the_faults_that_happened_are_named():
    tracker = {'stamps_back': 4, 'stamps_repeated': 0, 'keyframes': 12}
    mavlink = {'link_silences': 1, 'link_longest_silence_s': 20.4, 'link_clock_back': 0, 'connected': True}
    assert input_faults(tracker, mavlink) == {'frames_dropped_stamp_back': 4, 'link_silences': 1,
                                              'link_longest_silence_s': 20.4}


def test_a_clean_flight_has_no_input_faults_and_odd_values_are_ignored():
    assert input_faults({}, {}) == {}
    assert input_faults({'stamps_back': 'n/a', 'stamps_repeated': True}, {'link_silences': None}) == {}


def test_what_was_shed_in_flight_is_named_with_its_count():
    shed = shed_in_flight({'keyframes_shed': 12, 'pairs_shed_late': 30, 'pairs_done': 100}, {'ortho_batches_deferred': 0})
    assert shed == {'keyframes whose stereo pairs were shed': 12, 'stereo pairs shed for lag': 30}
    assert shed_in_flight({}, {}) == {}
