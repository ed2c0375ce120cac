"""A block that checks itself: the verdict of an aerial triangulation, offline and in flight.

`check_block(inputs, options)` takes what an adjusted block is (camera poses `map_T_cam` (N, 4, 4) in the
map frame, ENU metres; the GNSS antenna positions of the same cameras `fix_enu_m` (N, 3), NaN where a
camera has none; their stated sigmas; the tie points each camera sees; how the final adjustment ended)
and returns a `BlockVerdict`: 'ok', 'warning' or 'failed', with one `Finding` per check that is not
ok, each naming its reason and the photos it concerns.

The block's shape is judged on evidence from the photos themselves, never on how good its geotags are
assumed to be; the geotags then say how well the block is placed. The verdict names the checks that decided
it (`decided_by`), and `figures['shape']` holds the internal evidence:
- shape (internal evidence): the reprojection RMS of the tie points, their rays' intersection angles, the
  overlap graph (cameras joined by shared tie points: parts that share none are joined through their
  geotags only), and per-strip consistency: the flight's strips (runs of cameras along one heading) each
  look the way the whole block looks. A strip whose cameras look `fold_deg` or more away from the rest's,
  or a nadir flight whose cameras do not look one way, is a folded block: failed, whatever its geotags.
  Leave-strip-out: each strip's cameras against their geotags through the similarity of the other
  strips, against the scatter of the geotags themselves (a figure, said when a strip stands out).
- georeference: a block that neither its GNSS (3 cameras with a fix, off a line) nor 3 GCPs placed in the
  map frame sits in an arbitrary frame of its own: failed, and the checks that need the map's up and its
  place (gnss_rigid, ground_below, nadir) are not judged.
- gnss_fit: the cameras against their own GNSS through a robust similarity (the block's shape alone),
  residuals normalised by the GNSS noise (the estimated one where the adjustment estimated it). Far beyond
  that noise: failed when the geotags hold to what they state (RTK-like: the estimated noise within
  `noise_warn_factor` of the stated one) and the shape's own evidence does not vouch for it; otherwise a
  warning (the block and its geotags disagree). Cameras whose fix lies far from where the rest of the block
  puts them (a glitched geotag, a photo of another site) are named.
- gnss_rigid: the adjusted cameras against their GNSS as they are (the block's own georeference), normalised
  by the same noise: a block placed far from its own fixes is failed.
- ground_below: the tie points each camera sees lie below it. A block tipped over puts its ground beside
  or above its cameras: failed.
- nadir: the share of cameras within `nadir_tilt_deg` of nadir, against the flight's expectation (a
  mapping flight looks down unless told otherwise): a block whose cameras look sideways while the flight
  looked down is failed (tipped).
- photos_not_used: photos left out before the adjustment (another camera in the folder) are named.
- oriented: photos not oriented are named (a warning under `min_oriented_warn` oriented, by default any;
  under `min_oriented_failed`, failed).
- check_points: check points that disagree with the block far beyond the noise of its datum (its GNSS,
  at least 2 cm): the block or the control is wrong.
- convergence: a final adjustment that stopped short and still moves cameras: warning.
- gnss_bias: the GNSS bias the final adjustment estimated against >= 3 GCPs did not settle (its last step
  still 1 mm or more after its rounds): the block's place between its GCPs and its fixes is uncertain by about
  that step: warning.
- dome: the cameras' heights against their geotag heights, a quadratic surface over the block
  (core/self_calibration.py `height_bowl`): its rise at the block's radius against the geotags' own scatter
  about it. A level flight's altitudes (a barometer: centimetres from photo to photo) cannot dome, so a
  block whose cameras dome against them by far more than that scatter is bent, most often by self-calibrated
  radial distortion in a flat nadir block of parallel lines: warning. Judged after a full adjustment only.
- gnss_noise: the GNSS noise the adjustment estimated from the data, against what the fixes state:
  geotags poorer than they claim are said, and those it rejected are named; a horizontal scatter beyond
  `noise_h_far_m` on a block whose own evidence holds is said as such: the block is placed no better than
  its geotags (a compact camera's or a phone's GPS scatters that much).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from photogram_ros.core.self_calibration import height_bowl
from photogram_ros.core.similarity import similarity_ransac, umeyama

STATUS_ORDER = ('ok', 'warning', 'failed')


@dataclass
class BlockCheckOptions:
    """Thresholds of the block checks (dimensionless unless named with a unit)."""
    gnss_fit_warn: float = 3.0          # RMS of the similarity residuals / GNSS sigma: warning above
    gnss_fit_fail: float = 6.0          # ... failed above
    gnss_outlier: float = 5.0           # one camera's residual / sigma: its geotag is named
    nadir_tilt_deg: float = 15.0        # a camera within this of nadir counts as looking down
    nadir_share_warn: float = 0.8       # share near nadir expected of a nadir flight: warning under
    nadir_share_fail: float = 0.5       # ... failed under
    ground_below_fail: float = 0.9      # share of cameras whose tie points lie below them: failed under
    min_oriented_warn: float = 1.0      # share of photos oriented: warning under (1: any photo not oriented)
    min_oriented_failed: float = 0.5    # ... failed under
    noise_warn_factor: float = 3.0      # estimated GNSS noise / stated: warning above
    noise_h_far_m: float = 10.0         # estimated horizontal GNSS noise (m, about a similarity) beyond this: the
                                        # block is placed no better than its geotags, whatever they state (a warning
                                        # of its own; the shape is judged on internal evidence)
    fold_deg: float = 15.0              # a strip's median tilt from the vertical this far from the rest's: folded
    axis_share_fail: float = 0.5        # nadir flight: share of cameras within nadir_tilt_deg of the block's own
                                        # median optical axis, failed under (its parts look different ways)
    strip_turn_deg: float = 45.0        # a heading change between consecutive cameras this large starts a strip
    min_strip: int = 3                  # cameras in a strip for it to be judged
    reprojection_warn_px: float = 3.0   # tie points' reprojection RMS: warning above (wrong matches, a wrong camera)
    ray_angle_warn_deg: float = 1.0     # median intersection angle of the tie points' rays: warning under (depth
                                        # weakly determined: the shape rests on little)
    strip_out_warn: float = 4.0         # leave-strip-out: a strip's mean residual against its geotags, through the
                                        # other strips' similarity, / its standard error: said above
    level_warn_deg: float = 1.0         # tilt the GNSS heights gave the block beyond the one kept (deg): warning above
    check_warn: float = 5.0             # check-point RMSE / the datum's noise (>= 2 cm): warning above
    check_fail: float = 20.0            # ... failed above
    dome_warn_ratio: float = 4.0        # |rise| of the cameras' bowl against their geotag heights at the block's
                                        # radius / the geotags' scatter about it (at least 1 cm), and / the rise's
                                        # standard error (the cameras' layout: one or two lines do not determine
                                        # it): warning above both (and dome_warn_m)
    dome_warn_m: float = 0.15           # ... and |rise| above this, m


@dataclass
class Finding:
    check: str
    status: str                  # 'warning' or 'failed'
    text: str
    photos: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {'check': self.check, 'status': self.status, 'text': self.text, 'photos': list(self.photos)}


def ok_summary(figures: dict) -> str:
    """What a block without findings was found to do, from its check's `figures`."""
    by_gcps = figures.get('georeference', {}).get('cameras_with_fix', 3) < 3
    shape = figures.get('shape', {}).get('text')
    return (f"the block {'is placed by its GCPs' if by_gcps else 'agrees with its GNSS'}, looks at the ground "
            'below it and converged' + (f'; its shape holds by its own evidence ({shape})' if shape else ''))


@dataclass
class BlockVerdict:
    status: str                                     # 'ok', 'warning', 'failed'
    findings: list = field(default_factory=list)    # Finding, worst first
    figures: dict = field(default_factory=dict)     # what was measured, by check

    @property
    def decided_by(self) -> list:
        """The checks that set the status: the findings at the verdict's status, or (OK) the internal evidence
        that vouched for the block's shape."""
        if self.findings:
            return sorted({f.check for f in self.findings if f.status == self.status})
        return list(self.figures.get('shape', {}).get('evidence', []))

    @property
    def summary(self) -> str:
        """One line: the status and the worst reasons."""
        if not self.findings:
            return f'OK: {ok_summary(self.figures)}'
        return f'{self.status.upper()} (decided by {", ".join(self.decided_by)}): ' + \
            '; '.join(f.text for f in self.findings[:3]) + \
            (f' (+{len(self.findings) - 3} more)' if len(self.findings) > 3 else '')

    def to_dict(self) -> dict:
        return {'status': self.status, 'summary': self.summary, 'decided_by': self.decided_by,
                'findings': [f.to_dict() for f in self.findings], 'figures': self.figures}


@dataclass
class BlockInputs:
    """An adjusted block. names (N,); map_T_cam (N, 4, 4) map ENU (NaN rows: not oriented);
    fix_enu_m (N, 3) antenna positions, NaN without a fix; fix_sigma_hv_m (N, 2) stated horizontal and
    vertical sigma; noise_hv_m (2,) the estimated GNSS noise or None; rejected_fixes: names whose fix the
    adjustment did not use; ground_z_m (N,) median height (map up, m) of the tie points each camera sees,
    NaN when none; adjustment: {'status': str, 'matters': bool} of the final adjustment; excluded: photos
    left out of the block before it was adjusted (another camera), name -> reason;
    expect_nadir: whether the flight looked down (None: not known, the nadir check is skipped)."""
    names: list
    map_T_cam: np.ndarray
    fix_enu_m: np.ndarray
    fix_sigma_hv_m: np.ndarray
    ground_z_m: np.ndarray
    gnss_noise: dict = field(default_factory=dict)
    adjustment: dict = field(default_factory=dict)
    expect_nadir: bool | None = True
    n_photos: int | None = None
    excluded: dict = field(default_factory=dict)    # photo name -> why it was left out of the block
    check_rmse_hv_m: tuple | None = None            # check points: (RMSE horizontal m, vertical m, count)
    self_calibration: dict = field(default_factory=dict)  # the stepwise self-calibration's selection (to_dict())
    gnss_bias: dict = field(default_factory=dict)   # the estimated GNSS bias: {'bias_enu_m', 'settled', 'rounds',
                                                    # 'last_step_m'}; empty when it was not estimated
    georeferenced: bool | None = None               # the block was placed in the map frame (None: not known)
    gcps_in_block: int = 0                          # GCPs with a point in the block (its datum besides the GNSS)
    tie: dict = field(default_factory=dict)         # the tie points' own evidence (tie_evidence): reprojection_px,
                                                    # ray_angle_deg (median, p10), component (N,) overlap-graph part
                                                    # of each camera (-1: none); empty when not known


def inputs_from_at(at, n_photos: int | None = None, adjustment: dict | None = None,
                   expect_nadir: bool | None = True, excluded: dict | None = None,
                   thaw: bool = True) -> BlockInputs:
    """BlockInputs of an IncrementalAT `at` (core/incremental.py) after its adjustment: every keyframe,
    oriented or not; `adjustment` {'status', 'matters', 'text'} of its final adjustment. thaw False (in
    flight): keyframes spilled to disk are not read back for their ground height (it stays NaN)."""
    kfs = at.block.keyframes()
    n = len(kfs)
    T = np.full((n, 4, 4), np.nan)
    fix = np.full((n, 3), np.nan)
    sig = np.full((n, 2), np.nan)
    gz = np.full(n, np.nan)
    # The fix as a camera position: the camera centre minus the adjuster's own GNSS residual (lever arm,
    # antenna offset and estimated bias as the adjustment applies them); unoriented cameras: the fix.
    res = at.gnss_residuals([kf.kid for kf in kfs if kf.map_T_cam is not None])
    for i, kf in enumerate(kfs):
        if kf.fix_enu is not None:
            fix[i] = np.asarray(kf.fix_enu, float) - at.datum.bias_enu
            c = np.asarray(kf.fix_cov, float).reshape(3, 3)
            sig[i] = np.sqrt([0.5 * (c[0, 0] + c[1, 1]), c[2, 2]])
        if kf.map_T_cam is not None:
            T[i] = kf.map_T_cam
            if kf.kid in res:
                fix[i] = T[i, :3, 3] - res[kf.kid]
            P = at.keyframe_points(kf.kid) if thaw or not kf.frozen else np.zeros((0, 3))
            if len(P):
                gz[i] = float(np.median(P[:, 2]))
    sel = getattr(at, 'self_calibration', None)
    settle = at.rounds.settle
    bias = {'bias_enu_m': [float(v) for v in at.datum.bias_enu], **settle} if settle else {}
    return BlockInputs([kf.name for kf in kfs], T, fix, sig, gz, at.rounds.noise_estimate(), adjustment or {},
                       expect_nadir, n_photos if n_photos is not None else n, dict(excluded or {}),
                       self_calibration=sel.to_dict() if sel is not None else {}, gnss_bias=bias,
                       georeferenced=bool(at.block.georeferenced), gcps_in_block=at.gcps_in_block(),
                       tie=tie_evidence(at, thaw))


def tie_evidence(at, thaw: bool = True, max_points_per_camera: int = 400, min_shared: int = 5) -> dict:
    """The tie points' own evidence on the block of IncrementalAT `at`: {'reprojection_px': RMS over the oriented
    cameras' observations, 'ray_angle_deg': {'median', 'p10'} of the largest angle between the rays that meet
    at each tie point, 'component': (N,) the overlap-graph part of each keyframe (cameras sharing >= `min_shared`
    tie points are joined; -1 not oriented or not read), 'parts': the number of parts}. Up to
    `max_points_per_camera` observations of each camera are used (evenly spread); thaw False (in flight):
    frozen keyframes are not read."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    kfs = at.block.keyframes()
    n = len(kfs)
    sq, cnt = 0.0, 0
    rows, tids, dirs = [], [], []
    for i, kf in enumerate(kfs):
        if kf.map_T_cam is None or (kf.frozen and not thaw):
            continue
        ids, uv, active = kf.track_ids, kf.uv, kf.active
        keep = active & (ids >= 0)
        ids, uv = ids[keep], uv[keep]
        has = at.block.has_points(ids)
        ids, uv = ids[has], uv[has]
        if len(ids) > max_points_per_camera:
            pick = np.linspace(0, len(ids) - 1, max_points_per_camera).astype(int)
            ids, uv = ids[pick], uv[pick]
        if not len(ids):
            continue
        X = at.block.points_of(ids).reshape(-1, 3)
        e = at.reprojection_px(kf.map_T_cam, X, uv)
        e = e[np.isfinite(e)]
        sq, cnt = sq + float(np.sum(e ** 2)), cnt + len(e)
        d = X - np.asarray(kf.map_T_cam, float)[:3, 3]
        dirs.append(d / np.linalg.norm(d, axis=1, keepdims=True))
        rows.append(np.full(len(ids), i))
        tids.append(ids.astype(np.int64))
    out = {'reprojection_px': float(np.sqrt(sq / cnt)) if cnt else None, 'ray_angle_deg': None,
           'component': [-1] * n, 'parts': 0}
    if not rows:
        return out
    r, t, d = np.concatenate(rows), np.concatenate(tids), np.concatenate(dirs)
    u, col = np.unique(t, return_inverse=True)
    # Rays meeting at each tie point: the largest angle between one ray and the points' mean ray, twice
    # (the spread of the rays; two rays: their angle).
    mean = np.zeros((len(u), 3))
    np.add.at(mean, col, d)
    seen = np.bincount(col, minlength=len(u))
    mean /= np.linalg.norm(mean, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.sum(d * mean[col], axis=1), -1.0, 1.0)))
    spread = np.zeros(len(u))
    np.maximum.at(spread, col, ang)
    multi = 2.0 * spread[seen >= 2]
    if len(multi):
        out['ray_angle_deg'] = {'median': float(np.median(multi)), 'p10': float(np.percentile(multi, 10)),
                                'points': int(len(multi))}
    # The overlap graph: cameras x tie points, cameras joined by >= min_shared shared points.
    A = coo_matrix((np.ones(len(r)), (r, col)), shape=(n, len(u))).tocsr()
    shared = (A @ A.T).tocoo()
    strong = shared.data >= min_shared
    G = coo_matrix((np.ones(int(strong.sum())), (shared.row[strong], shared.col[strong])), shape=(n, n))
    _, labels = connected_components(G, directed=False)
    used = np.zeros(n, bool)
    used[np.unique(r)] = True
    comp = np.where(used, labels, -1)
    parts = np.unique(comp[comp >= 0])
    remap = {int(c): k for k, c in enumerate(sorted(parts, key=lambda c: -int(np.sum(comp == c))))}
    out['component'] = [remap.get(int(c), -1) for c in comp]
    out['parts'] = len(parts)
    return out


def _length(m: float) -> str:
    """A length for a finding's text: metres to 0.1 m from 1 m up, centimetres to 0.1 cm below (RTK geotags)."""
    return f'{m:.1f} m' if abs(m) >= 1.0 else f'{m * 100:.1f} cm'


def _worse(a: str, b: str) -> str:
    return a if STATUS_ORDER.index(a) >= STATUS_ORDER.index(b) else b


def _names(names, mask, most: int = 12) -> list:
    return [names[i] for i in np.flatnonzero(mask)][:most]


def tilt_from_nadir_deg(map_T_cam: np.ndarray) -> np.ndarray:
    """(N,) angle (degrees) between each camera's optical axis and straight down (map up = +z)."""
    z = np.asarray(map_T_cam, float).reshape(-1, 4, 4)[:, :3, 2]
    return np.degrees(np.arccos(np.clip(-z[:, 2], -1.0, 1.0)))


_NOT_PLACED = 'not judged: the block is not georeferenced (its frame is arbitrary)'


def _georeference(b: BlockInputs, oriented: np.ndarray, findings: list, figures: dict) -> bool:
    """Whether the block sits in the map frame; a finding when it does not."""
    n_fix = int((oriented & np.all(np.isfinite(b.fix_enu_m), axis=1)).sum())
    figures['georeference'] = {'georeferenced': b.georeferenced, 'cameras_with_fix': n_fix,
                               'gcps_in_block': int(b.gcps_in_block)}
    if b.georeferenced is not False:
        return True
    findings.append(Finding('georeference', 'failed', f'the block is not georeferenced: {n_fix} of '
                            f'{int(oriented.sum())} oriented cameras have a GNSS fix and {b.gcps_in_block} GCPs are '
                            'in it (3 cameras with a fix or 3 GCPs, not on a line, place it): its coordinates are '
                            'in an arbitrary frame of its own, not the map\'s'))
    return False


def _nadir(b: BlockInputs, o: BlockCheckOptions, T: np.ndarray, oriented: np.ndarray, names: list, findings: list,
           figures: dict) -> None:
    tilt = tilt_from_nadir_deg(T[oriented])
    near = tilt <= o.nadir_tilt_deg
    figures['nadir'] = {'share_within_deg': float(near.mean()), 'deg': o.nadir_tilt_deg,
                        'median_tilt_deg': float(np.median(tilt)), 'max_tilt_deg': float(np.max(tilt)),
                        'expected': b.expect_nadir}
    if b.expect_nadir and near.mean() < o.nadir_share_warn:
        st = 'failed' if near.mean() < o.nadir_share_fail else 'warning'
        findings.append(Finding('nadir', st, f'{100 * near.mean():.0f} % of the cameras look within '
                                f'{o.nadir_tilt_deg:g} degrees of nadir (median tilt {np.median(tilt):.0f} degrees) '
                                'on a flight that looked down', _names(np.asarray(names, object)[oriented], ~near, 50)))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(_unit(a) * _unit(b), axis=-1), -1.0, 1.0)))


def strips_of(centres_m: np.ndarray, turn_deg: float = 45.0) -> list:
    """The flight's strips: runs of consecutive cameras (in flight order, `centres_m` (N, 3)) along one heading;
    a heading change beyond `turn_deg` from the strip's first step starts a new one. Steps under a tenth of
    the median step (hovering) keep the strip. Returns a list of index arrays."""
    n = len(centres_m)
    if n < 2:
        return [np.arange(n)]
    step = np.diff(centres_m[:, :2], axis=0)
    length = np.linalg.norm(step, axis=1)
    small = length < 0.1 * max(float(np.median(length)), 1e-9)
    strips, start, heading = [], 0, None
    for i in range(n - 1):
        if small[i]:
            continue
        h = step[i] / length[i]
        if heading is None:
            heading = h
        elif np.degrees(np.arccos(np.clip(h @ heading, -1.0, 1.0))) > turn_deg:
            strips.append(np.arange(start, i + 1))
            start, heading = i + 1, None
    strips.append(np.arange(start, n))
    return strips


def _shape(b: BlockInputs, o: BlockCheckOptions, T: np.ndarray, oriented: np.ndarray, names: list, findings: list,
           figures: dict) -> bool:
    """The block's shape on the photos' own evidence: whether it failed (folded). Fills figures['shape']."""
    idx = np.flatnonzero(oriented)
    axes = T[idx, :3, 2]
    C = T[idx, :3, 3]
    med = _unit(np.median(axes, axis=0))
    ang = _angle_deg(axes, med)
    share = float(np.mean(ang <= o.nadir_tilt_deg))
    fig = {'view_axes': {'share_within_deg': share, 'deg': o.nadir_tilt_deg, 'median_deg': float(np.median(ang))}}
    evidence, text, failed = [], [], False
    nm = np.asarray(names, object)
    judged = bool(b.expect_nadir) and len(idx) >= 2 * o.min_strip
    if judged and share < o.axis_share_fail:
        failed = True
        findings.append(Finding('view_axes', 'failed', f'the cameras do not look one way: {100 * share:.0f} % of them '
                                f'within {o.nadir_tilt_deg:g} degrees of the block\'s own median axis on a flight that '
                                'looked down: the block is folded', _names(nm[idx], ang > o.nadir_tilt_deg, 50)))
    elif judged:
        evidence.append('view_axes')
    # Per strip: its cameras' median tilt from the vertical against the strips' median. The tilt's size, not its
    # direction: a camera pitched on its body looks forward on every strip, the other way on
    # the way back; a folded part of the block tilts by the fold.
    strips = [s for s in strips_of(C, o.strip_turn_deg) if len(s) >= o.min_strip]
    tilt = tilt_from_nadir_deg(T[idx])
    per = []
    if len(strips) >= 2:
        strip_tilt = np.array([np.median(tilt[st]) for st in strips])
        usual = float(np.median(strip_tilt))          # the strips' majority
        for k, st in enumerate(strips):
            per.append({'strip': k, 'photos': [str(nm[idx[st[0]]]), str(nm[idx[st[-1]]])], 'cameras': int(len(st)),
                        'tilt_from_usual_deg': float(abs(strip_tilt[k] - usual)), 'tilt_deg': float(strip_tilt[k])})
    fig['strips'] = per
    if per:
        worst = max(per, key=lambda x: x['tilt_from_usual_deg'])
        if judged and b.georeferenced is not False and worst['tilt_from_usual_deg'] > o.fold_deg:
            failed = True
            bad = [x for x in per if x['tilt_from_usual_deg'] > o.fold_deg]
            findings.append(Finding('strips', 'failed', f'{len(bad)} of {len(per)} strips tilt unlike the rest of '
                                    f'the block (by up to {worst["tilt_from_usual_deg"]:.0f} degrees, strip '
                                    f'{worst["photos"][0]}..{worst["photos"][1]}; more than {o.fold_deg:g}): the block '
                                    'is folded', [p for x in bad for p in x['photos']]))
        elif judged and b.georeferenced is not False:
            evidence.append('strips')
            text.append(f'{len(per)} strips within {worst["tilt_from_usual_deg"]:.1f} degrees of one another')
    # Leave-strip-out against the geotags (a figure): each strip's mean residual through the other strips'
    # similarity, against the geotags' scatter about that similarity / sqrt(its cameras).
    fix = b.fix_enu_m[idx]
    ok = np.all(np.isfinite(fix), axis=1)
    lso = []
    for k, st in enumerate(strips):
        rest = np.setdiff1d(np.flatnonzero(ok), st)
        st = st[ok[st]]
        if len(st) < o.min_strip or len(rest) < 4:
            continue
        sim = umeyama(C[rest], fix[rest])
        scatter = float(np.sqrt(np.mean(np.sum((sim.apply(C[rest]) - fix[rest])[:, :2] ** 2, axis=1))))
        mean_h = float(np.linalg.norm(np.mean(sim.apply(C[st]) - fix[st], axis=0)[:2]))
        lso.append({'strip': k, 'mean_h_m': mean_h, 'ratio': mean_h / max(scatter / np.sqrt(len(st)), 1e-3)})
    fig['leave_strip_out'] = lso
    t = b.tie or {}
    rp = t.get('reprojection_px')
    fig['reprojection_px'] = rp
    if rp is not None:
        if rp > o.reprojection_warn_px:
            findings.append(Finding('reprojection', 'warning', f'the tie points reproject at {rp:.2f} px RMS (more '
                                    f'than {o.reprojection_warn_px:g}): wrong matches or a wrong camera model bend '
                                    'the block'))
        else:
            evidence.append('reprojection')
            text.append(f'reprojection {rp:.2f} px')
    ra = t.get('ray_angle_deg')
    fig['ray_angle_deg'] = ra
    if ra:
        if ra['median'] < o.ray_angle_warn_deg:
            findings.append(Finding('ray_angles', 'warning', f'the tie points\' rays meet at {ra["median"]:.2f} degrees '
                                    f'(median; under {o.ray_angle_warn_deg:g}): their depth, and the block\'s shape, '
                                    'rest on little'))
        else:
            evidence.append('ray_angles')
            text.append(f'rays meeting at {ra["median"]:.0f} degrees (median)')
    comp = np.asarray(t.get('component') or [], int)
    if len(comp) == len(names):
        parts = [np.flatnonzero(comp == c) for c in range(int(t.get('parts', 0)))]
        fig['overlap_graph'] = {'parts': len(parts), 'cameras': [int(len(p)) for p in parts]}
        if len(parts) > 1:
            small = [names[i] for p in parts[1:] for i in p]
            findings.append(Finding('overlap_graph', 'warning', f'the block is {len(parts)} parts that share no tie '
                                    f'points ({", ".join(str(len(p)) for p in parts)} cameras): they are joined '
                                    'through their geotags only, and placed relative to one another no better than '
                                    'those', small[:50]))
        elif parts:
            evidence.append('overlap_graph')
            text.append('one overlap graph')
    fig['evidence'] = evidence
    fig['text'] = ', '.join(text)
    fig['failed'] = failed
    figures['shape'] = fig
    return failed


def _gnss_fit(b: BlockInputs, o: BlockCheckOptions, oriented: np.ndarray, findings: list, figures: dict) -> None:
    has = oriented & np.all(np.isfinite(b.fix_enu_m), axis=1)
    rejected = set(b.gnss_noise.get('rejected', []))
    use = has & np.array([n not in rejected for n in b.names])
    if use.sum() < 4:
        figures['gnss_fit'] = {'n': int(use.sum()), 'note': 'fewer than 4 oriented cameras with a fix: not judged'}
        return
    C = b.map_T_cam[:, :3, 3]
    sig = b.fix_sigma_hv_m[use]
    g = b.gnss_noise
    noise = np.array([g['used_h_m'], g['used_v_m']]) if g.get('used_h_m') else np.median(sig, axis=0)
    # Residuals of a robust similarity: the shape of the block against the shape of its GNSS track.
    thr = 4.0 * float(np.hypot(*noise)) + 0.05
    res = similarity_ransac(C[use], b.fix_enu_m[use], thr, np.random.default_rng(0), min_spread_ratio=0.005)
    sim = res.sim if res.ok else umeyama(C[use], b.fix_enu_m[use])
    r = sim.apply(C[has]) - b.fix_enu_m[has]
    rh, rv = np.hypot(r[:, 0], r[:, 1]), np.abs(r[:, 2])
    inl = np.array([n not in rejected for n in np.asarray(b.names, object)[has]])
    rms_h = float(np.sqrt(np.mean(rh[inl] ** 2)))
    rms_v = float(np.sqrt(np.mean(rv[inl] ** 2)))
    norm = np.sqrt((rh / (noise[0] * np.sqrt(2))) ** 2 + (rv / noise[1]) ** 2) / np.sqrt(2)
    core = norm[inl]
    # The block's fit, robust to a few bad geotags: the RMS over the 80 % best-fitting cameras.
    kept = np.sort(core)[:max(4, int(np.ceil(0.8 * len(core))))]
    fit = float(np.sqrt(np.mean(kept ** 2)))
    out = (norm > o.gnss_outlier) & inl
    figures['gnss_fit'] = {'n': int(has.sum()), 'rms_h_m': rms_h, 'rms_v_m': rms_v, 'noise_h_m': float(noise[0]),
                           'noise_v_m': float(noise[1]), 'normalised_rms': fit, 'scale': float(sim.scale),
                           'outliers': _names(np.asarray(b.names, object)[has], out, 50)}
    if fit > o.gnss_fit_warn:
        # Far beyond their noise, the geotags fail the block only when they hold to what they state (the noise
        # the adjustment estimated from them within noise_warn_factor of it): then they are evidence of its shape.
        est = [g.get('estimated_h_m'), g.get('estimated_v_m')]
        credible = None in est or (est[0] <= o.noise_warn_factor * g.get('stated_h_m', np.inf)
                                   and est[1] <= o.noise_warn_factor * g.get('stated_v_m', np.inf))
        st = 'failed' if fit > o.gnss_fit_fail and credible else 'warning'
        why = ('the block is folded, tipped or mis-matched' if st == 'failed' else
               'the geotags are poorer than they state, or the block is bent: it is placed no better than its '
               f'geotags ({_length(float(np.hypot(rms_h, rms_v)))})')
        findings.append(Finding('gnss_fit', st, f'the block\'s shape disagrees with its own GNSS: cameras '
                                f'{rms_h:.2f} m H / {rms_v:.2f} m V from it after a similarity, {fit:.1f}x the GNSS '
                                f'noise ({noise[0]:.2f} m H, {noise[1]:.2f} m V): {why}', []))
    if out.any():
        worst = np.argsort(-norm[out])
        names = [np.asarray(b.names, object)[has][out][i] for i in worst]
        findings.append(Finding('gnss_outliers', 'warning',
                                f'{int(out.sum())} geotags lie far from where the block puts their photos (more than '
                                f'{o.gnss_outlier:g}x the GNSS noise; up to {_length(rh[out].max())} H, '
                                f'{_length(rv[out].max())} V): glitched geotags or photos of another site: {", ".join(names[:8])}', names[:50]))


def _dome(b: BlockInputs, o: BlockCheckOptions, oriented: np.ndarray, findings: list, figures: dict) -> None:
    if not (b.adjustment or {}).get('status'):
        return   # a block in flight between full adjustments: its window updates leave it bent until the next one
    rejected = set(b.gnss_noise.get('rejected', []))
    use = oriented & np.all(np.isfinite(b.fix_enu_m), axis=1) & np.array([n not in rejected for n in b.names])
    if use.sum() < 7:
        return
    C = b.map_T_cam[use, :3, 3]
    F = b.fix_enu_m[use]
    bowl = height_bowl(F[:, :2], C[:, 2] - F[:, 2])
    # The geotags' scatter at least 1 cm (heights are written to the centimetre at best).
    scatter = max(bowl['scatter_m'], 0.01)
    ratio = abs(bowl['rise_m']) / scatter
    rs = bowl['rise_sigma_m']
    t = abs(bowl['rise_m']) / rs if np.isfinite(rs) and rs > 0 else 0.0
    figures['dome'] = {**bowl, 'rise_sigma_m': rs if np.isfinite(rs) else None, 'ratio_to_scatter': ratio,
                       'ratio_to_sigma': t}
    if ratio > o.dome_warn_ratio and t > o.dome_warn_ratio and abs(bowl['rise_m']) > o.dome_warn_m:
        sel = b.self_calibration or {}
        how = (f' (the stepwise self-calibration kept {", ".join(sel.get("kept", [])) or "none"} of '
               f'{", ".join(sel.get("candidates", []))})' if sel else '')
        shape = 'dome' if bowl['rise_m'] < 0 else 'bowl'
        findings.append(Finding('dome', 'warning', f'the block is bent: its cameras {shape} against their geotag '
                                f'heights by {bowl["rise_m"]:+.2f} m at the block\'s radius '
                                f'({bowl["radius_m"]:.0f} m), {ratio:.1f}x the geotags\' own scatter about that '
                                f'surface ({bowl["scatter_m"]:.3f} m) and {t:.1f}x its standard error; likely cause: '
                                'self-calibrated radial distortion in a flat nadir block of '
                                f'parallel lines{how}, which trades off with the block\'s curvature (fly cross '
                                'lines or add GCPs with heights; a calibrated camera)'))


def check_block(b: BlockInputs, o: BlockCheckOptions | None = None) -> BlockVerdict:
    """The verdict on the adjusted block `b` (see the module docstring)."""
    o = o or BlockCheckOptions()
    findings, figures = [], {}
    T = np.asarray(b.map_T_cam, float).reshape(-1, 4, 4)
    names = list(b.names)
    oriented = np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)
    n_photos = b.n_photos if b.n_photos is not None else len(names)
    n_or = int(oriented.sum())
    figures['oriented'] = {'oriented': n_or, 'photos': int(n_photos)}
    if n_or == 0:
        findings.append(Finding('oriented', 'failed', f'nothing oriented (0 of {n_photos} photos)'))
        return BlockVerdict('failed', findings, figures)
    share = n_or / max(n_photos, 1)
    if share < o.min_oriented_warn:
        # Photos left unoriented are named (a photo of another site, a blurred one): a warning, and under
        # min_oriented_failed of them oriented the block failed.
        st = 'failed' if share < o.min_oriented_failed else 'warning'
        findings.append(Finding('oriented', st, f'{n_or} of {n_photos} photos oriented',
                                _names(names, ~oriented, 50)))
    if b.excluded:
        why = sorted(set(b.excluded.values()))
        findings.append(Finding('photos_not_used', 'warning', f'{len(b.excluded)} photos left out of the block '
                                f'({"; ".join(why)}): {", ".join(list(b.excluded)[:8])}', list(b.excluded)[:50]))
    shape_failed = _shape(b, o, T, oriented, names, findings, figures)
    _gnss_fit(b, o, oriented, findings, figures)
    placed = _georeference(b, oriented, findings, figures)
    # Rigid: the adjusted cameras against their fixes as they are.
    rejected = set(b.gnss_noise.get('rejected', []))
    has = oriented & np.all(np.isfinite(b.fix_enu_m), axis=1) & np.array([n not in rejected for n in names])
    if has.any() and placed:
        r = T[has, :3, 3] - b.fix_enu_m[has]
        rh, rv = np.hypot(r[:, 0], r[:, 1]), np.abs(r[:, 2])
        figures['gnss_rigid'] = {'rms_h_m': float(np.sqrt(np.mean(rh ** 2))), 'rms_v_m': float(np.sqrt(np.mean(rv ** 2)))}
        g = b.gnss_noise
        noise = (np.array([g['used_h_m'], g['used_v_m']]) if g.get('used_h_m')
                 else np.median(b.fix_sigma_hv_m[has], axis=0))
        norm = np.sort(np.sqrt((rh / (noise[0] * np.sqrt(2))) ** 2 + (rv / noise[1]) ** 2) / np.sqrt(2))
        fit = float(np.sqrt(np.mean(norm[:max(1, int(np.ceil(0.8 * len(norm))))] ** 2)))
        figures['gnss_rigid']['normalised_rms'] = fit
        if has.sum() >= 4 and fit > o.gnss_fit_warn:
            findings.append(Finding('gnss_rigid', 'failed' if fit > o.gnss_fit_fail else 'warning',
                                    f'the adjusted cameras sit {figures["gnss_rigid"]["rms_h_m"]:.2f} m H / '
                                    f'{figures["gnss_rigid"]["rms_v_m"]:.2f} m V from their own GNSS, {fit:.1f}x its '
                                    'noise: the georeference is off'))
    # The ground below the cameras.
    gz = np.asarray(b.ground_z_m, float).reshape(-1)
    seen = oriented & np.isfinite(gz)
    if seen.any() and placed:
        below = T[seen, 2, 3] > gz[seen]
        figures['ground_below'] = {'share': float(below.mean()), 'n': int(seen.sum()),
                                   'median_height_above_ground_m': float(np.median(T[seen, 2, 3] - gz[seen]))}
        if below.mean() < o.ground_below_fail:
            findings.append(Finding('ground_below', 'failed',
                                    f'the ground lies above or beside {int((~below).sum())} of {int(seen.sum())} '
                                    'cameras (their tie points are not below them): the block is tipped over',
                                    _names(np.asarray(names, object)[seen], ~below, 50)))
    # Nadir.
    if placed:
        _nadir(b, o, T, oriented, names, findings, figures)
    else:
        figures['nadir'] = {'note': _NOT_PLACED}
        figures['ground_below'] = {'note': _NOT_PLACED}
    # Convergence.
    adj = b.adjustment or {}
    figures['adjustment'] = dict(adj)
    if adj.get('status') in ('failed', 'diverged'):
        findings.append(Finding('convergence', 'failed', f'the final adjustment {adj["status"]}'))
    elif adj.get('matters'):
        findings.append(Finding('convergence', 'warning', adj.get('text') or 'the final adjustment did not converge '
                                'and would still move cameras'))
    # The GNSS bias against the GCPs.
    if b.gnss_bias:
        figures['gnss_bias'] = dict(b.gnss_bias)
        if not b.gnss_bias['settled']:
            findings.append(Finding('gnss_bias', 'warning', f'the GNSS bias against the GCPs did not settle in '
                                    f'{b.gnss_bias["rounds"]} adjustments (its last step '
                                    f'{_length(b.gnss_bias["last_step_m"])}): the block sits between its GCPs and '
                                    'its fixes to about that'))
    # Check points: surveyed truth the block did not use. Far beyond the noise the block's datum carries
    # (its GNSS, at least 2 cm), the block or the control is wrong.
    if b.check_rmse_hv_m is not None:
        h, v, n_chk = b.check_rmse_hv_m
        g0 = b.gnss_noise
        ok_fix = np.all(np.isfinite(b.fix_sigma_hv_m), axis=1)
        noise = (np.array([g0['used_h_m'], g0['used_v_m']]) if g0.get('used_h_m') else
                 np.median(b.fix_sigma_hv_m[ok_fix], axis=0) if ok_fix.any() else np.array([0.02, 0.02]))
        noise = np.maximum(noise, 0.02)
        ratio = float(max(h / noise[0], v / noise[1]))
        figures['check_points'] = {'rmse_h_m': h, 'rmse_v_m': v, 'n': n_chk, 'ratio_to_noise': ratio}
        if ratio > o.check_warn:
            findings.append(Finding('check_points', 'failed' if ratio > o.check_fail else 'warning',
                                    f'the {n_chk} check points disagree with the block by {h:.2f} m H / {v:.2f} m V, '
                                    f'{ratio:.0f}x the noise of its datum ({noise[0]:.2f} m H, {noise[1]:.2f} m V): '
                                    'the block or the control file is wrong'))
    if placed:
        _dome(b, o, oriented, findings, figures)
    # GNSS noise.
    g = b.gnss_noise
    rejected = list(g.get('rejected', []))
    if g.get('estimated_h_m') is not None and g.get('n'):
        stated = np.array([g['stated_h_m'], g['stated_v_m']])
        est = np.array([g['estimated_h_m'], g['estimated_v_m']])
        figures['gnss_noise'] = dict(g)
        poor = est > o.noise_warn_factor * stated
        lev = g.get('level') or {}
        tilted = float(lev.get('gnss_tilt_deg', 0.0)) - float(lev.get('kept_tilt_deg', 0.0))
        if poor.any() or tilted > o.level_warn_deg:
            why = []
            if poor.any():
                why.append('poorer than they state')
            if tilted > o.level_warn_deg:
                why.append(f'their heights would tilt the block by {lev["gnss_tilt_deg"]:.1f} degrees where its '
                           f'cameras look down: levelled to {lev["kept_tilt_deg"]:.1f} degrees')
            findings.append(Finding('gnss_noise', 'warning', f'the geotags are poor ({"; ".join(why)}): estimated '
                                    f'noise {_length(est[0])} horizontal, {_length(est[1])} vertical (stated '
                                    f'{_length(stated[0])}, {_length(stated[1])}); they were weighted as measured, and '
                                    'the block is placed no better than they are'))
        # Beyond noise_h_far_m the block's place is as poor as its geotags, even when they state nearly as much.
        if est[0] > o.noise_h_far_m and not shape_failed:
            shape = figures['shape'].get('text') or 'no internal evidence against it'
            findings.append(Finding('geotags_far', 'warning', f'the cameras scatter {est[0]:.1f} m horizontally about '
                                    'their geotags after a similarity (a compact camera\'s or a phone\'s GPS does); '
                                    f'the block\'s shape holds by its own evidence ({shape}): it is placed no better '
                                    f'than its geotags ({est[0]:.0f} m)'))
    if rejected:
        findings.append(Finding('gnss_rejected', 'warning', f'{len(rejected)} geotags not used, far beyond the '
                                f'flight\'s GNSS noise from where the block puts their photos (a glitched geotag, or a '
                                f'photo the tie points place poorly): {", ".join(rejected[:8])}', rejected[:50]))
    status = 'ok'
    for f in findings:
        status = _worse(status, f.status)
    findings.sort(key=lambda f: -STATUS_ORDER.index(f.status))
    return BlockVerdict(status, findings, figures)
