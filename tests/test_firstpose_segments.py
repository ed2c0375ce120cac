"""What a segment's join says about the tracker's ids it shares with the block (core/at_segments.py `last_fit`,
the stage's `segment_join_ties`), and the heading a straight line's fixes give (core/incremental.py
`line_heading_sigma_rad`, the provisional georeference's test)."""

from __future__ import annotations

import numpy as np

from test_chain_segments import K_BREAK, K_CHAIN, N_KEYFRAMES, _chained, flight  # noqa: F401  (fixture)

from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions, line_heading_sigma_rad


def _joins(sk, recs):
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m)), origin=sk.origin)
    notes = []
    for r in recs:
        at.add_keyframe(r)
        if at.segments.current is not None:
            notes.append(dict(at.segments.last_fit))
    return at.segments.joins_made(), notes


def test_a_join_through_tie_points_counts_them_and_a_gnss_join_says_why(flight):  # noqa: F811
    sk = flight
    chained, _, n_cont = _chained(sk.records[:N_KEYFRAMES], K_BREAK, K_CHAIN)
    joins, _ = _joins(sk, chained)
    assert joins[0]['through'] == 'ties' and joins[0]['why'] == ''
    assert joins[0]['shared_points'] >= joins[0]['inliers'] >= 8 and joins[0]['shared_observed'] > 0
    cut, _, _ = _chained(sk.records[:N_KEYFRAMES], K_BREAK, N_KEYFRAMES)
    joins, notes = _joins(sk, cut)
    print(f'links cut: {notes[-1] if notes else None}, joins {joins}')
    # Every track renamed after the break: nothing shared, and the note says so while the segment waits.
    assert notes and all(n['shared_observed'] == 0 and n['shared_points'] == 0 for n in notes)
    assert all('0 shared tie points' in n['why'] or 'no oriented' in n['why'] for n in notes)
    assert all(j['through'] != 'ties' and j['why'] for j in joins)


def test_the_line_heading_sigma_is_the_fix_sigma_over_the_spread_and_its_count():
    covs = [np.diag([25.0, 25.0, 100.0])] * 6
    # 6 keyframes 16 m apart (the simulated survey's): RMS spread 27.3 m along the line, 5 m fixes: 4.3 deg.
    C = np.arange(6) * 16.0
    s = float(np.std(C))
    assert abs(np.degrees(line_heading_sigma_rad(covs, s)) - np.degrees(5.0 / (s * np.sqrt(6)))) < 1e-9
    assert 4.0 < np.degrees(line_heading_sigma_rad(covs, s)) < 4.5
    assert line_heading_sigma_rad([], 10.0) == np.inf and line_heading_sigma_rad(covs, 0.0) == np.inf
