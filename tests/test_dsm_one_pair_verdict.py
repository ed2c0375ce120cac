"""A survey flown with one stereo pair per spot (60 % forward overlap, lines that barely share a band) leaves
two agreeing pairs over a few percent of its DSM: the verdict weighs what one pair measured against the
interpolated heights (export.json dsm.one_pair_check) before it calls the flight failed."""

from __future__ import annotations

import json

import pytest


def _acc():
    from photogram_ros.io.flight_verdict import keyframe_accounting
    return keyframe_accounting({'tracker': {'keyframes': 41}, 'bundle': {
        'keyframes_received': 41, 'keyframes_oriented': 38, 'keyframes_not_oriented': 3}}, 38)


def test_one_pair_agreeing_with_the_interpolation_makes_a_thin_dsm_a_warning():
    from photogram_ros.io.flight_verdict import mapping_verdict
    # seneca_part's replay map (export of its map_final): 8.2 % confirmed, 48 % more one pair, 0.14 m median.
    one = {'share': 0.48, 'median_abs_dz_m': 0.14, 'p90_abs_dz_m': 0.90, 'tolerance_m': 0.707}
    v = mapping_verdict(_acc(), True, 0.096, True, None, one)
    assert v['mapped'] and not v['failures']
    assert '48.0 %' in v['warnings'][0] and '0.14 m from the interpolated heights' in v['warnings'][0]
    # Without that evidence, or when one pair contradicts the interpolation, the thin DSM fails the flight.
    bare = mapping_verdict(_acc(), True, 0.096, True)
    assert not bare['mapped'] and 'nearly empty' in bare['failures'][0]
    off = mapping_verdict(_acc(), True, 0.096, True, None, {**one, 'median_abs_dz_m': 1.2})
    assert not off['mapped'] and 'not what stereo saw' in off['failures'][0]
    # Too little of either: failed.
    few = mapping_verdict(_acc(), True, 0.02, True, None, {**one, 'share': 0.03})
    assert not few['mapped']


def test_the_evidence_is_read_from_the_export_json_beside_the_dsm(tmp_path):
    from photogram_ros.io.flight_verdict import dsm_one_pair_evidence
    dsm = tmp_path / 'dsm.tif'
    assert dsm_one_pair_evidence(dsm) is None          # no export.json
    (tmp_path / 'export.json').write_text(json.dumps({'dsm': {
        'max_spread_m': 0.707, 'camera_hull': {'filled_one_pair': 0.48},
        'one_pair_check': {'cells': 219287, 'median_abs_dz_m': 0.142, 'p90_abs_dz_m': 0.902, 'bias_m': -0.015}}}))
    ev = dsm_one_pair_evidence(dsm)
    assert ev == pytest.approx({'share': 0.48, 'median_abs_dz_m': 0.142, 'p90_abs_dz_m': 0.902, 'tolerance_m': 0.707})
    (tmp_path / 'export.json').write_text('{not json')
    assert dsm_one_pair_evidence(dsm) is None
