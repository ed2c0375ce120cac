"""What the adjuster's segments say on /diagnostics after a keyframe (stages/adjustment.py): why a waiting segment's
tie points do not join it yet, and how a join was made."""

from photogram_ros.stages.report import WARN


def segment_diagnostics(diag, segments, joined: int) -> None:
    """/diagnostics of the adjuster's segments after a keyframe: why a waiting segment's tie points do not join
    it yet (`segment_join_ties`), and the join of `joined` keyframes (a WARN when only the GNSS joined them)."""
    if segments.current is not None:
        diag.set('segment_join_ties', _fit_text(segments.last_join_try()))
    if joined:
        diag.count('keyframes_joined_from_a_segment', joined)
        text, tied = _join_text(joined, (segments.joins_made() or [{'through': 'gnss'}])[-1])
        diag.set('last_segment_join', text)
        if not tied:
            diag.problem(text, WARN)


def _join_text(n: int, join: dict) -> tuple[str, bool]:
    """What a segment's join says (core/at_segments.Segments.joins_made), and whether tie points tied it."""
    if join['through'] == 'ties':
        return f'{n} keyframes after a break in the tracks joined the block through {join["ties"]} tie points', True
    if join['through'] == 'mtp':
        return (f'every track was lost: {n} keyframes after the break joined the block through {join["mtps"]} manual '
                'tie points'), True
    return (f'every track was lost: {n} keyframes after the break were oriented as a segment of their own and joined '
            'the block through their GNSS (no tie point links the two: their relative accuracy is the GNSS\'s; '
            f'{_fit_text(join)})'), False


def _fit_text(fit: dict) -> str:
    """A segment's last try through the tracker's tie points (core/at_segments.Segments.last_join_try), in words."""
    return (f'tracker ids shared with the block: {fit.get("shared_observed", 0)} seen in both, '
            f'{fit.get("shared_points", 0)} triangulated in both, {fit.get("inliers", 0)} fitting'
            + (f': {fit["why"]}' if fit.get('why') else ''))
