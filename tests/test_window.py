"""Sliding-window selection: bounded problem size as the flight grows, and its geometry."""

import numpy as np

from photogram_ros.core.window import select_window


def _strip(n_kf, per_kf=300, overlap=0.8, line_len=50):
    """Keyframes along lines; each sees a run of point ids, consecutive ones share `overlap`."""
    step = int(per_kf * (1 - overlap))
    kf_tracks, track_kfs = {}, {}
    for k in range(n_kf):
        line, j = divmod(k, line_len)
        start = line * 100_000 + j * step
        ids = np.arange(start, start + per_kf)
        if line > 0:   # side overlap: the neighbouring line saw a third of these points
            ids = np.concatenate([ids, np.arange((line - 1) * 100_000 + j * step, (line - 1) * 100_000 + j * step + 100)])
        kf_tracks[k] = ids
        for t in ids.tolist():
            track_kfs.setdefault(t, []).append(k)
    return kf_tracks, track_kfs


def test_window_frees_the_newest_and_fixes_the_sharing_keyframes():
    kf_tracks, track_kfs = _strip(30)
    sel = select_window(list(range(30)), 10, kf_tracks, track_kfs)
    assert sel.free_kfs == list(range(20, 30))
    # Keyframes 15..19 share points with 20..24 (80 % overlap, 5 keyframes deep); older ones do not.
    assert sel.fixed_kfs == list(range(15, 20))
    assert set(sel.track_ids.tolist()) == set(np.concatenate([kf_tracks[k] for k in range(20, 30)]).tolist())


def test_window_size_stays_bounded_as_the_flight_grows():
    kf_tracks, track_kfs = _strip(500)
    sizes = []
    for n in (60, 200, 500):
        sel = select_window(list(range(n)), 10, kf_tracks, track_kfs, max_fixed=30)
        sizes.append((len(sel.free_kfs), len(sel.fixed_kfs), len(sel.track_ids)))
    print('free, fixed, points at 60/200/500 keyframes:', sizes)
    # The same work at keyframe 60 and 500: ten free keyframes, a capped fixed set, the same points.
    assert all(s[0] == 10 and s[1] <= 30 and s[2] == sizes[0][2] for s in sizes)


def test_window_cap_keeps_the_keyframes_sharing_most_points():
    kf_tracks, track_kfs = _strip(120)
    sel = select_window(list(range(120)), 10, kf_tracks, track_kfs, max_fixed=3)
    window = set(np.concatenate([kf_tracks[k] for k in range(110, 120)]).tolist())
    shared = {k: len(window & set(kf_tracks[k].tolist())) for k in range(110)}
    best = sorted(shared.values())[-3]
    assert len(sel.fixed_kfs) == 3 and all(shared[k] >= best for k in sel.fixed_kfs)
