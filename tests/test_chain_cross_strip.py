"""Tie points across strips for keyframes KLT carried (core/cross_strip.py through core/tracker.py), on the
simulator's tiny survey rendered at 320 x 240 (test_tracker.SimFrames): two 60 m lines flown at 2 frames a second,
close enough for KLT, with the true positions as GNSS fixes. The second line's keyframes overlap the first's
footprints: with the cross-strip logic they share track ids with them (the same ground points); a keyframe no
other strip overlaps gets no SIFT features unless it is one the chain stores."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from photogram_ros.core.cross_strip import CrossStrip, CrossStripParams, adopt_track_ids
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.core.keyframes import ChainStore
from photogram_ros.core.tracker import TrackerParams

OFF = dict(cross_strip_store_every=0, cross_strip_min_back=0)   # the defaults
ON = dict(cross_strip_store_every=3, cross_strip_min_back=6)
LINE_1_END_S, LINE_2_START_S = 12.5, 22.0    # the tiny preset's first line, its turn, its second line


@pytest.fixture(scope='module')
def two_lines():
    from test_tracker import SimFrames
    return SimFrames(36.0)


def _fixes(frames):
    origin = LocalFrame(47.0, 8.0, 500.0)
    out = []
    for stamp, T in sorted(frames.poses.items()):
        lat, lon, h = origin.enu_to_geodetic(T[:3, 3])
        out.append(GnssFix(float(lat), float(lon), float(h), np.eye(3) * 0.01, stamp, 2))
    return out


def _strips(frames, kfs):
    t0 = min(frames.poses)
    t = {kf.index: (kf.stamp_ns - t0) * 1e-9 for kf in kfs}
    a = [kf for kf in kfs if t[kf.index] < LINE_1_END_S]
    b = [kf for kf in kfs if t[kf.index] > LINE_2_START_S]
    return a, b


def _crossing(frames, kfs):
    a, b = _strips(frames, kfs)
    ids_a = np.unique(np.concatenate([k.observations['track_id'] for k in a]))
    ids_b = np.unique(np.concatenate([k.observations['track_id'] for k in b]))
    return np.intersect1d(ids_a, ids_b), a, b


@pytest.fixture(scope='module')
def runs(two_lines):
    fixes = _fixes(two_lines)
    return {name: two_lines.run(TrackerParams(**values), fixes=fixes)
            for name, values in (('off', OFF), ('cross', ON))}


def test_second_line_keyframes_share_track_ids_with_the_first(two_lines, runs):
    tr, kfs = runs['cross']
    tr_off, kfs_off = runs['off']
    crossing, a, b = _crossing(two_lines, kfs)
    crossing_off, _, _ = _crossing(two_lines, kfs_off)
    assert tr.stats.breaks == 0 and tr_off.stats.breaks == 0     # KLT carried every keyframe
    # Which keyframes of the second line see a track of the first.
    linked = [k for k in b if np.isin(k.observations['track_id'], crossing).sum() >= 15]
    linked_off = [k for k in _strips(two_lines, kfs_off)[1]
                  if np.isin(k.observations['track_id'], crossing_off).sum() >= 15]
    print(f'{len(a)} + {len(b)} keyframes on the lines; ids crossing: {len(crossing)} (off: {len(crossing_off)}); '
          f'second-line keyframes with >= 15 of them: {len(linked)} (off: {len(linked_off)}); '
          f'stored {tr.cross.stored}, revisits {tr.cross.revisits}')
    every = TrackerParams().cross_strip_revisit_every
    assert len(b) // (2 * every) <= tr.cross.revisits <= -(-len(kfs) // every)
    assert len(crossing) >= 100 and len(linked) >= len(b) // 2
    assert len(linked) >= len(linked_off) + 2
    # The shared ids are the same ground points: their observations agree with the truth.
    sub = [replace(k, observations=k.observations[np.isin(k.observations['track_id'], crossing)]) for k in kfs]
    err = two_lines.track_errors([k for k in sub if len(k.observations)])
    assert len(err) >= 100 and float(np.median(err)) < 1.0


def test_a_keyframe_no_other_strip_overlaps_gets_no_sift(two_lines, runs):
    tr, kfs = runs['cross']
    a, _ = _strips(two_lines, kfs)
    # On the first line no earlier strip exists: only every store_every-th keyframe (and the first) has features.
    store = ON['cross_strip_store_every']
    in_chain = set(tr.chain.keys)
    first_line = [k.index for k in a]
    assert [i for i in first_line if i in in_chain] == [i for i in first_line if i % store == 0]
    # With the logic off, only the first keyframe has any.
    tr_off, _ = runs['off']
    assert tr_off.chain.keys == [0] and tr_off.cross.stored == tr_off.cross.revisits == 0


def test_plan_matches_only_older_overlapping_keyframes():
    cs = CrossStrip(CrossStripParams(cross_strip_store_every=0, cross_strip_min_back=6, cross_strip_reach=0.75))
    here = lambda x, y: (np.array([x, y, 0.0]), 1.0)   # noqa: E731
    # Keyframes 0-9 along a line, 10 m apart at 75 % front overlap: a 40 m footprint.
    chain = ChainStore(10)
    for k in range(10):
        assert cs.plan(k, here(10.0 * k, 0.0), 0.75, False, chain, []) is None
    assert cs.footprint_m() == pytest.approx(40.0)
    # Chain entries: keyframe 1 on a strip 25 m aside, keyframe 8 (recent), keyframe 2 31 m aside.
    at = {1: (20.0, 25.0), 8: (90.0, 0.0), 2: (20.0, 31.0)}
    for k in at:
        chain.add(k, k, np.zeros((0, 2)), np.zeros((0, 128)), np.zeros(0))
    chain.locate(lambda stamp: here(*at[stamp]))
    # Keyframe 10 back over x = 20 m: keyframe 1 (9 older, 25 m off) is another strip's.
    assert cs.plan(10, here(20.0, 0.0), 0.75, False, chain, [0, 1, 2]) == [0]
    # Only the recent chain (8: 2 keyframes back), or an old one beyond reach (31 m > 0.75 x 40 m): no features.
    assert cs.plan(11, here(20.0, 0.0), 0.75, False, chain, [1, 2]) is None
    assert cs.revisits == 1


def test_features_adopt_the_klt_track_they_sit_on():
    feat_uv = np.array([[10.0, 10.0], [10.5, 10.0], [50.0, 50.0], [80.0, 80.0]])
    feat_ids = np.array([-1, -1, 7, -1], np.int64)
    pts = np.array([[10.2, 10.0], [50.0, 50.0], [81.0, 80.0]], np.float32)
    ids = np.array([100, 7, 300], np.uint32)
    assert adopt_track_ids(feat_uv, feat_ids, pts, ids, 1.5) == 2
    # The nearest feature takes track 100; track 7 is the third feature's already; track 300 is 1 px away.
    assert feat_ids.tolist() == [100, -1, 7, 300]
