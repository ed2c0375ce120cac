"""The flight's verdict: keyframes taken, oriented and why not (the nodes' counters), the DSM's measured share
and what one stereo pair says of its interpolated cells, and whether the flight mapped (io/flight_report puts
them at the top of the report; replay and run print keyframes_line and the verdict's sentences).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

MIN_ORIENTED_SHARE = 0.5     # fewer keyframes oriented than this: the flight did not map
MIN_DSM_VALID_SHARE = 0.5    # a DSM with fewer cells holding a height than this is a warning
FAILED_DSM_VALID_SHARE = 0.1  # ... and with fewer than this, the flight did not map
# The products against what the oriented photos saw (export.json dsm.footprint: the camera centres' hull widened
# by a quarter of the flying height, io/export_raster.surface_in_crs). Stereo seeing less than half of it (cells it
# measured, and interpolated cells one pair's heights check) is a warning: the widening stays inside a nadir photo's footprint at any usual field of view (a 60 degree lens sees
# 0.58 of the height either side), so a block that mapped measures most of it (the simulator's sample flight, whose
# lines' ends and margins fill the rest, over 80 %); half is where the products stop being the block's map and
# become a patch of it (seneca's every other photo before one-pair cells: a 34 x 37 m patch of a 300 x 250 m block).
MIN_FOOTPRINT_SHARE = 0.5
# More than this share of the footprint's measured cells from one stereo pair that no second pair confirmed is a
# warning: a 60 % forward overlap survey's DSM, sound where the one pair is (its cells are kept only where they
# agree with their neighbours), but no second look checked it for a gross mismatch.
MAX_ONE_PAIR_SHARE = 0.5
NOT_ORIENTED_PREFIX = 'not_oriented_'   # bundle_node counters per reason (not_oriented_<reason>), when it has them
# The adjuster's count at the end of the flight, per reason, of the keyframes it still holds not oriented
# (not_oriented_at_end_<reason>), when it has them: each keyframe's final reason, where the counters above are
# the reasons given in flight (a later step orients some of those keyframes: a segment joined, the final
# adjustment's second chance).
AT_END_PREFIX = 'not_oriented_at_end_'
# The end-of-flight reason of a keyframe oriented once and given up since (not counted not oriented in flight).
GIVEN_UP_AT_END = 'given_up_after_being_oriented'
# Per-reason counters that hold at the end by how they are counted (from the map folder, not in flight).
FINAL_REASONS = ('taken_before_the_restart_without_a_pose',)
UNPLACED_REASON = 'given up: before an early break (a line too short for its GNSS)'
ADJUSTER_REASON = 'not oriented by the bundle adjuster'


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def keyframe_accounting(counts: dict, oriented: int, bundle_status: str | None = None,
                        frames_unusable: int | None = None) -> dict:
    """Keyframes taken (the tracker's count), oriented (`oriented`: those with an adjusted, georeferenced
    pose in the map, which the products use), not oriented (taken minus oriented) and why, from the nodes'
    counters (`counts`: role -> Graph.counts()). `keyframes_not_oriented_by_reason` adds up to
    `keyframes_not_oriented`.

    Reasons: never reached the adjuster, failed there, taken before a restart without a pose (final by how
    they are counted); then, with the adjuster's end-of-flight counters (AT_END_PREFIX), each keyframe's
    final reason. Without those, the adjuster's reasons are the ones it gave in flight
    (`keyframes_not_oriented_in_flight` and `..._in_flight_by_reason`, with the keyframes given up before an
    early break and those oriented in flight without a georeferenced pose in the map): when they add up to the
    keyframes still missing they are the reasons; when they count more (a later step oriented some of them),
    `keyframes_oriented_after_the_window_gave_up` says how many more, and the keyframes still missing are
    counted under ADJUSTER_REASON. What no counter explains is 'unaccounted'. `bundle_status`: the adjuster's
    last status on /diagnostics, named when it has no counter per reason; `frames_unusable`: the tracker's
    unusable_frames on /diagnostics."""
    tr, b = counts.get('tracker', {}), counts.get('bundle', {})
    taken = int(tr.get('keyframes', 0))
    missing = max(0, taken - int(oriented))
    out = {'keyframes_taken': taken, 'keyframes_oriented': int(oriented),
           'keyframes_oriented_in_flight': int(b.get('keyframes_oriented', 0))}
    if frames_unusable is not None:
        out['frames_unusable'] = int(frames_unusable)
    for key in ('frames_tracked', 'keyframes_without_fix'):
        if key in tr:
            out[key] = int(tr[key])
    for key in ('keyframes_joined_from_a_segment', 'keyframes_oriented_at_end'):
        if _number(b.get(key)):
            out[key] = int(b[key])
    at_end = {k[len(AT_END_PREFIX):]: int(v) for k, v in b.items() if k.startswith(AT_END_PREFIX) and _number(v)}
    per_reason = {k[len(NOT_ORIENTED_PREFIX):]: int(v) for k, v in b.items()
                  if k.startswith(NOT_ORIENTED_PREFIX) and not k.startswith(AT_END_PREFIX) and _number(v)}
    sure = {}
    if 'bundle' in counts:
        sure['never reached the bundle adjuster'] = max(0, taken - int(b.get('keyframes_received', 0)))
    sure['failed in the bundle adjuster (an error, see the problems)'] = int(b.get('keyframes_failed', 0))
    sure.update({f'not oriented: {k.replace("_", " ")}': per_reason.pop(k) for k in FINAL_REASONS if k in per_reason})
    why = {k: v for k, v in sure.items() if v}
    if at_end:
        why.update({(UNPLACED_REASON if k == GIVEN_UP_AT_END else f'not oriented: {k.replace("_", " ")}'): v
                    for k, v in at_end.items() if v})
        # The adjuster holds them oriented, the map has no georeferenced pose for them.
        why['oriented by the bundle adjuster, no georeferenced pose in the map'] = max(0, missing - sum(why.values()))
        why = {k: v for k, v in why.items() if v}
    else:
        if per_reason:
            in_flight = {f'not oriented: {k.replace("_", " ")}': v for k, v in per_reason.items()}
        else:
            in_flight = {ADJUSTER_REASON + (f' (its last status: {bundle_status})' if bundle_status else ''):
                         int(b.get('keyframes_not_oriented', 0))}
        # Keyframes before an early break that their GNSS could not place, given up for the flight after it.
        unplaced = int(b.get('keyframes_unplaced', 0))
        in_flight[UNPLACED_REASON] = unplaced
        in_flight['oriented in flight, no georeferenced pose in the map'] = max(
            0, out['keyframes_oriented_in_flight'] - int(oriented) - unplaced)
        in_flight = {k: v for k, v in in_flight.items() if v}
        flight_n, rest = sum(in_flight.values()), max(0, missing - sum(why.values()))
        out['keyframes_not_oriented_in_flight'] = flight_n
        out['keyframes_not_oriented_in_flight_by_reason'] = in_flight
        if flight_n <= rest:
            why.update(in_flight)
        else:
            # A later step (a segment joined, the final adjustment's second chance) oriented some of them: which
            # reason each keyframe still missing had is not counted.
            out['keyframes_oriented_after_the_window_gave_up'] = flight_n - rest
            if rest:
                why[ADJUSTER_REASON] = rest
    counted = sum(why.values())
    if counted < missing:
        why['unaccounted (no node counted why)'] = missing - counted
    out['keyframes_not_oriented'] = missing
    out['keyframes_not_oriented_by_reason'] = why if missing else {}
    return out


def not_oriented_text(acc: dict) -> str:
    """'K not oriented' and its reasons in words, from keyframe_accounting: '4 not oriented: 4 by the bundle
    adjuster (in flight 13 were not oriented, for: ...; 9 of them oriented later by segment joins and the final
    adjustment's second chance)'."""
    k = acc.get('keyframes_not_oriented', 0)
    if not k:
        return '0 not oriented'
    def short(reason):
        return reason.removeprefix('not oriented: ').removeprefix('not oriented ').replace('given up:', 'given up')
    parts = []
    for reason, n in acc['keyframes_not_oriented_by_reason'].items():
        part = f'{n} {short(reason)}'
        if reason == ADJUSTER_REASON:
            flight = acc.get('keyframes_not_oriented_in_flight_by_reason', {})
            by = [name for key, name in (('keyframes_joined_from_a_segment', 'segment joins'),
                                         ('keyframes_oriented_at_end', "the final adjustment's second chance"))
                  if acc.get(key)]
            part += (f" (in flight {acc.get('keyframes_not_oriented_in_flight', 0)} were not oriented, for: "
                     + ', '.join(f'{v} {short(r)}' for r, v in flight.items())
                     + f"; {acc.get('keyframes_oriented_after_the_window_gave_up', 0)} of them oriented later by "
                     + (' and '.join(by) if by else 'a later step') + ')')
        parts.append(part)
    return f'{k} not oriented: ' + '; '.join(parts)


def keyframes_line(acc: dict) -> str:
    """The console's keyframe line: taken, oriented, not oriented with the reasons (not_oriented_text)."""
    return (f"keyframes: {acc.get('keyframes_taken', 0)} taken, {acc.get('keyframes_oriented', 0)} oriented, "
            + not_oriented_text(acc))


def dsm_valid_share(dsm_path) -> float | None:
    """Share of the mapped area's DSM cells that hold a measured height: cells inside the convex hull of
    the cells with a height (a diagonal strip's raster rectangle is half empty by its shape, not by a
    failure) whose band 2 (stereo pairs, core export: 0 where interpolated) is at least 1; every cell
    with a height when the DSM has one band. None without a DSM file, 0 for a DSM without a height."""
    if not dsm_path or not Path(dsm_path).exists():
        return None
    import cv2
    import rasterio
    with rasterio.open(dsm_path) as ds:
        z = ds.read(1, masked=True)
        pairs = ds.read(2) if ds.count >= 2 else None
    valid = ~np.ma.getmaskarray(z) & np.isfinite(np.ma.getdata(z))
    if pairs is not None:
        valid &= pairs >= 1
    if valid.sum() < 3:
        return 0.0
    hull = np.zeros(valid.shape, np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(np.argwhere(valid)[:, ::-1].astype(np.int32)), 1)
    return float(valid[hull > 0].mean())


def dsm_one_pair_evidence(dsm_path) -> dict | None:
    """What one stereo pair measured of the DSM's interpolated cells, from the export.json beside dsm.tif
    (io/export: dsm.camera_hull.filled_one_pair, dsm.one_pair_check, dsm.max_spread_m as the tolerance);
    None without it."""
    if not dsm_path:
        return None
    try:
        dsm = json.loads((Path(dsm_path).parent / 'export.json').read_text()).get('dsm') or {}
    except (OSError, ValueError):
        return None
    check = dsm.get('one_pair_check') or {}
    if not check.get('cells'):
        return None
    return {'share': float((dsm.get('camera_hull') or {}).get('filled_one_pair', 0.0)),
            'median_abs_dz_m': float(check['median_abs_dz_m']), 'p90_abs_dz_m': float(check['p90_abs_dz_m']),
            'tolerance_m': float(dsm.get('max_spread_m', 0.0))}


def dsm_footprint_cover(dsm_path) -> dict | None:
    """The DSM over the cameras' footprint, from the export.json beside dsm.tif (io/export: dsm.footprint):
    {'cells', 'measured' (any pairs), 'measured_one_pair', 'filled_one_pair' (interpolated near confirmed cells,
    where one pair's heights check the interpolation), 'valid'} as shares of the footprint's cells; None without
    it (an export before the footprint was measured)."""
    if not dsm_path:
        return None
    try:
        foot = (json.loads((Path(dsm_path).parent / 'export.json').read_text()).get('dsm') or {}).get('footprint')
    except (OSError, ValueError):
        return None
    if not foot or not foot.get('cells'):
        return None
    return {k: foot[k] for k in ('cells', 'measured', 'measured_one_pair', 'filled_one_pair', 'valid') if k in foot}


def footprint_warnings(footprint: dict | None) -> list[str]:
    """The verdict's warnings on the DSM against the cameras' footprint (dsm_footprint_cover): stereo saw under
    MIN_FOOTPRINT_SHARE of it (the cells it measured, and the interpolated ones one pair's heights check); over
    MAX_ONE_PAIR_SHARE of what it measured is one unconfirmed pair's."""
    if not footprint or not footprint.get('cells'):
        return []
    measured, one = float(footprint.get('measured', 0.0)), float(footprint.get('measured_one_pair', 0.0))
    checked = float(footprint.get('filled_one_pair', 0.0))
    said = (f"stereo measured {measured * 100:.1f} % of the cameras' footprint (the camera centres' hull widened by "
            f"a quarter of the flying height: what the oriented photos saw), {one * 100:.1f} % of it from one stereo "
            f"pair that no second pair confirmed")
    why_one = ('too little overlap for a second pair: it needs three photos of a spot along a line, over 67 % '
               'forward overlap, or the band two lines share; a one-pair cell is kept only where it agrees with its '
               'neighbours, no second look checked it')
    mostly_one = measured > 0 and one > MAX_ONE_PAIR_SHARE * measured
    if measured + checked < MIN_FOOTPRINT_SHARE:
        return [f"the products cover little of what the photos saw: {said}; the rest is interpolated "
                f"({checked * 100:.1f} % of the footprint near confirmed cells, where one pair's heights check "
                f"the interpolation; {float(footprint.get('valid', 0.0)) * 100:.1f} % holds a height)"
                + (f'; most of what stereo measured rests on one pair ({why_one})' if mostly_one else '')]
    return [f'most of the DSM rests on one stereo pair: {said} ({why_one})'] if mostly_one else []


def mapping_verdict(accounting: dict, georeferenced: bool, dsm_share: float | None, mapped_products: bool,
                    products_error: str | None = None, dsm_one_pair: dict | None = None,
                    block_check: dict | None = None, footprint: dict | None = None) -> dict:
    """{'mapped': bool, 'failures': [sentences], 'warnings': [sentences]}: a flight with no georeferenced
    keyframe, fewer than half of its keyframes oriented, products that could not be made (`products_error`:
    why), or a DSM nearly empty (or none while keyframes were oriented) did not map; a DSM measured by stereo
    over under MIN_DSM_VALID_SHARE of its area (trees, water, low overlap: the rest interpolated) mapped, with a
    warning. A DSM that two agreeing pairs measured over under FAILED_DSM_VALID_SHARE of its area mapped, with a
    warning, when one pair measured enough more of it and agrees with its interpolated heights (`dsm_one_pair`:
    export.json's dsm.camera_hull.filled_one_pair as 'share' and dsm.one_pair_check, with 'tolerance_m' the
    DSM's max_spread_m): a survey flown with one pair per spot (60 % forward overlap) has no second pair to
    check with, and the one pair is the evidence there is. `block_check`: the adjuster's check of the block
    after its final adjustment ({'status': 'ok' | 'warning' | 'failed', 'summary': its line}; bundle_node's
    final_verdict on /diagnostics): a failed block (folded, far from its GNSS, not converged where it
    matters) did not map, whatever its DSM looks like; a warning is the flight's warning. `footprint`: the DSM
    over the cameras' footprint (dsm_footprint_cover): warnings when stereo measured little of it, or when one
    unconfirmed pair measured most of it (footprint_warnings); the verdict carries it as 'dsm_footprint'.
    `dsm_share` counts every cell stereo measured (band 2 >= 1: one pair too, where no confirmed cell is near)."""
    failures, warnings = [], []
    check = block_check or {}
    if check.get('status') == 'failed':
        failures.append(f"the adjuster's final check of the block failed: {check.get('summary') or 'no reason given'}")
    elif check.get('status') == 'warning':
        warnings.append(f"the adjuster's final check of the block warns: {check.get('summary') or 'no reason given'}")
    taken, oriented = accounting['keyframes_taken'], accounting['keyframes_oriented']
    if taken == 0:
        frames, unusable = accounting.get('frames_tracked'), accounting.get('frames_unusable')
        failures.append('the tracker took no keyframe' + (f' from {frames} frames' if frames is not None else '')
                        + (f' ({unusable} unusable: too few features to track)' if unusable else ''))
    if not georeferenced:
        failures.append('no georeferenced keyframe: no map origin, no products')
    if taken and oriented < MIN_ORIENTED_SHARE * taken:
        failures.append(f'only {oriented} of {taken} keyframes ({100.0 * oriented / taken:.0f} %) were oriented '
                        f'(at least {MIN_ORIENTED_SHARE * 100:.0f} % are needed)')
    if dsm_share is not None and dsm_share < MIN_DSM_VALID_SHARE:
        said = (f'{dsm_share * 100:.1f} % of the DSM\'s cells over the mapped area (the convex hull of its '
                f'measured heights) hold a height measured by stereo (dsm.tif band 2; the rest is interpolated)')
        one = dsm_one_pair or {}
        share_one, median_m = one.get('share') or 0.0, one.get('median_abs_dz_m')
        one_said = ''
        if share_one > 0 and median_m is not None:
            one_said = (f'; one stereo pair measured {share_one * 100:.1f} % of the camera hull\'s cells too, '
                        f'{median_m:.2f} m from the interpolated heights (median; p90 {one.get("p90_abs_dz_m", 0):.2f} '
                        f'm): no second pair checked them')
        agrees = median_m is not None and median_m <= one.get('tolerance_m', 0.0)
        if dsm_share < FAILED_DSM_VALID_SHARE and not (agrees and dsm_share + share_one >= FAILED_DSM_VALID_SHARE):
            failures.append(f'the DSM is nearly empty: {said}' + one_said
                            + (' (more than the DSM\'s spread limit: the interpolation is not what stereo saw)'
                               if one_said and not agrees else ''))
        else:
            warnings.append(f'the DSM is interpolated over much of its area: only {said}{one_said} (trees, water and '
                            'plain roofs give stereo no height; or too little overlap: a second pair needs three photos '
                            'of a spot along a line, over 67 % forward overlap, or the band two lines share)')
    elif dsm_share is None and georeferenced and mapped_products:
        failures.append('no DSM was written')
    if products_error:
        failures.append(f'no products were made: {products_error}')
    out = {'mapped': not failures, 'failures': failures, 'warnings': warnings, 'dsm_valid_share': dsm_share}
    if footprint:
        warnings += footprint_warnings(footprint)
        out['dsm_footprint'] = footprint
    return out
