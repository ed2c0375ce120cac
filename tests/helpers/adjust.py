"""The incremental aerial triangulation of simulated keyframes, as the block-check tests run it."""

from __future__ import annotations

from photogram_ros.core.incremental import IncrementalAT, IncrementalOptions


def adjust_keyframes(sk, records, **opt):
    """(IncrementalAT, the full adjustment's StepReport) of `records` of the simulated keyframes `sk`
    (sim.observations.simulate_keyframes), with its lever arm and origin; `opt`: IncrementalOptions."""
    at = IncrementalAT(sk.camera, IncrementalOptions(lever_arm_cam_m=tuple(sk.lever_arm_cam_m), **opt),
                       origin=sk.origin)
    for r in records:
        at.add_keyframe(r)
    return at, at.full_adjustment()
