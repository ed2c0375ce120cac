"""The adjustment stage's count of keyframes not oriented, by reason (stages/adjustment.py)."""


class NotOrientedCounts:
    """keyframes_not_oriented and a counter per reason (not_oriented_<status>, e.g.
    not_oriented_too_few_known_points) that the flight report lists; a keyframe counted so on arrival that a
    later step orients (it waited) is taken out again, so that oriented plus not oriented stays the keyframes
    processed (a replay's backpressure and the report count on it)."""

    def __init__(self, diag):
        self.diag = diag
        self._why: dict[int, str] = {}   # stamp -> the reason it was counted under

    def count(self, status: str, stamp_ns: int) -> None:
        self.diag.count('keyframes_not_oriented')
        reason = status.split(' (')[0].strip().replace(' ', '_') or 'unknown'
        self.diag.count(f'not_oriented_{reason}')
        self._why[stamp_ns] = reason

    def oriented_since(self, block, n: int) -> None:
        """The step oriented the newest `n` of `block`'s registered keyframes."""
        for kid in block.registered[-n:] if n > 0 else []:
            reason = self._why.pop(block.keyframe(kid).stamp_ns, None)
            if reason is not None:
                self.diag.count('keyframes_not_oriented', -1)
                self.diag.count(f'not_oriented_{reason}', -1)

    def at_end(self, block) -> None:
        """End of flight: each keyframe `block` holds not oriented, counted under its final reason
        (not_oriented_at_end_<reason>, io/flight_verdict): the reason it was counted under in flight, else
        given_up_after_being_oriented (oriented once, given up since: before an early break)."""
        for kf in block.keyframes():
            if kf.map_T_cam is None:
                self.diag.count('not_oriented_at_end_' + self._why.get(kf.stamp_ns, 'given_up_after_being_oriented'))
