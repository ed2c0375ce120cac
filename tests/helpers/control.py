"""Control files of a simulated flight's targets, as a surveyor would write them (with field faults on request)."""

from __future__ import annotations

import numpy as np

from photogram_ros.core.control import SurveyedTarget
from photogram_ros.io.control_file import write_control_file


def targets_file(path, origin, targets, gcp_height_m: float | None = None, moved_enu_m: dict | None = None,
                 crs: str = 'EPSG:32632'):
    """Write the targets' true positions (LocalFrame `origin`) to a control file at `path` in `crs`; its path.
    `gcp_height_m` writes that placeholder height for every GCP; `moved_enu_m` {name: (e, n, u)} moves a
    target's surveyed position by that many metres."""
    moved = moved_enu_m or {}
    survey = []
    for t in targets:
        lat, lon, h = origin.enu_to_geodetic(np.asarray(t.center_enu) + np.asarray(moved.get(t.name, (0.0, 0.0, 0.0))))
        if gcp_height_m is not None and t.role == 'gcp':
            h = gcp_height_m
        survey.append(SurveyedTarget(t.name, t.marker_id, float(lat), float(lon), float(h), t.role))
    return write_control_file(path, survey, crs)
