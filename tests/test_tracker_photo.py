"""The tracker on photo-rate input: the simulator's survey line shot every 2.5 s instead of
every 0.5 s, so that a frame moves far beyond KLT's reach. Descriptor matching against the recent
keyframes must carry the track ids on (points seen by 3+ keyframes) at sub-pixel accuracy against the
true terrain (the track truth of tests/test_tracker.py)."""

from __future__ import annotations

import numpy as np
import pytest

from test_tracker import SimFrames


@pytest.fixture(scope='module')
def photo_line():
    return SimFrames(40.0, fps=0.4)


def test_photo_rate_frames_are_bridged_with_tracks_over_three_keyframes(photo_line):
    from photogram_ros.core.tracker import TrackerParams
    tr, kfs = photo_line.run(TrackerParams(klt_min_share=0.2))
    s = tr.stats
    ids = np.concatenate([k.observations['track_id'] for k in kfs])
    _, counts = np.unique(ids, return_counts=True)
    e = photo_line.track_errors(kfs)
    print(f'{s.frames} frames, {s.keyframes} keyframes, {s.breaks} breaks ({s.bridged} bridged); tracks in 3+ '
          f'keyframes {int(np.sum(counts >= 3))}, 4+ {int(np.sum(counts >= 4))}; errors median {np.median(e):.3f} px, '
          f'> 2 px {np.mean(e > 2) * 100:.2f} %')
    assert s.keyframes >= 0.8 * s.frames and s.keyframes >= 10
    # KLT (4 pyramid levels) still reaches most of these frames; where it does not, descriptors bridge.
    assert s.breaks >= 3 and s.bridged == s.breaks, 'every break of this line is bridged by descriptor matching'
    # Every keyframe shares tracks with its predecessor: the bundle adjuster can chain them.
    for a, b in zip(kfs[:-1], kfs[1:]):
        assert len(np.intersect1d(a.observations['track_id'], b.observations['track_id'])) >= 30
    assert np.sum(counts >= 3) >= 30 * len(kfs)
    assert np.median(e) <= 0.5 and np.mean(e > 2.0) <= 0.02
