"""The chain in flight (core/tracker.py with core/keyframes.ChainStore): each new keyframe is matched by
descriptors against the earlier keyframes whose footprints it overlaps by GNSS, across strips too, and takes
the track ids they carry, so the adjuster resects it from points it already knows.

Fast: the footprint candidates of a new keyframe (photo_matching.earlier_candidates: triangulate's
candidate_order for the newest photo), and the ids linked across strips on a synthetic two-strip survey at
photo rate (every frame beyond KLT's reach). Slow: `replay` of seneca_part (41 near-infrared photos of a
fixed wing) against what `triangulate` orients (bench/results/inflight_chain_*.jsonl)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from photogram_ros.core import photo_matching as pm
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.gnss_fix import STATUS_FIX, GnssFix
from photogram_ros.core.tracker import Tracker, TrackerParams

ROOT = Path(__file__).resolve().parents[1]


def test_footprint_candidates_are_triangulates_and_reach_across_strips():
    # Two strips 60 m apart, photos every 30 m: the new photo starts strip 2 above strip 1's first photos.
    strip1 = np.array([[x, 0.0, 100.0] for x in np.arange(0.0, 301.0, 30.0)])
    strip2 = np.array([[x, 60.0, 100.0] for x in np.arange(300.0, 59.0, -30.0)])
    earlier = np.vstack([strip1, strip2])
    new = np.array([30.0, 60.0, 100.0])
    order, first = pm.earlier_candidates(earlier, new, neighbours=4, sigma_h_m=0.0)
    chosen = set(order[:first].tolist())
    # Its nearest: strip 2's previous photo (30 m) and strip 1's photos below it (60-67 m), not the far end.
    assert {len(strip1) + len(strip2) - 1, 1} <= chosen
    assert 0 in chosen or 2 in chosen
    assert not chosen & set(range(5, len(strip1)))
    # The same row as triangulate's pair planning of the whole block gives the newest photo.
    o_all, f_all = pm.candidate_order(np.vstack([earlier, new]), 4, 0.0)
    assert list(order[:first]) == list(o_all[-1, :f_all[-1]])
    # A poor fix widens the reach (two geotags' uncertainty), as in triangulate.
    _, first_poor = pm.earlier_candidates(earlier, new, neighbours=4, sigma_h_m=10.0)
    assert first_poor > first


def _ground(size_px: int, seed: int = 3) -> np.ndarray:
    """A textured flat ground (multi-scale noise), uint8."""
    rng = np.random.default_rng(seed)
    g = np.zeros((size_px, size_px), np.float32)
    for s, w in ((1.5, 1.0), (4.0, 2.0), (12.0, 3.0)):
        g += w * cv2.GaussianBlur(rng.normal(0, 1, (size_px, size_px)).astype(np.float32), (0, 0), s)
    g = (g - g.mean()) / g.std()
    return np.clip(128 + 40 * g, 0, 255).astype(np.uint8)


def _two_strip_survey():
    """Nadir photos of a flat ground over two strips (60 % forward overlap, strip 2 flown back over strip 1
    with 40 % side overlap), 7 s apart, with GNSS fixes at the photo centres (0.1 m per px, 50 m up)."""
    ground = _ground(2200)
    w, h, f, gsd = 480, 360, 500.0, 0.1
    camera = PinholeCamera(w, h, f, f, (w - 1) / 2, (h - 1) / 2)
    xs = np.arange(300, 1900, int(0.4 * w))
    centres = [(x, 600) for x in xs] + [(x, 600 + int(0.6 * h)) for x in xs[::-1]]
    origin = LocalFrame(47.0, 8.0, 500.0)
    shots = []
    for k, (cx, cy) in enumerate(centres):
        img = ground[cy - h // 2: cy - h // 2 + h, cx - w // 2: cx - w // 2 + w]
        lat, lon, alt = origin.enu_to_geodetic(np.array([[cx * gsd, -cy * gsd, 550.0 - 500.0 + 50.0]]))
        stamp = int(1e18) + k * 7_000_000_000
        fix = GnssFix(float(np.ravel(lat)[0]), float(np.ravel(lon)[0]), float(np.ravel(alt)[0]),
                      np.diag([0.5, 0.5, 1.0]), stamp, STATUS_FIX)
        shots.append((stamp, np.ascontiguousarray(img), fix))
    return camera, shots, len(xs)


def _fly(camera, shots, params):
    tr = Tracker(camera, params)
    kfs = []
    for stamp, img, fix in shots:
        tr.add_fix(fix)
        kfs += tr.process(img, stamp)
    kfs += tr.flush()
    return tr, kfs


def test_keyframes_share_track_ids_across_strips_and_the_chain_stays_small():
    camera, shots, per_strip = _two_strip_survey()
    p = TrackerParams(match_features=1500, chain_features=600)
    tr, kfs = _fly(camera, shots, p)
    assert len(kfs) == len(shots), 'photo rate: every photo a keyframe'
    ids = [set(k.observations['track_id'].tolist()) for k in kfs]
    # The last photos of strip 2 lie above strip 1's first ones, flown long before (beyond the last
    # match_keyframes keyframes): they must share track ids with them.
    old = set().union(*ids[:2])
    cross = [len(ids[i] & old) for i in range(len(kfs) - 2, len(kfs))]
    assert all(n >= 15 for n in cross), cross
    assert len(kfs) - 2 - 1 > p.match_keyframes
    # Without the chain, a break only looks at the last keyframes: no id reaches back across the turn.
    off = TrackerParams(match_features=1500, chain_features=600, chain_neighbours=0)
    _, kfs0 = _fly(camera, shots, off)
    ids0 = [set(k.observations['track_id'].tolist()) for k in kfs0]
    old0 = set().union(*ids0[:2])
    assert max(len(ids0[i] & old0) for i in range(len(kfs0) - 2, len(kfs0))) < min(cross) / 3
    # Bounded memory: what the chain keeps per keyframe (uint8 descriptors, capped features).
    per_kf = tr.chain.nbytes() / len(tr.chain)
    published = max(len(k.observations) for k in kfs)
    assert per_kf <= p.chain_features * (128 + 8 + 4) + 4 * published + 100
    assert all(len(d) <= p.chain_features for d in tr.chain.desc)
    assert tr.stats.chain_verified >= len(kfs) - 1


def _result_row(name: str = 'seneca', variant: str = 'all') -> tuple[dict, Path]:
    """The newest bench/results/inflight_chain_*.jsonl row of a set (the figure the slow test guards)."""
    files = sorted((ROOT / 'bench' / 'results').glob('inflight_chain_*.jsonl'), key=lambda p: p.stat().st_mtime)
    for path in reversed(files):
        for line in reversed(path.read_text().splitlines()):
            row = json.loads(line)
            if row.get('set') == name and row.get('variant') == variant and row.get('share') is not None:
                return row, path
    pytest.skip('no bench/results/inflight_chain_*.jsonl row for seneca')


@pytest.mark.slow
def test_replay_of_seneca_orients_what_triangulate_orients(tmp_path):
    """bench/results/inflight_chain_<commit>.jsonl (seneca, all): replay orients >= 95 % of the keyframes whose
    photos triangulate orients (every photo is a keyframe at photo rate)."""
    row, path = _result_row()
    photos = ROOT.parent / 'shared' / 'data' / 'photos' / 'seneca_part' / 'images'
    out = tmp_path / 'replay'
    env = {**os.environ, 'PYTHONPATH': str(ROOT)}
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'replay', str(photos), '--out', str(out), '--quiet'],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=3600)
    lines = [ln for ln in (out / 'trajectory.csv').read_text().splitlines()[1:] if ln.strip()] \
        if (out / 'trajectory.csv').exists() else []
    print(f'seneca replay: {len(lines)} oriented; the bench ({path.name}): {row["replay_oriented_of_triangulated"]} '
          f'of the {row["keyframes_triangulated"]} keyframes triangulate orients; exit {r.returncode}')
    # Oriented keyframes against triangulate's count (the same 41 photos, all keyframes): at least 95 %.
    assert len(lines) >= math.ceil(0.95 * row['triangulate_oriented'])
    assert row['share'] >= 0.95, f'{path.name}: share {row["share"]}'
