"""The tracker's features_fallback (core/other_image.py) on a real photo-rate survey: brighton_beach's every other
photo (9 DJI photos 14 s apart, half the forward overlap), through the tracker and the adjuster in-process as
tracker_node and bundle_node chain them (the end of flight as the adjustment stage's: the waiting keyframes'
second chance).

DJI_0018, the first photo, sees texture in its overlaps only along one line of the image (x ~ 3100 px). Its
CLAHE-normalised features verify with no later keyframe; on the raw grey they verify with DJI_0020 (a patch of
~15 tracks) and with DJI_0028 across the strip (~30). Without the fallback it shares no track with any keyframe
and stays without a pose (`replay` 8 of 9: bench/results/inflight_chain_fbc92ca.jsonl, brighton half)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import shared_data
from photogram_ros.core.incremental import IncrementalAT, KeyframeRecord
from photogram_ros.core.tracker import EncodedImage, Tracker, TrackerParams
from photogram_ros.stages.adjustment import AdjustmentParams

pytestmark = [pytest.mark.realdata, pytest.mark.slow]


def _fly(params: TrackerParams):
    from photogram_ros.io.image_source import FolderSource, read_exif_gps
    src = FolderSource(shared_data('photos', 'brighton_beach', 'images'))
    cam = src.exif_intrinsics().camera
    tr = Tracker(cam, params)
    at = IncrementalAT(cam, AdjustmentParams())
    kfs, names = [], {}

    def adjust(new):
        for k in new:
            at.add_keyframe(KeyframeRecord(k.stamp_ns, k.observations['track_id'].astype(np.int64),
                                           np.column_stack([k.observations['u'], k.observations['v']]), k.fix))
            kfs.append(k)
    for i, (path, stamp) in enumerate(src.entries[::2]):
        tr.add_fix(read_exif_gps(path).gnss_fix(stamp, 5.0, 10.0))
        names[i] = Path(path).name
        adjust(tr.process(EncodedImage(Path(path).read_bytes()), stamp))
    adjust(tr.flush())
    return tr, at, kfs, [names[k.frame_index] for k in kfs]


def _shared(kfs, a: int, b: int) -> int:
    return len(np.intersect1d(kfs[a].observations['track_id'], kfs[b].observations['track_id']))


def test_the_first_photo_of_every_other_brighton_links_through_its_raw_image_and_gets_a_pose():
    tr, at, kfs, names = _fly(TrackerParams(features_fallback=True))   # as config/replay.yaml
    assert names[0] == 'DJI_0018.JPG' and names[5] == 'DJI_0028.JPG' and len(kfs) == 9
    assert tr.other_image.bridged >= 1
    # Across the strip: DJI_0028's raw features take the ids of DJI_0018's (a weak keyframe it overlaps).
    assert _shared(kfs, 0, 5) >= 15
    ids0 = kfs[0].observations['track_id']
    assert len(np.unique(ids0)) == len(ids0), 'one observation per track id'
    at.retry_unregistered()
    assert at.kfs[0].map_T_cam is not None
    # Where its fix says, within the fix's own stated horizontal sigma (5 m, as given to the tracker above); the
    # full set's replay puts this camera 0.35 m from it.
    off_m = float(np.linalg.norm(at.kfs[0].map_T_cam[:3, 3] - at.kfs[0].fix_enu))
    print(f'DJI_0018 shares {_shared(kfs, 0, 1)} tracks with DJI_0020, {_shared(kfs, 0, 5)} with DJI_0028; '
          f'its pose {off_m:.2f} m from its fix')
    assert off_m < 5.0


def test_without_the_fallback_the_first_photo_stays_alone():
    tr, at, kfs, _ = _fly(TrackerParams(features_fallback=False))
    assert tr.other_image.bridged == 0
    assert max(_shared(kfs, 0, k) for k in range(1, len(kfs))) == 0
    at.retry_unregistered()
    assert at.kfs[0].map_T_cam is None
