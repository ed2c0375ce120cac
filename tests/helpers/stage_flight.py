"""A simulated flight through the adjustment stage as in flight (no ROS): RTK fixes and target rows keyframe by
keyframe, the live quality after each, then the final adjustment."""

from __future__ import annotations

import numpy as np

from photogram_ros.core.control import TARGET_DTYPE
from photogram_ros.core.gnss_fix import COV_DIAGONAL_KNOWN, STATUS_GBAS_FIX
from photogram_ros.params import from_dict
from photogram_ros.stages.adjustment import AdjustmentParams, AdjustmentStage, DiagnosticsLog, RecordedOutputs


def fly_stage(sk, targets, control_file: str = '', **overrides):
    """sk (sim.observations.SimKeyframes) through an AdjustmentStage with `control_file` (its targets' markers
    from `targets`, the world's) and AdjustmentParams overrides by name, then finished. Returns (stage, live):
    live holds, per keyframe, (the GCPs the block uses, the live quality) when there is a control file, else
    nothing."""
    p = from_dict(AdjustmentParams, {'lever_arm_cam_m': [float(v) for v in sk.lever_arm_cam_m],
                                     'control_file': str(control_file), **overrides})
    stage = AdjustmentStage(p, DiagnosticsLog(), RecordedOutputs())
    stage.set_camera(sk.camera)
    marker = {t.name: t.marker_id for t in targets}
    live = []
    for r in sk.records:
        f = r.fix
        stage.add_fix(r.stamp_ns, f.lat_deg, f.lon_deg, f.h_m, np.diag(np.diag(f.cov_enu_m2)), STATUS_GBAS_FIX,
                      COV_DIAGONAL_KNOWN)
        rows = np.zeros(len(r.target_uv), TARGET_DTYPE)
        for j, (name, uv) in enumerate(r.target_uv.items()):
            rows[j]['marker_id'], rows[j]['u'], rows[j]['v'] = marker[name], uv[0], uv[1]
        stage.add_keyframe(r.stamp_ns, r.track_ids, r.uv, rows if control_file else None)
        stage.drain()
        if control_file:
            live.append((stage.at.control_summary()['gcps_used'], stage.quality()))
    stage.finish()
    return stage, live
