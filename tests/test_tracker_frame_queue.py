"""core/frame_queue.py: the tracker's queue drops only frames the chain can spare (redundant by GNSS), never one
whose removal leaves a gap wider than the keyframe spacing allows; without GNSS it drops the oldest."""

import math

import numpy as np

from photogram_ros.core.frame_queue import FrameQueue
from photogram_ros.core.gnss_fix import GnssFix

M_PER_DEG_LAT = 6371008.8 * math.pi / 180.0


def _fixes(north_m_by_stamp: dict):
    """fix_of(stamp) for frames flying north: stamp -> metres north of (45 N, 7 E)."""
    def fix_of(stamp_ns):
        n = north_m_by_stamp.get(stamp_ns)
        if n is None:
            return None
        return GnssFix(45.0 + n / M_PER_DEG_LAT, 7.0, 100.0, np.eye(3) * 0.01, int(stamp_ns))
    return fix_of


def test_photo_rate_frames_are_all_needed_and_kept_past_the_queue_size():
    # Every photo a keyframe, 30 m apart (seneca's 60 % overlap): removing any leaves a 60 m gap > the spacing.
    north = {k: 30.0 * k for k in range(10)}
    q = FrameQueue(size=2, max_bytes=10**9)
    dropped = []
    for k in range(10):
        dropped += q.push(f'photo{k}', k, 1000, _fixes(north), spacing_m=0.5 * 30.0)
    assert dropped == [] and len(q) == 10 and q.kept_over_size == 8


def test_the_redundant_frame_goes_first_and_the_reason_says_so():
    # Frames at 0, 10, 11, 20, 30 m; keyframes 20 m apart (a drop keeps gaps within 10 m): the frame at 10 m or
    # 11 m is redundant (its neighbours 11 m or 10 m apart... the smallest gap left: removing 10 m leaves 0->11).
    north = {0: 0.0, 1: 10.0, 2: 11.0, 3: 20.0, 4: 30.0}
    q = FrameQueue(size=3, max_bytes=10**9)
    q.push('f0', 0, 1, _fixes(north), 10.0)
    q.popleft()                                  # the tracker took f0
    out = []
    for k in (1, 2, 3, 4):
        out += q.push(f'f{k}', k, 1, _fixes(north), 12.0)
    assert [d.item for d in out] == ['f2'], out   # f1..f3 waiting + f4: removing f2 leaves 10 -> 20: 10 m
    assert out[0].reason == 'redundant' and abs(out[0].gap_m - 10.0) < 0.01
    assert 'redundant' in out[0].message and '10.0 m' in out[0].message
    assert list(q) == ['f1', 'f3', 'f4']


def test_a_frame_far_from_the_last_kept_one_is_never_dropped():
    # The tracker took the frame at 0 m; waiting at 40 m (far: needed), 41 m, 42 m; new at 43 m. Keyframe spacing
    # 10 m: only frames between 40 m and 43 m can go, never the one at 40 m (removing it leaves 0 -> 41 m).
    north = {0: 0.0, 1: 40.0, 2: 41.0, 3: 42.0, 4: 43.0}
    q = FrameQueue(size=1, max_bytes=10**9)
    q.push('f0', 0, 1, _fixes(north), 10.0)
    q.popleft()
    out = []
    for k in (1, 2, 3, 4):
        out += q.push(f'f{k}', k, 1, _fixes(north), 10.0)
    assert 'f1' not in [d.item for d in out] and 'f4' in list(q)
    assert list(q)[0] == 'f1' and len(out) == 2 and all(d.reason == 'redundant' for d in out)


def test_without_gnss_the_oldest_waiting_frame_goes():
    q = FrameQueue(size=2, max_bytes=10**9)
    out = []
    for k in range(6):
        out += q.push(f'f{k}', k, 1, lambda t: None, 10.0)
    assert list(q) == ['f4', 'f5'] and [d.item for d in out] == ['f0', 'f1', 'f2', 'f3']
    assert all(d.reason == 'no_position' for d in out)


def test_needed_frames_are_kept_until_the_memory_bound_then_the_most_redundant_goes():
    north = {0: 0.0, 1: 30.0, 2: 60.0, 3: 80.0, 4: 120.0}
    q = FrameQueue(size=1, max_bytes=3500)
    q.push('f0', 0, 1000, _fixes(north), 15.0)
    q.popleft()                                  # the tracker took f0
    out = []
    for k in range(1, 5):
        out += q.push(f'f{k}', k, 1000, _fixes(north), 15.0)
    # Every gap a drop would leave is beyond 15 m: kept until f1..f4 hold 4000 B > 3500 B; then the smallest gap
    # left goes: f2 (30 -> 80 m: 50 m; f1 would leave 0 -> 60 m, f3 60 -> 120 m).
    assert [d.item for d in out] == ['f2'] and out[0].reason == 'over_memory' and q.nbytes == 3000
    assert 'may need it' in out[0].message and list(q) == ['f1', 'f3', 'f4']


def test_no_keyframe_spacing_yet_keeps_every_positioned_frame():
    north = {k: 1.0 * k for k in range(5)}
    q = FrameQueue(size=2, max_bytes=10**9)
    out = []
    for k in range(5):
        out += q.push(f'f{k}', k, 1, _fixes(north), None)
    assert out == [] and len(q) == 5
