"""The verdict weighs the products against what the oriented photos saw (export.json dsm.footprint: the camera
centres' hull widened by a quarter of the flying height), and says how much of it one unconfirmed stereo pair
measured: a DSM that is a patch of the block, or rests on one pair, is not a clean 'mapped'."""

from __future__ import annotations

import json

import pytest


def _acc():
    from photogram_ros.io.flight_verdict import keyframe_accounting
    return keyframe_accounting({'tracker': {'keyframes': 21}, 'bundle': {
        'keyframes_received': 21, 'keyframes_oriented': 17, 'keyframes_not_oriented': 4}}, 17)


def test_a_patch_of_the_footprint_is_a_warning_with_its_numbers():
    from photogram_ros.io.flight_verdict import MIN_FOOTPRINT_SHARE, mapping_verdict
    # seneca every other photo, exported with one-pair cells: 8.4 % of the footprint measured, 8.3 % by one pair.
    foot = {'cells': 501328, 'measured': 0.0836, 'measured_one_pair': 0.0831, 'valid': 1.0}
    v = mapping_verdict(_acc(), True, 0.62, True, footprint=foot)
    assert v['mapped'] and v['dsm_footprint'] == foot
    patch = [w for w in v['warnings'] if 'cover little of what the photos saw' in w]
    assert len(patch) == 1 and '8.4 %' in patch[0] and '8.3 %' in patch[0]
    assert len(v['warnings']) == 1 and 'most of what stereo measured rests on one pair' in patch[0]
    # Just over the threshold with confirmed heights: no footprint warning.
    fine = mapping_verdict(_acc(), True, 0.9, True,
                           footprint={**foot, 'measured': MIN_FOOTPRINT_SHARE + 0.01, 'measured_one_pair': 0.1})
    assert fine['mapped'] and not fine['warnings']
    # Interpolated cells that one pair's heights check count as seen (seneca's full replay: 30.5 + 19.8 %).
    seen = mapping_verdict(_acc(), True, 0.9, True, footprint={**foot, 'measured': 0.305, 'filled_one_pair': 0.198,
                                                               'measured_one_pair': 0.1})
    assert not seen['warnings']


def test_one_pair_heights_over_the_footprint_are_not_an_empty_dsm():
    """seneca's full replay failed with 'the DSM is nearly empty' (0.0 % confirmed over the mapped area) while
    one pair measured half of the camera hull: with those cells in band 2 (1) the DSM's measured share counts
    them, and the verdict warns that one pair carries it."""
    from photogram_ros.io.flight_verdict import mapping_verdict
    foot = {'cells': 700000, 'measured': 0.62, 'measured_one_pair': 0.61, 'valid': 1.0}
    v = mapping_verdict(_acc(), True, 0.71, True, footprint=foot)
    assert v['mapped'] and not v['failures']
    assert len(v['warnings']) == 1 and 'rests on one stereo pair' in v['warnings'][0]
    assert '62.0 %' in v['warnings'][0] and '61.0 %' in v['warnings'][0]
    # Without the footprint (an older export.json) the verdict is as it was.
    assert mapping_verdict(_acc(), True, 0.71, True) == {'mapped': True, 'failures': [], 'warnings': [],
                                                         'dsm_valid_share': 0.71}


def test_the_footprint_is_read_from_the_export_json_beside_the_dsm(tmp_path):
    from photogram_ros.io.flight_verdict import dsm_footprint_cover
    dsm = tmp_path / 'dsm.tif'
    assert dsm_footprint_cover(dsm) is None and dsm_footprint_cover(None) is None
    (tmp_path / 'export.json').write_text(json.dumps({'dsm': {'footprint': {
        'cells': 10, 'valid': 1.0, 'measured': 0.5, 'measured_one_pair': 0.2, 'filled': 0.5}}}))
    assert dsm_footprint_cover(dsm) == pytest.approx({'cells': 10, 'measured': 0.5, 'measured_one_pair': 0.2,
                                                      'valid': 1.0})
    (tmp_path / 'export.json').write_text(json.dumps({'dsm': {}}))
    assert dsm_footprint_cover(dsm) is None
