"""Ground control in flight, checked before the adjustment leans on it.

The tracker's marker detections are control rows of their own kind: one per keyframe and target. A GCP
with a wrong coordinate or a placeholder height (0 or 400 m, from a surveyor without heights) would bend
the block in flight just as it does after the flight. So every target is held as a check point (it
builds no geometry and the adjustment does not see it) until both of these hold:
- the block is georeferenced for good (not provisionally, as on a straight first line);
- `min_keyframes` oriented keyframes have seen it (one, at the end of the flight).

A flight that ends without such a block (it never turned: the GNSS leaves the roll about its line
undetermined, and only the GCPs fix it) takes its control as given at the end (`unchecked_vetting`), and
says so; only a height the file itself shows to be a placeholder is then used horizontally only.

Otherwise `vet_control` (core/control.py) checks the target's detections and its survey against the block
as the GNSS alone has placed it, just as `triangulate` does after the flight:
- a detection far from where the others intersect is taken out (a misread marker, or a second board
  with the same id);
- a GCP that the block contradicts horizontally is not used;
- a GCP whose height the block contradicts far beyond both sigmas is used horizontally only.

A GCP that passes gets its point and its prior (IncrementalAT.triangulate_targets). The verdict is final:
from then on the adjustment leans on the GCP, and it is no longer a fair judge of it. Later detections of
an admitted GCP are checked by the adjuster itself (it drops an observation far from its point). Check
points are vetted in the same way, for their rows and notes; they never enter the adjustment.

`LiveControl` provides:
- `observe(kid, target_uv)`: a keyframe's detections (target name -> distorted pixel);
- `set_surveyed(control)`: the surveyed points in the map frame, once its origin is known;
- `adjuster_control()`: the ControlPoints to give the adjuster (IncrementalAT.set_control);
- `update(at, final)`: vets the targets now due and applies the verdicts to the adjuster; returns the
  new faults, one sentence each;
- `vetting`: every detection's fate and every point's use so far (core.control.ControlVetting);
- `observations(name, registered)`: the detections of a target that are kept, for its figures;
- `use_of(name)` and `summary()`: where each target stands ('held', 'full', 'horizontal', 'unused',
  'check', 'not_seen').
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from photogram_ros.core.control import (ControlRow, ControlVetting, ControlVettingOptions, unchecked_vetting,
                                        vet_control)
from photogram_ros.core.at_block import ControlPoint
from photogram_ros.core.incremental import IncrementalAT
from photogram_ros.params import param


@dataclass
class LiveControlOptions(ControlVettingOptions):
    """When a target seen in flight is checked and, if it is a GCP that passes, used (and how: the
    vetting options)."""
    control_min_keyframes: int = param(3, 'a target is checked against the GNSS-only block (and a GCP used) once '
                                          'this many oriented keyframes have seen it (at the end of the flight: one)',
                                       min=2, max=1000)


class LiveControl:
    """The in-flight control of one block: detections in, verdicts out (see the module docstring)."""

    def __init__(self, file_heights: dict | None = None, options: LiveControlOptions | None = None):
        self.opt = options or LiveControlOptions()
        self.file_heights = dict(file_heights or {})
        self.surveyed: dict[str, ControlPoint] = {}
        self.vetting = ControlVetting([], {}, {})
        self._obs: dict[str, list] = {}        # name -> [(keyframe id, (2,) uv)]
        self._rejected: set = set()            # (name, keyframe id) of the detections taken out

    def set_surveyed(self, control: list[ControlPoint]) -> None:
        self.surveyed = {c.name: c for c in control}

    def observe(self, kid: int, target_uv: dict) -> None:
        for name, uv in target_uv.items():
            self._obs.setdefault(name, []).append((int(kid), np.asarray(uv, float).reshape(2)))

    def observations(self, name: str, registered) -> list:
        """[(keyframe id, uv)] of `name` in the keyframes `registered`, without the rejected detections."""
        return [(k, uv) for k, uv in self._obs.get(name, []) if k in registered and (name, k) not in self._rejected]

    def use_of(self, name: str) -> str:
        p = self.vetting.points.get(name)
        if p is not None:
            return p.use
        c = self.surveyed.get(name)
        if c is None or name not in self._obs:
            return 'not_seen'
        return 'held' if c.role == 'gcp' else 'check'

    def adjuster_control(self) -> list[ControlPoint]:
        """Control as the adjuster should take it now: a GCP not yet checked is held as a check point."""
        held = [replace(c, role='check') if c.role == 'gcp' and c.name not in self.vetting.points else c
                for c in self.surveyed.values()]
        return self.vetting.control_points(held)

    def update(self, at: IncrementalAT, final: bool = False) -> list[str]:
        """Vet the targets due (module docstring), take their rejected detections out of `at`, give it the
        control and the points of the GCPs admitted; returns the new faults."""
        weak = not at.georeferenced or at.georef_provisional
        pending = [n for n in self.surveyed if n not in self.vetting.points and n in self._obs]
        if not pending or (weak and not final):
            return []
        registered = set(at.block.oriented())
        need = 1 if final else self.opt.control_min_keyframes
        seen = {n: self.observations(n, registered) for n in pending}
        due = [n for n in pending if len(seen[n]) >= need]
        if not due:
            return []
        rows, kid_of = [], {}
        for n in due:
            for k, uv in seen[n]:
                rows.append(ControlRow(0, at.block.keyframe(k).name, n, uv))
                kid_of[at.block.keyframe(k).name] = k
        poses = {name: at.block.keyframe(k).map_T_cam for name, k in kid_of.items()}
        if weak:
            # The flight ends without a GNSS-only block that could judge the control (it never turned: the
            # roll about its line is an assumption that only the GCPs can fix). Take them as given.
            why = ('the block has no georeference from its GNSS' if not at.georeferenced else
                   'the flight never turned, so the GNSS leaves the roll about its line undetermined')
            later = unchecked_vetting(at.block.camera, poses, set(poses), rows, [self.surveyed[n] for n in due], why,
                                      self.file_heights)
        else:
            later = vet_control(at.block.camera, poses, set(poses), rows, [self.surveyed[n] for n in due],
                                at.fix_sigma_enu_m(), _ground_near(at, [self.surveyed[n].map_xyz for n in due]),
                                self.file_heights, self.opt, detected=True)
        new = self.vetting.merge(later, self.file_heights, self.opt)
        for f in later.rows:
            if f.fate == 'outlier':
                k = kid_of[f.row.image]
                self._rejected.add((f.row.name, k))
                at.drop_target_observation(k, f.row.name)
        at.set_control(self.adjuster_control())
        at.triangulate_targets([n for n in due if self.use_of(n) in ('full', 'horizontal')])
        return new

    def summary(self) -> dict:
        """Counts of the targets by where they stand, and the detections rejected."""
        uses = [self.use_of(n) for n, c in self.surveyed.items() if c.role == 'gcp']
        return {'gcps': len(uses), 'gcps_held': uses.count('held'), 'gcps_full': uses.count('full'),
                'gcps_horizontal_only': uses.count('horizontal'), 'gcps_rejected': uses.count('unused'),
                'gcps_not_seen': uses.count('not_seen'), 'control_detections_rejected': len(self._rejected)}

    def to_dict(self) -> dict:
        """The vetting so far: points, faults, the fates of the detections and those not used (the used
        ones are only counted: a long flight has thousands), every surveyed target's use."""
        v = self.vetting.to_dict()
        v['rows'] = [r for r in v['rows'] if r['fate'] != 'used']
        return {**v, 'use': {n: self.use_of(n) for n in self.surveyed}, **self.summary()}


def _ground_near(at: IncrementalAT, xyz_m: list, radius_m: float = 50.0) -> np.ndarray:
    """(N, 3) tie points of the hot tracks (those the window still sees) near the given points: the
    ground under a target seen once."""
    ids = at.block.tie_point_ids(hot=True)
    if not len(ids):
        return np.zeros((0, 3))
    P = at.block.points_of(ids).reshape(-1, 3)
    near = np.zeros(len(P), bool)
    for x in xyz_m:
        near |= np.hypot(P[:, 0] - x[0], P[:, 1] - x[1]) < radius_m
    return P[near]
