"""Feature tracker and keyframe choice: a stream of frames in, mapping keyframes out.

Per frame: grey conversion, a power-of-two reduction of large frames (`track_max_px`: 1920 px frames
are tracked at half size, 4000 px photos at a quarter, 5472 px (20 MP) photos at an eighth; positions go
out in full-frame pixels), and
photometric normalisation (mean/std or CLAHE, so that exposure jumps do not break KLT), pyramidal KLT
from the previous frame with a constant-velocity prior and a forward-backward check, RANSAC on the
essential matrix in undistorted normalized coordinates, then top-up detection (goodFeaturesToTrack
per grid cell, so one textured corner cannot take all the features).

Beyond KLT's reach (photo-rate input 0.1-2 Hz, a gap, a fast turn, a black frame: fewer than
`recover_min_tracks` survivors or under `klt_min_share` of the tracks) the frame is matched by
descriptors (core/photo_matching.py: SIFT on the reduced frame, ratio test, essential matrix) against
the chain: the earlier keyframes whose footprints it overlaps by GNSS (photo_matching.earlier_candidates,
the way `triangulate` plans its pairs: the `chain_neighbours` nearest and any within that distance plus
the fixes' uncertainty, across strips and turns), and the last `match_keyframes` keyframes, nearest
first. A frame stops there once `chain_enough_verified` keyframes verified a match, or
once `chain_stop_after_failures` in a row failed after one verified (farther ones overlap less). With that
early stop off, after `klt_rest_after_losses` frames in a row on which KLT lost its tracks (photo-rate input),
KLT is tried on every KLT_RETRY_EVERY-th frame only: the others go straight to descriptors (the two together
are refused: TrackerParams.check). A matched feature takes the track id its matches carry (the id published by the most keyframes
where they differ: the likeliest to be a point the adjuster knows), so a keyframe shares tie points with
every oriented keyframe it overlaps, not only the previous one; the KLT tracks of the nearest matched
keyframe still held are refined onto the frame through the homography of the matches (sub-pixel, ids
kept). A keyframe made after a break is matched with the chain's candidates not tried yet and publishes
every SIFT feature as a track (those without an id start one), which later keyframes continue. With
`chain_klt_keyframes` keyframes KLT carried (video rate) do the same with `chain_features` of theirs.
Without it, core/cross_strip.py gives SIFT features to every `cross_strip_store_every`-th keyframe KLT carried
(kept in the chain) and to one whose GNSS footprint overlaps a chain entry of another strip (matched with those
only), so that strips KLT carried share tie points.
What the chain keeps per keyframe (core.keyframes.ChainStore): `chain_features` SIFT features (uint8
descriptors, reduced-image pixels, track ids) and the ids it published: ~226 kB for a photo-rate
keyframe (1500 features, 4000 tracks), the newest `chain_max_keyframes`; plus one byte per track id
(how many keyframes published it). A break is counted either way; `bridged` says the ids continued.

Keyframes are chosen for mapping: a new one when the front overlap with the last keyframe falls to
`keyframe_overlap` (the frame closest to the target is taken, which may be the previous frame),
or when fewer than `min_surviving` of the keyframe's tracks survive. Overlap comes from a
homography on the shared tracks, or from the GPS distance flown when the fix is good.

A frame may also come still compressed (`EncodedImage`: the JPEG/PNG bytes of a photo): it is then
decoded straight at the working size (libjpeg's DCT scaling, cv2.IMREAD_REDUCED_GRAYSCALE_2/4/8: a
20 MP photo in about 0.1 s instead of 0.3 s for the full decode, grey conversion and reduction), and
decoded at full size only when it becomes a keyframe, the first time its `image` is read (so a node
can do that off its frame loop).

The keyframe record (stable interface, consumed by the bundle adjuster)
-----------------------------------------------------------------------
`Keyframe`:
  index          int      0, 1, 2, ... in the order keyframes are emitted
  frame_index    int      index of the source frame among the frames given to the tracker
  stamp_ns       int      the image's header stamp, ns
  image          ndarray  (H, W, 3) uint8 BGR, the original (not normalised) image (of an EncodedImage:
                          decoded at full size the first time it is read; DataError if it cannot be)
  observations   ndarray  structured, dtype FEATURE_DTYPE, one row per track seen in this image:
                   track_id uint32  the same id in every keyframe that sees the same ground point
                   u, v     float64 distorted pixel coordinates (origin at the centre of the top-left pixel)
                   xn, yn   float64 undistorted normalized coordinates x/z, y/z (optical frame)
  fix            GnssFix | None  the GNSS fix interpolated to stamp_ns (core.gnss_fix; None during an outage)
  overlap        float    estimated front overlap with the previous keyframe (nan for the first)
  break_before   bool     tracking broke between the previous keyframe and this one
  bridged        bool     ... and descriptor matching reconnected the tracks (ids continue)
On ROS the table travels as a PointCloud2 with exactly these named fields (msgs.keyframe_features_msg).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from photogram_ros.core.chain_links import TrackViews, assign_track_ids, enough_links
from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.cross_strip import CrossStrip, CrossStripParams
from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.klt import KltStep
from photogram_ros.core.keyframe_image import EncodedImage, Keyframe
from photogram_ros.core.other_image import OtherImageFallback, first_per_id
from photogram_ros.core.keyframes import ChainStore, FixBuffer, OverlapGrid, gps_distance_m, homography_overlap
from photogram_ros.core.photo_matching import (DescriptorIndex, MatchingOptions, PhotoFeatures, extract,
                                               match_pair)
from photogram_ros.errors import CalibrationError, ConfigError
from photogram_ros.params import param

KLT_RETRY_EVERY = 4      # while KLT rests (klt_rest_after_losses), it is tried on every this-many-th frame
# Why TrackerParams.check refuses klt_rest_after_losses with the chain's early stop.
CHAIN_STOP_WITH_KLT_REST = ('together (4, 3 and 3) they folded a strip of seneca_part\'s replay (block check FAILED, '
                            '23.3/16.7 m from GPS: bench/results/real_surveys_6e10adb.jsonl) where each alone did not: '
                            'the links of that strip barely change (bench/tracker_chain_links.py), the small changes '
                            'of the two elsewhere add up to another path of the incremental adjustment')
SPACING_KEYFRAMES = 10   # keyframes over which keyframe_spacing_m is the median
FEATURE_DTYPE = np.dtype([('track_id', '<u4'), ('u', '<f8'), ('v', '<f8'), ('xn', '<f8'), ('yn', '<f8')])


@dataclass
class TrackerParams(CrossStripParams):
    grid_cols: int = param(8, 'Detection grid columns (features are spread over the cells)', min=1, max=64)
    grid_rows: int = param(6, 'Detection grid rows', min=1, max=64)
    max_features: int = param(400, 'Tracks kept alive per frame (topped up per cell)', min=16, max=20000)
    min_distance_px: float = param(10.0, 'Minimum distance between features, px', min=1.0, max=200.0)
    quality_level: float = param(0.01, 'goodFeaturesToTrack quality, relative to the best corner in a cell',
                                 min=1e-4, max=0.5)
    klt_window_px: int = param(21, 'KLT window size, px (odd)', min=5, max=101)
    klt_levels: int = param(3, 'KLT pyramid levels above the full image', min=0, max=8)
    fb_max_px: float = param(0.5, 'Forward-backward KLT disagreement beyond which a track is dropped, px',
                             min=0.01, max=10.0)
    klt_err_factor: float = param(2.5, 'Drop tracks whose KLT residual exceeds this times the median (0: off)',
                                  min=0.0, max=100.0)
    derotate_deg: float = param(1.0, 'Above this frame-to-frame rotation, KLT is refined on the de-rotated '
                                'previous image, deg (0: off)', min=0.0, max=90.0)
    ransac_px: float = param(1.0, 'Essential-matrix RANSAC threshold, px (converted with fx)', min=0.05, max=20.0)
    normalize: str = param('clahe', 'Photometric normalisation before tracking (CLAHE measured most precise)',
                           choices=('none', 'meanstd', 'clahe'))
    min_contrast_dn: float = param(4.0, 'Frames with a grey-level std below this are unusable (black, '
                                   'white, lens cap), DN', min=0.0, max=100.0)
    keyframe_overlap: float = param(0.8, 'Front overlap with the last keyframe at which a new one is taken',
                                    min=0.05, max=0.98)
    min_surviving: float = param(0.3, "New keyframe when fewer than this fraction of the keyframe's tracks "
                                 'survive', min=0.0, max=1.0)
    min_parallax_px: float = param(2.0, 'No overlap-driven keyframe below this median track motion, px '
                                   '(hovering)', min=0.0, max=1000.0)
    overlap_source: str = param('image', 'Front overlap from tracked points (image), GPS distance (gps), or '
                                'GPS when its fix is good else image (auto)', choices=('image', 'gps', 'auto'))
    ground_distance_m: float = param(0.0, 'Camera height above ground for GPS overlap, m (0: GPS overlap off)',
                                     min=0.0, max=10000.0)
    gps_max_sigma_m: float = param(0.5, 'GPS overlap only with a horizontal sigma below this, m', min=0.0,
                                   max=100.0)
    recover_min_tracks: int = param(30, 'Fewer surviving tracks than this is a break: match the last '
                                    'keyframe by descriptors', min=8, max=10000)
    track_max_px: int = param(1024, 'Frames whose long side exceeds this are tracked (KLT, detection, descriptors) '
                              'at a power-of-two reduction that fits, px: 1920 px at half size, 4000 px at a '
                              'quarter, 5472 px (20 MP) at an eighth; smaller frames as they are',
                              min=160, max=20000)
    match_keyframes: int = param(4, 'At a break the frame is matched by descriptors (core/photo_matching.py) '
                                 'against this many recent keyframes, nearest by GNSS first', min=1, max=50)
    match_features: int = param(4000, 'SIFT features per frame matched at a break (their track ids continue in '
                                'the keyframes that see them again)', min=100, max=50000)
    chain_neighbours: int = param(8, 'Each new keyframe (and a frame at a break) is matched by descriptors against '
                                  'the earlier keyframes whose footprints it overlaps, from their GNSS positions, '
                                  'across strips too: this many nearest and any within that distance plus the '
                                  'fixes\' uncertainty (photo_matching.earlier_candidates, as triangulate plans its '
                                  'pairs); its features take their track ids. 0: off (a break matches only the '
                                  'last match_keyframes)', min=0, max=100)
    chain_features: int = param(1500, 'SIFT features a keyframe publishes as tracks and keeps for later keyframes '
                                'to match (those linked to earlier keyframes first, then the strongest): 140 bytes '
                                'each', min=50, max=50000)
    chain_max_keyframes: int = param(600, 'Keyframes whose features are kept for cross-keyframe matching (the '
                                     'newest; ~226 kB each at 1500 features of 4000 tracks)', min=1, max=100000)
    chain_enough_verified: int = param(0, 'A frame stops matching chain entries (nearest by GNSS first) once this '
                                       'many verified a match (0: every candidate is tried). 4 with '
                                       'chain_stop_after_failures 3: the tracker\'s CPU on 20 MP seneca 0.72x '
                                       '(inflight_20mp_tracker_cpu_seneca_6a51a7e), every real set as many oriented, '
                                       'but brighton\'s replay 1.10-1.17x further from GPS vertically (0.26 against '
                                       '0.22-0.23 m: real_surveys_tracker_chainstop_on/off_6c8d3df, _brighton_again_*_6a51a7e): '
                                       'off. Not with '
                                       'klt_rest_after_losses (TrackerParams.check)', min=0, max=100)
    chain_stop_after_failures: int = param(0, 'A frame that verified a match with a chain entry stops after this '
                                           'many further entries in a row fail (the farther ones overlap less; '
                                           '0: every candidate is tried). Not with klt_rest_after_losses', min=0, max=100)
    chain_linked_ids: int = param(50, 'An earlier keyframe already sharing this many track ids with the new one '
                                  '(KLT, or an earlier match) is not matched again', min=1, max=100000)
    features_on: str = param('normalised', 'Image the SIFT features of descriptor matching are detected on: the '
                             'reduced grey after the tracker\'s photometric normalisation (normalised), or as decoded '
                             '(raw): CLAHE makes KLT precise but can cost a weak pair its verified matches (brighton_beach '
                             'every other photo: DJI_0018-DJI_0020 verify raw, not after CLAHE); raw alone loses '
                             'seneca\'s near-infrared keyframes (inflight_chain_69c54e1); features_fallback adds the '
                             'other image where a break needs it', choices=('raw', 'normalised'))
    features_fallback: bool = param(False, 'Keyframes at or after a break (photo-rate input) also publish SIFT '
                                    'features of the other image (raw <-> normalised), matched first with those of '
                                    'the weak keyframes they overlap by GNSS (the first, or one only its other image '
                                    'bridged); a frame at a break that verifies no keyframe with features_on is '
                                    'matched on its other image against the last match_keyframes keyframes\' '
                                    '(core/other_image.py). One more extraction per such keyframe: 1.5x the tracker\'s '
                                    'CPU per photo on brighton_beach (inflight_chain_fallback_cost_cbb9276), which a '
                                    'live camera\'s pace cannot spare on a 2-core computer (off by default); '
                                    'config/replay.yaml turns it on: its every other photo: DJI_0018 linked '
                                    '(inflight_chain_7898530)')
    chain_klt_keyframes: bool = param(False, 'Also keyframes that KLT carried (video-rate input, no break since the '
                                      'last keyframe) get SIFT features, publish chain_features of them as tracks '
                                      'and are matched with the earlier keyframes they overlap; off: only frames '
                                      'at a break and the keyframes after one (photo-rate input)')
    klt_rest_after_losses: int = param(0, 'After this many frames in a row on which KLT lost the tracks (photo-rate '
                                       'input: every frame bridged by descriptors), KLT is tried on every '
                                       'KLT_RETRY_EVERY-th frame only, the others go straight to descriptor matching '
                                       '(0: KLT tried on every frame). Only with the chain\'s early stop off '
                                       '(chain_enough_verified and chain_stop_after_failures 0: TrackerParams.check)',
                                 min=0, max=1000)
    klt_min_share: float = param(0.2, 'Fewer KLT survivors than this share of the previous frame\'s tracks also '
                                 'tries descriptor matching (photo-rate input: motion far beyond KLT)',
                                 min=0.0, max=1.0)
    gap_s: float = param(0.0, 'A frame interval above this is a gap, s (0: 2.5 x the usual interval)',
                         min=0.0, max=3600.0)
    fix_wait_s: float = param(1.5, 'How long a keyframe waits for a GPS fix after it is made (on the clock '
                                    'process() is given: the frame stamps, or a node\'s receive clock), s '
                                    '(more than the GPS period: 1 Hz receivers are common)',
                              min=0.0, max=10.0)
    fix_lag_max_s: float = param(20.0, 'While fixes keep arriving but lag behind the frames (a GNSS stream '
                                       'delivered late under load), a keyframe waits up to this long (on the '
                                       'same clock) for its fix; a fix stream that stops for fix_wait_s ends '
                                       'the wait, s', min=0.0, max=120.0)
    fix_max_gap_s: float = param(2.5, 'No fix is interpolated across a GPS gap longer than this, s (2.5 GPS '
                                       'periods at 1 Hz: decoded fix stamps jitter)',
                                 min=0.01, max=60.0)

    def check(self) -> None:
        """ConfigError for KLT's rest together with the chain's early stop: with both, the replay of seneca_part
        folded a strip (block check FAILED; each alone did not, CHAIN_STOP_WITH_KLT_REST)."""
        if self.klt_rest_after_losses and (self.chain_enough_verified or self.chain_stop_after_failures):
            raise ConfigError(
                f'klt_rest_after_losses {self.klt_rest_after_losses} with the chain\'s early stop '
                f'(chain_enough_verified {self.chain_enough_verified}, chain_stop_after_failures '
                f'{self.chain_stop_after_failures}): {CHAIN_STOP_WITH_KLT_REST}; set klt_rest_after_losses 0, '
                f'or both chain_enough_verified and chain_stop_after_failures 0')


@dataclass
class TrackerStats:
    frames: int = 0
    unusable: int = 0          # black / over-exposed / featureless frames
    gaps: int = 0              # frame intervals above gap_s
    breaks: int = 0            # KLT could not carry the tracks
    bridged: int = 0           # ... and descriptor matching to the last keyframe reconnected them
    keyframes: int = 0
    tracks_alive: int = 0
    last_overlap: float = float('nan')
    out_of_order: int = 0
    process_s: float = 0.0     # total time in process()
    chain_pairs: int = 0       # keyframe pairs matched by descriptors (breaks and cross-keyframe)
    chain_verified: int = 0    # ... of them verified
    chain_bytes: int = 0       # what cross-keyframe matching keeps (core.keyframes.ChainStore)
    chain_dropped: int = 0     # keyframes whose features were dropped (beyond chain_max_keyframes)
    keyframe_spacing_m: float = float('nan')   # median GNSS distance between the last keyframes released with fixes


@dataclass
class _Frame:
    index: int
    stamp_ns: int
    image: np.ndarray          # original image (BGR or grey), or the EncodedImage it came as
    gray: np.ndarray           # normalised grey
    raw: np.ndarray | None     # the reduced grey before normalisation (None: the same as gray or not needed)
    pyr: list
    pts: np.ndarray            # (N, 2) float32 pixels of the reduced image
    ids: np.ndarray            # (N,) uint32
    overlap: float | None = None
    fix: GnssFix | None = None
    features: PhotoFeatures | None = None   # SIFT of the reduced image, computed at a break
    feat_ids: np.ndarray | None = None      # (K,) int64 track id per feature (-1: none)
    # Descriptor tracks this frame starts as a keyframe (not followed by KLT; a later frame
    # matching its features continues them): (M, 2) reduced-image pixels and (M,) ids.
    extra_pts: np.ndarray = field(default_factory=lambda: np.empty((0, 2), np.float32))
    extra_ids: np.ndarray = field(default_factory=lambda: np.empty(0, np.uint32))
    chain_tried: set = field(default_factory=set)   # keyframe indices this frame was matched with
    chain_verified: int = 0       # ... of them verified
    chain_failed_run: int = 0     # entries failed in a row since the last verified one
    desc_index: DescriptorIndex | None = None   # FLANN trees over `features`, built at its first match



def _descriptor_index(frame: _Frame) -> DescriptorIndex:
    """The frame's DescriptorIndex: built once, searched by every keyframe it is matched against."""
    if frame.desc_index is None or frame.desc_index.size != len(frame.features.desc):
        frame.desc_index = DescriptorIndex(frame.features.desc)
    return frame.desc_index


def _dedupe_feature_ids(frame: _Frame) -> None:
    """One feature per track id of `frame` (two features matched to one track: keep the first)."""
    first_per_id(frame.feat_ids)

@dataclass
class _KfState:
    frame: _Frame
    keyframe: Keyframe
    id_to_row: dict
    xn: np.ndarray


class Tracker:
    """Feed frames with `process(image, stamp_ns)`, fixes with `add_fix`; keyframes come back."""

    def __init__(self, camera: PinholeCamera | None, params: TrackerParams | None = None):
        self.params = params or TrackerParams()
        self.stats = TrackerStats()
        self.fixes = FixBuffer(self.params.fix_max_gap_s)
        self.camera = None
        self._prev: _Frame | None = None
        self._kf: _KfState | None = None
        self._recent: list[_KfState] = []   # the last match_keyframes keyframes, oldest first
        self._pending: list[tuple[Keyframe, int]] = []   # (keyframe, clock when it was made, ns)
        self.chain = ChainStore(self.params.chain_max_keyframes)
        self.cross = CrossStrip(self.params)   # which keyframes KLT carried get SIFT features
        self._held: list[_KfState] = []   # the keyframe states whose full features are held (= _recent)
        self._views = TrackViews()   # per track id: keyframes that published it
        self._origin: LocalFrame | None = None   # local frame of the chain's positions (the first fix)
        self._clock_ns = 0
        self._fix_seen = (None, None)   # (latest fix stamp, clock when it first advanced to it)
        self._last_kf_fix: GnssFix | None = None   # of the last keyframe released with one
        self._kf_spacing_m: list[float] = []       # GNSS distances between the last keyframes released with fixes
        self._next_id = 0
        self._n_frames = 0
        self._velocity = np.zeros(2, np.float32)   # median image motion, px/s
        self._klt_losses = 0        # frames in a row on which KLT lost the tracks (klt_rest_after_losses)
        self._dt_hist: list[float] = []
        self._lost = False          # a frame was unusable since the last tracked one
        self._break_since_kf = False
        self._bridged_since_kf = False
        self._break_index = -1      # frame index of the last break (the keyframe choice must not skip it)
        self._clahe = cv2.createCLAHE(2.0, (8, 8))
        p = self.params
        self._win = (p.klt_window_px | 1, p.klt_window_px | 1)
        if camera is not None:
            self.set_camera(camera)

    # --- inputs ----------------------------------------------------------------------------------

    def set_camera(self, camera: PinholeCamera) -> None:
        camera.validate()
        if self.camera is not None and camera == self.camera:
            return
        self.camera = camera
        # A power-of-two reduction (1920 -> 960, 4000 -> 1000): exact pixel areas, and fast to make.
        reduce = 1
        while max(camera.width, camera.height) / reduce > self.params.track_max_px:
            reduce *= 2
        self._scale = 1.0 / reduce          # reduced px per full px
        self._work_cam = camera if self._scale == 1.0 else camera.scaled(self._scale)
        self._klt_step = KltStep(self.params, self._work_cam)
        self._grid = OverlapGrid(camera)
        self._prev = None     # points of another calibration cannot be continued
        self._kf = None
        self._recent = []
        self.chain = ChainStore(self.params.chain_max_keyframes)
        self.other_image = OtherImageFallback(   # features_fallback (core/other_image.py)
            self._work_cam, self._match_options(), 
            lambda uv: self._work_cam.in_image(uv, margin_px=self._win[0] / 2 + 1), self._new_ids, lambda s: (self._position_of(s) or (None,))[0], self.params)

    def add_fix(self, fix: GnssFix | dict) -> None:
        """A GNSS fix, or the dict of msgs.fix_from_navsatfix."""
        self.fixes.add(fix if isinstance(fix, GnssFix) else GnssFix.from_dict(fix))

    # --- the frame pipeline ----------------------------------------------------------------------

    def process(self, image: np.ndarray | EncodedImage, stamp_ns: int, clock_ns: int | None = None) \
            -> list[Keyframe]:
        """Track one frame (an (H, W[, 3]) uint8 array, or an EncodedImage decoded here at the working size);
        returns the keyframes completed so far (usually none or one). CalibrationError when the frame's size
        is not the camera's, DataError when an EncodedImage cannot be decoded.

        `clock_ns` is the time the waits for GPS fixes (fix_wait_s, fix_lag_max_s) are measured on: the
        frame's stamp when None (stream time: an offline run gives the same keyframes at any speed); a
        node passes its monotonic clock, so fixes its executor delivers late under load are waited for in
        real time, however fast the frames of a backlog or a replay go by."""
        t0 = time.perf_counter()
        self._clock_ns = int(stamp_ns if clock_ns is None else clock_ns)
        try:
            return self._process(image, int(stamp_ns))
        finally:
            self.stats.process_s += time.perf_counter() - t0

    def _process(self, image, stamp_ns):
        if self.camera is None:
            raise CalibrationError('no camera calibration yet: frames cannot be used before camera_info '
                                   'or a calibration file gives the intrinsics')
        encoded = isinstance(image, EncodedImage)
        gray = self._reduced_grey(image) if encoded else None
        if not encoded:
            h, w = image.shape[:2]
            self.camera.check_image_size(w, h)
        self.stats.frames += 1
        index = self._n_frames
        self._n_frames += 1
        if self._prev is not None and stamp_ns <= self._prev.stamp_ns:
            self.stats.out_of_order += 1
            return []
        if not encoded:
            gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        mean, std = (float(v[0][0]) for v in cv2.meanStdDev(gray))
        if std < self.params.min_contrast_dn or mean > 250.0:
            self.stats.unusable += 1
            self._lost = True
            return self._release()
        if self._scale < 1.0 and not encoded:
            gray = cv2.resize(gray, (self._work_cam.width, self._work_cam.height), interpolation=cv2.INTER_AREA)
        g = self._normalise(gray, mean, std)
        # (Python's calcOpticalFlowPyrLK cannot take prebuilt pyramids; it builds them itself.)
        raw = gray if g is not gray and (self.params.features_on == 'raw' or self.params.features_fallback) else None
        cur = _Frame(index, stamp_ns, image, g, raw, g, np.empty((0, 2), np.float32), np.empty(0, np.uint32))
        if self._prev is None or self._kf is None:
            cur.pts, cur.ids = self._top_up(cur, cur.pts, cur.ids)
            self._make_keyframe(cur, overlap=float('nan'))
        else:
            self._track(cur)
        self.stats.tracks_alive = len(cur.ids)
        self._prev = cur
        return self._release()

    def _reduced_grey(self, image: EncodedImage) -> np.ndarray:
        """A compressed frame decoded at the working size (CalibrationError when its size is not the camera's)."""
        reduce = int(round(1.0 / self._scale))
        g = image.reduced_grey(reduce)
        h, w = g.shape
        cam = self.camera
        if (w, h) != (-(-cam.width // reduce), -(-cam.height // reduce)):
            raise CalibrationError(
                f'images are about {w * reduce}x{h * reduce} (decoded at 1/{reduce}: {w}x{h}) but the calibration '
                f'is for {cam.width}x{cam.height}: use the calibration of this camera mode, or scale it with '
                'PinholeCamera.scaled()')
        # DCT scaling rounds the size up; the working camera rounds to the nearest: same pixel grid, cropped.
        return np.ascontiguousarray(g[:self._work_cam.height, :self._work_cam.width])

    def current_tracks(self) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) pixel positions and (N,) track ids in the last tracked frame (for debug drawing)."""
        if self._prev is None:
            return np.empty((0, 2), np.float32), np.empty(0, np.uint32)
        return self._prev.pts.copy(), self._prev.ids.copy()

    def flush(self) -> list[Keyframe]:
        """At the end of the stream: emit the keyframes still waiting for a GPS fix."""
        out = [self._finish(k) for k, _ in self._pending]
        self._pending = []
        return out

    def _normalise(self, gray, mean, std):
        mode = self.params.normalize
        if mode == 'clahe':
            return self._clahe.apply(gray)
        if mode == 'meanstd':
            a = 48.0 / max(std, 1.0)
            return cv2.addWeighted(gray, a, gray, 0.0, 128.0 - a * mean)
        return gray

    def _gap_limit_s(self) -> float:
        if self.params.gap_s > 0:
            return self.params.gap_s
        if len(self._dt_hist) < 3:
            return float('inf')
        return 2.5 * float(np.median(self._dt_hist))

    def _track(self, cur: _Frame) -> None:
        p = self.params
        prev = self._prev
        dt = (cur.stamp_ns - prev.stamp_ns) * 1e-9
        if dt > self._gap_limit_s():
            self.stats.gaps += 1
        else:
            self._dt_hist = (self._dt_hist + [dt])[-20:]
        p0, i0 = prev.pts, prev.ids
        if len(i0) > 2 * p.max_features:   # descriptor tracks of a keyframe: KLT follows a spread share
            sel = np.linspace(0, len(i0) - 1, 2 * p.max_features).astype(int)
            p0, i0 = p0[sel], i0[sel]
        resting = (p.klt_rest_after_losses and self._klt_losses >= p.klt_rest_after_losses
                   and self._klt_losses % KLT_RETRY_EVERY)
        if resting:   # photo-rate input: KLT has lost every frame lately; descriptors carry the chain
            pts, ids, flow = p0[:0], i0[:0], None
        else:
            pts, ids, flow = self._klt_step.track(prev.pyr, cur.pyr, p0, i0, self._velocity * dt)
        lost_klt = len(ids) < max(p.recover_min_tracks, p.klt_min_share * len(i0))
        self._klt_losses = self._klt_losses + 1 if lost_klt else 0
        if len(ids) >= p.recover_min_tracks and flow is not None:
            self._velocity = (flow / dt).astype(np.float32)
        if lost_klt:
            # Beyond KLT's reach (photo-rate input, a fast turn, a gap): descriptors against the
            # last keyframes; kept when they link more tracks than KLT carried.
            rec = self._recover(cur)
            if rec is not None and len(rec[1]) > len(ids):
                pts, ids = rec
                self._bridge(cur)
            elif len(ids) < p.recover_min_tracks:
                self.stats.breaks += 1
                self._break_since_kf = True
                self._break_index = cur.index
                pts, ids = np.empty((0, 2), np.float32), np.empty(0, np.uint32)
        self._lost = False
        cur.pts, cur.ids = self._top_up(cur, pts, ids)
        self._decide(cur)

    def _top_up(self, cur: _Frame, pts, ids):
        """Detect new corners in the grid cells that have fallen below their share of features."""
        p = self.params
        h, w = cur.gray.shape
        nc, nr = p.grid_cols, p.grid_rows
        per_cell = max(1, p.max_features // (nc * nr))
        cx = np.minimum((pts[:, 0] * nc / w).astype(int), nc - 1) if len(pts) else np.empty(0, int)
        cy = np.minimum((pts[:, 1] * nr / h).astype(int), nr - 1) if len(pts) else np.empty(0, int)
        counts = np.bincount(cy * nc + cx, minlength=nc * nr) if len(pts) else np.zeros(nc * nr, int)
        need = np.flatnonzero(counts < max(1, int(0.7 * per_cell)))
        if len(need) == 0:
            return pts, ids
        mask = np.full((h, w), 255, np.uint8)
        border = self._win[0] // 2 + 2
        mask[:border], mask[-border:], mask[:, :border], mask[:, -border:] = 0, 0, 0, 0
        r = int(round(p.min_distance_px))
        for x, y in pts:
            cv2.circle(mask, (int(round(x)), int(round(y))), r, 0, -1)
        new = []
        for cell in need:
            j, i = divmod(int(cell), nc)
            x0, x1 = i * w // nc, (i + 1) * w // nc
            y0, y1 = j * h // nr, (j + 1) * h // nr
            c = cv2.goodFeaturesToTrack(cur.gray[y0:y1, x0:x1], per_cell - int(counts[cell]), p.quality_level,
                                        p.min_distance_px, mask=mask[y0:y1, x0:x1], blockSize=7)
            if c is not None:
                new.append(c.reshape(-1, 2) + np.array([x0, y0], np.float32))
        if not new:
            return pts, ids
        new = np.concatenate(new).astype(np.float32)
        new_ids = np.arange(self._next_id, self._next_id + len(new), dtype=np.uint32)
        self._next_id += len(new)
        return np.concatenate([pts, new]), np.concatenate([ids, new_ids])

    # --- breaks ----------------------------------------------------------------------------------

    def _bridge(self, cur: _Frame) -> None:
        """Count a break that descriptor matching reconnected (track ids continue)."""
        self.stats.breaks += 1
        self.stats.bridged += 1
        self._break_since_kf = self._bridged_since_kf = True
        self._break_index = cur.index

    def _match_options(self) -> MatchingOptions:
        n = self.params.match_features
        return MatchingOptions(max_features=n, features_per_mpx=max(100.0, 4.0 * n), min_inliers=15,
                               ransac_method='usac')

    def _features_of(self, frame: _Frame) -> None:
        """SIFT features of a frame (reduced-image pixels), without track ids yet (-1)."""
        if frame.features is None:
            img = frame.raw if frame.raw is not None and self.params.features_on == 'raw' else frame.gray
            frame.features = extract(str(frame.index), img, (1.0, 1.0), self._match_options())
            frame.feat_ids = np.full(len(frame.features.uv), -1, np.int64)

    def _new_ids(self, n: int) -> np.ndarray:
        t = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        return t

    def _position_of(self, stamp_ns: int):
        """((3,) local metres, horizontal sigma m) of the GNSS fix at (or nearest, within fix_max_gap_s) the
        stamp, in the chain's local frame (at the first fix used); None without one."""
        fix = self.fixes.near(stamp_ns, self.params.fix_max_gap_s)
        if fix is None:
            return None
        if self._origin is None:
            self._origin = LocalFrame(fix.lat_deg, fix.lon_deg, fix.h_m)
        enu = np.asarray(self._origin.geodetic_to_enu(fix.lat_deg, fix.lon_deg, fix.h_m), float).reshape(3)
        return enu, float(fix.horizontal_sigma_m)

    def _shared_ids(self, frame: _Frame) -> np.ndarray:
        """The track ids the frame holds so far (KLT, and features linked by descriptors)."""
        got = frame.feat_ids[frame.feat_ids >= 0] if frame.feat_ids is not None else np.empty(0, np.int64)
        return np.concatenate([frame.ids.astype(np.int64), got])

    def _candidates(self, cur: _Frame, at_break: bool) -> list[int]:
        """Chain entries (core.keyframes.ChainStore) to match the frame with: the earlier keyframes whose
        footprints it overlaps by GNSS (photo_matching.earlier_candidates: the chain_neighbours nearest and any
        within reach, across strips), nearest first; at a break also the last match_keyframes keyframes (the
        only ones without positions). Not those the frame was matched with already, nor (but at a break)
        those it already shares chain_linked_ids track ids with."""
        p = self.params
        ch = self.chain
        ch.locate(self._position_of)
        if not at_break and p.chain_neighbours == 0:
            return []
        n = len(ch)
        recent = list(range(n - 1, max(-1, n - 1 - p.match_keyframes), -1))
        here = self._position_of(cur.stamp_ns)
        chosen = ch.overlapping(here, p.chain_neighbours)
        if at_break or here is None:
            chosen = chosen + [i for i in ch.nearest_first(recent, here) if i not in chosen]
        have = self._shared_ids(cur)
        out = []
        for i in chosen:
            if ch.keys[i] in cur.chain_tried:
                continue
            # (At a break the KLT survivors are no link: most are coincidences far beyond KLT's reach.)
            if not at_break and len(have) and int(np.isin(ch.seen[i], have).sum()) >= p.chain_linked_ids:
                continue
            out.append(i)
        return out

    def _entry_features(self, i: int) -> tuple[PhotoFeatures, np.ndarray]:
        """A chain entry's features and track ids (-1: not published): all of a keyframe still among the
        last match_keyframes, else the ones the chain keeps."""
        key = self.chain.keys[i]
        for k in self._recent:
            if k.keyframe.index == key and k.frame.features is not None:
                return k.frame.features, k.frame.feat_ids
        ch = self.chain
        return PhotoFeatures('', ch.uv[i].astype(np.float64), ch.descriptors(i)), ch.ids[i].astype(np.int64)

    def _chain_match(self, cur: _Frame, entries: list[int]) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """Descriptor matching (photo_matching.match_pair: ratio test, essential-matrix RANSAC) of the frame's
        features against the chain entries; a feature without a track id takes the id its matches carry, the
        one seen by the most keyframes where they differ (the likeliest to be known to the adjuster; then the
        oldest). Returns the verified (entry, entry pixels, frame features) in the order tried."""
        opt = self._match_options()
        f, got = cur.features, cur.feat_ids
        ch = self.chain
        verified, dsts, tids = [], [], []
        for i in entries:
            if enough_links(cur.chain_verified, cur.chain_failed_run, self.params):
                break
            cur.chain_tried.add(ch.keys[i])
            self.stats.chain_pairs += 1
            feats, ids = self._entry_features(i)
            m = match_pair(feats, f, self._work_cam, opt, index_b=_descriptor_index(cur))
            if not m.verified:
                cur.chain_failed_run += 1
                continue
            cur.chain_verified += 1
            cur.chain_failed_run = 0
            self.stats.chain_verified += 1
            self.other_image.linked(ch.keys[i])
            rows, dst = m.matches[:, 0], m.matches[:, 1]
            verified.append((i, feats.uv[rows], dst))
            keep = ids[rows] >= 0
            dsts.append(dst[keep])
            tids.append(ids[rows][keep].astype(np.int64))
        assign_track_ids(got, dsts, tids, self._views)
        return verified

    def _recover(self, cur: _Frame):
        """Descriptor matching of the frame at a break against the chain's candidates (`_candidates`: the
        keyframes it overlaps by GNSS, and the last ones), nearest first. A matched feature takes the track
        id its match carries in that keyframe; the KLT tracks of the nearest verified keyframe still held
        are refined onto the frame through the homography of the matches (sub-pixel, their ids kept).
        Returns (pts, ids) of the linked tracks, or None when no keyframe verified enough matches."""
        opt = self._match_options()
        self._features_of(cur)
        f = cur.features
        if len(f.uv) < opt.min_inliers:
            return None
        got = cur.feat_ids
        verified = self._chain_match(cur, self._candidates(cur, at_break=True))
        refined = (np.empty((0, 2), np.float32), np.empty(0, np.uint32))
        states = {k.keyframe.index: k for k in self._recent}
        for i, uv_kf, dst in verified:
            k = states.get(self.chain.keys[i])
            if k is not None:
                refined = self._klt_step.through_homography(k.frame.gray, k.frame.pts, k.frame.ids, uv_kf, f.uv[dst],
                                                             cur.gray)
                if len(refined[1]):
                    break
        if not len(refined[1]):
            refined = self._recover_from_klt_keyframes(cur)
        if int((got >= 0).sum()) < opt.min_inliers and not len(refined[1]):
            got[:] = -1
            return None if verified else self.other_image.recover(cur.index, cur.gray, cur.raw, cur.stamp_ns, [
                (k.keyframe.index, k.keyframe.stamp_ns) for k in self._recent])
        _dedupe_feature_ids(cur)
        inside = self._work_cam.in_image(f.uv, margin_px=self._win[0] / 2 + 1)
        take = (got >= 0) & inside & ~np.isin(got, refined[1].astype(np.int64))   # KLT-refined positions win
        return (np.concatenate([refined[0], f.uv[take].astype(np.float32)]),
                np.concatenate([refined[1], got[take].astype(np.uint32)]))

    def _recover_from_klt_keyframes(self, cur: _Frame):
        """The last keyframes KLT carried (not in the chain: no SIFT tracks published), newest first: the
        frame matched with their features (computed now), their KLT tracks refined onto it through the
        homography of the matches (ids kept); a matched feature takes the id the keyframe's feature got (a
        new one: that keyframe is out, later frames continue it). (pts, ids) of the refined tracks."""
        none = (np.empty((0, 2), np.float32), np.empty(0, np.uint32))
        stored = set(self.chain.keys)
        f, got = cur.features, cur.feat_ids
        for k in reversed(self._recent):
            if k.keyframe.index in stored or k.keyframe.index in cur.chain_tried:
                continue
            cur.chain_tried.add(k.keyframe.index)
            self._features_of(k.frame)
            self.stats.chain_pairs += 1
            m = match_pair(k.frame.features, f, self._work_cam, self._match_options(),
                           index_b=_descriptor_index(cur))
            if not m.verified:
                continue
            self.stats.chain_verified += 1
            rows, dst = m.matches[:, 0], m.matches[:, 1]
            open_ = got[dst] < 0
            fresh = open_ & (k.frame.feat_ids[rows] < 0)
            k.frame.feat_ids[rows[fresh]] = self._new_ids(int(fresh.sum()))
            got[dst[open_]] = k.frame.feat_ids[rows[open_]]
            refined = self._klt_step.through_homography(k.frame.gray, k.frame.pts, k.frame.ids,
                                                             k.frame.features.uv[rows], f.uv[dst], cur.gray)
            if len(refined[1]):
                return refined
        return none

    # --- keyframes -------------------------------------------------------------------------------

    def _measure(self, cur: _Frame):
        """(overlap or None, surviving fraction, median parallax px) of `cur` against the keyframe."""
        kf = self._kf
        rows = np.array([kf.id_to_row.get(int(i), -1) for i in cur.ids], int)
        shared = rows >= 0
        n_kf = max(len(kf.frame.ids), 1)
        surviving = shared.sum() / n_kf
        if shared.sum() < 8:
            return None, surviving, 0.0
        xn_kf = kf.xn[rows[shared]]
        xn_cur = self._work_cam.pixel_to_normalized(cur.pts[shared])
        parallax = float(np.median(np.linalg.norm(xn_cur - xn_kf, axis=1))) * self._work_cam.fx
        overlap = None
        fix_ok = self._gps_overlap(cur)
        if fix_ok is not None:
            overlap = fix_ok
        if overlap is None:
            overlap, _ = homography_overlap(self._grid, xn_kf, xn_cur, 2.0 / self._work_cam.fx)
        return overlap, surviving, parallax

    def _gps_overlap(self, cur: _Frame) -> float | None:
        p = self.params
        if p.overlap_source == 'image' or p.ground_distance_m <= 0:
            return None
        a = self.fixes.at(self._kf.keyframe.stamp_ns)
        b = self.fixes.at(cur.stamp_ns)
        if a is None or b is None or max(a.horizontal_sigma_m, b.horizontal_sigma_m) > p.gps_max_sigma_m:
            return None
        # Image top points along the flight: the along-track footprint is the image height.
        footprint_m = p.ground_distance_m * self.camera.height / self.camera.fy
        return max(0.0, 1.0 - gps_distance_m(a, b) / footprint_m)

    def _decide(self, cur: _Frame) -> None:
        p = self.params
        overlap, surviving, parallax = self._measure(cur)
        cur.overlap = overlap
        if overlap is None or surviving < p.min_surviving:
            self._make_keyframe(cur, overlap if overlap is not None else float('nan'))
            return
        if overlap > p.keyframe_overlap or parallax < p.min_parallax_px:
            return
        prev = self._prev
        if (prev is not None and prev is not self._kf.frame and prev.overlap is not None
                and self._break_index < prev.index
                and abs(prev.overlap - p.keyframe_overlap) < abs(overlap - p.keyframe_overlap)):
            self._make_keyframe(prev, prev.overlap)
            overlap, surviving, _ = self._measure(cur)
            cur.overlap = overlap
            if overlap is None or surviving < p.min_surviving or overlap <= p.keyframe_overlap:
                self._make_keyframe(cur, overlap if overlap is not None else float('nan'))
            return
        self._make_keyframe(cur, overlap)

    def _to_full_px(self, pts: np.ndarray) -> np.ndarray:
        """Reduced-image pixels -> full-image pixels (pixel centres at integers in both)."""
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        return pts if self._scale == 1.0 else (pts + 0.5) / self._scale - 0.5

    def _wants_features(self, frame: _Frame) -> bool:
        """Descriptors for a new keyframe: every one with chain_klt_keyframes (and chain_neighbours > 0);
        else the first one, and every one while the stream needs descriptor matching (a break
        bridged since, or at, the last keyframe: photo-rate input), so that a later frame matching them
        continues their tracks."""
        p = self.params
        return ((p.chain_neighbours > 0 and p.chain_klt_keyframes) or frame.features is not None
                or not self._recent or self._bridged_since_kf or self._recent[-1].keyframe.bridged)

    def _publish_features(self, frame: _Frame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The keyframe's SIFT features that become its tracks: inside the image, one per track id, all of them
        after a break (photo-rate input: descriptors carry the chain), else those linked to earlier keyframes
        then the strongest others, chain_features in all. New ones get new ids and join the keyframe's
        descriptor tracks (`extra_*`) unless a KLT track carries their id already. Returns what the chain
        keeps of them: chain_features, linked first (reduced-image pixels, RootSIFT descriptors, track ids)."""
        _dedupe_feature_ids(frame)
        f, fid = frame.features, frame.feat_ids
        ok = self._work_cam.in_image(f.uv, margin_px=self._win[0] / 2 + 1)
        strength = f.response if f.response is not None else np.zeros(len(fid), np.float32)
        order = np.lexsort((-strength, fid < 0))       # linked first, then the strongest
        order = order[ok[order]]
        if not (self._break_since_kf or not self._recent):
            order = order[:self.params.chain_features]
        fid[np.setdiff1d(np.arange(len(fid)), order)] = -1
        lone = order[fid[order] < 0]
        fid[lone] = self._new_ids(len(lone))
        shown = np.concatenate([frame.ids, frame.extra_ids]).astype(np.int64)
        add = order[~np.isin(fid[order], shown)]
        frame.extra_pts = np.concatenate([frame.extra_pts, f.uv[add].astype(np.float32)])
        frame.extra_ids = np.concatenate([frame.extra_ids, fid[add].astype(np.uint32)])
        order = order[:self.params.chain_features]
        if self._break_since_kf or not self._recent:   # core/other_image.py: features of the other image too
            near = self.chain.overlapping(self._position_of(frame.stamp_ns), self.params.chain_neighbours)
            frame.extra_pts, frame.extra_ids = self.other_image.publish(
                frame.index, self.stats.keyframes, frame.gray, frame.raw, (frame.pts, frame.ids),
                (frame.extra_pts, frame.extra_ids), [self.chain.keys[i] for i in near])
        return f.uv[order], f.desc[order], fid[order]

    def _make_keyframe(self, frame: _Frame, overlap: float) -> None:
        chain = None
        wanted = self._wants_features(frame)
        entries = self._candidates(frame, at_break=False) if wanted or self.cross.on else []
        cross = self.cross.plan(self.stats.keyframes, self._position_of(frame.stamp_ns), overlap, wanted,
                                self.chain, entries)
        if wanted or cross is not None:
            self._features_of(frame)
            if len(frame.features.uv):
                self._chain_match(frame, entries if wanted else cross)
                if not wanted:
                    self.cross.adopt_klt_ids(frame.features.uv, frame.feat_ids, frame.pts, frame.ids)
            chain = self._publish_features(frame)
        all_ids = np.concatenate([frame.ids, frame.extra_ids])
        _, first = np.unique(all_ids, return_index=True)
        first.sort()
        all_ids = all_ids[first]
        uv = self._to_full_px(np.concatenate([frame.pts, frame.extra_pts])[first])
        xn = self.camera.pixel_to_normalized(uv)
        obs = np.empty(len(all_ids), FEATURE_DTYPE)
        obs['track_id'] = all_ids
        obs['u'], obs['v'] = uv[:, 0], uv[:, 1]
        obs['xn'], obs['yn'] = xn[:, 0], xn[:, 1]
        image = frame.image
        if not isinstance(image, EncodedImage) and image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        kf = Keyframe(self.stats.keyframes, frame.index, frame.stamp_ns, image, obs, None, float(overlap),
                      self._break_since_kf, self._bridged_since_kf, (self.camera.width, self.camera.height))
        self.stats.keyframes += 1
        if np.isfinite(overlap):
            self.stats.last_overlap = float(overlap)
        self._break_since_kf = self._bridged_since_kf = False
        self._kf = _KfState(frame, kf, {int(i): r for r, i in enumerate(all_ids)}, xn)
        self._recent = (self._recent + [self._kf])[-self.params.match_keyframes:]
        self._views.add(all_ids)
        if chain is not None:
            self.chain.add(kf.index, kf.stamp_ns, *chain, seen=all_ids)
            self.stats.chain_bytes = self.chain.nbytes()
            self.stats.chain_dropped = self.chain.dropped
        kept = {id(k) for k in self._recent}
        for k in self._held:
            if id(k) not in kept:
                k.frame.features = k.frame.feat_ids = k.frame.raw = None   # the chain keeps what later ones match
        self.other_image.keep(k.keyframe.index for k in self._recent)
        self._held = list(self._recent)
        self._pending.append((kf, self._clock_ns))

    def _finish(self, kf: Keyframe) -> Keyframe:
        kf.fix = self.fixes.at(kf.stamp_ns)
        if kf.fix is not None:
            if self._last_kf_fix is not None:
                self._kf_spacing_m = (self._kf_spacing_m + [gps_distance_m(self._last_kf_fix, kf.fix)])[-SPACING_KEYFRAMES:]
                self.stats.keyframe_spacing_m = float(np.median(self._kf_spacing_m))
            self._last_kf_fix = kf.fix
        return kf

    def keyframe_spacing_m(self) -> float | None:
        """The median GNSS distance between the last SPACING_KEYFRAMES consecutive keyframes released with fixes, m
        (None before two): how far apart the keyframe rule takes them (core/frame_queue.py's drop rule)."""
        v = self.stats.keyframe_spacing_m
        return None if not np.isfinite(v) else v

    def _release(self) -> list[Keyframe]:
        """Keyframes whose GPS fix is known (a fix after the stamp arrived) or waited for long enough.

        A keyframe waits fix_wait_s (on process()'s clock) for a later fix. While the fix stream still
        advances (its latest stamp moved within the last fix_wait_s) but lags behind the frames, it waits
        on, up to fix_lag_max_s: a late fix stream must not strip keyframes of their positions. No fix at
        all, or a stream that stopped (an outage), ends the wait after fix_wait_s."""
        now_ns = self._clock_ns
        out = []
        latest = self.fixes.latest_ns()
        if latest is not None and latest != self._fix_seen[0]:
            self._fix_seen = (latest, now_ns)
        wait_ns = int(self.params.fix_wait_s * 1e9)
        lag_ns = max(wait_ns, int(self.params.fix_lag_max_s * 1e9))
        advancing = latest is not None and now_ns - self._fix_seen[1] < wait_ns
        while self._pending:
            kf, made_ns = self._pending[0]
            waited = now_ns - made_ns
            if (latest is not None and latest >= kf.stamp_ns) or waited >= lag_ns or \
                    (waited >= wait_ns and not advancing):
                out.append(self._finish(self._pending.pop(0)[0]))
            else:
                break
        return out

    def fix_lag_s(self, newest: bool = False) -> float:
        """How far the newest fix is behind the oldest keyframe waiting for one (newest=True: the newest such
        keyframe, which the end of a stream waits for), s; 0 when none waits."""
        latest = self.fixes.latest_ns()
        if not self._pending or latest is None:
            return 0.0
        return max(0.0, (self._pending[-1 if newest else 0][0].stamp_ns - latest) * 1e-9)
