"""What the flight started from, kept in the map folder for the report: each keyframe's GNSS fix and the
input camera calibration (before a final adjustment's self-calibration replaces camera.json); and the ground
the adjuster's tie points found, for the matching after landing.

    keyframe_fixes.jsonl   one JSON object a line: stamp_ns, lat_deg, lon_deg, h_m (ellipsoidal), status
                           (NavSatStatus), optional sigma_h_m, sigma_v_m, appended as the keyframes' fixes come (`append_keyframe_fix`)
    camera_input.json      the first calibration the flight was given (`save_input_camera`), in camera.json's
                           layout (the ROS calibration YAML as JSON)
    tie_point_ground.json  the median height (map z, m) of the adjuster's latest tie points and their count
                           (`save_tie_point_ground`): the ground io/densify.py searches around when the in-flight
                           map fused too little to say (a replay whose stereo found no partner or shed its pairs)

The flight report reads them (`keyframe_fixes`, `input_camera`) for the GNSS residuals per photo and the
calibration before and after; `copy_inputs` carries them into the map folder densify makes. A folder
without them gives a report that says so.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

FIXES_FILE = 'keyframe_fixes.jsonl'
INPUT_CAMERA_FILE = 'camera_input.json'
TIE_GROUND_FILE = 'tie_point_ground.json'


def append_keyframe_fix(root: str | Path, stamp_ns: int, lat_deg: float, lon_deg: float, h_m: float,
                        status: int, sigma_h_m: float | None = None, sigma_v_m: float | None = None) -> None:
    """Append one keyframe's fix (a later line for the same stamp replaces an earlier one when read); its
    1-sigmas, m, when given (a resumed run feeds the fix again with them)."""
    row = {'stamp_ns': int(stamp_ns), 'lat_deg': float(lat_deg), 'lon_deg': float(lon_deg), 'h_m': float(h_m),
           'status': int(status)}
    if sigma_h_m is not None and sigma_v_m is not None:
        row.update(sigma_h_m=float(sigma_h_m), sigma_v_m=float(sigma_v_m))
    with open(Path(root) / FIXES_FILE, 'a') as f:
        f.write(json.dumps(row) + '\n')


def keyframe_fixes(root: str | Path) -> dict[int, dict]:
    """stamp_ns -> {'lat_deg', 'lon_deg', 'h_m', 'status'[, 'sigma_h_m', 'sigma_v_m']}; {} without the file. A
    line cut short by a kill (the last one) is skipped."""
    path = Path(root) / FIXES_FILE
    out: dict[int, dict] = {}
    if not path.exists():
        return out
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
            fix = {k: row[k] for k in ('lat_deg', 'lon_deg', 'h_m', 'status')}
            out[int(row['stamp_ns'])] = {**fix, **{k: row[k] for k in ('sigma_h_m', 'sigma_v_m') if k in row}}
        except (ValueError, KeyError, TypeError):
            continue
    return out


def save_input_camera(root: str | Path, camera, name: str = 'input') -> bool:
    """Keep the flight's first calibration (a later call leaves it); True when written."""
    path = Path(root) / INPUT_CAMERA_FILE
    if path.exists():
        return False
    tmp = path.with_suffix('.json.tmp')
    tmp.write_text(json.dumps(camera.to_ros_yaml_dict(name)))
    tmp.replace(path)
    return True


def input_camera(root: str | Path):
    """The core.camera model saved by save_input_camera, or None."""
    from photogram_ros.core.camera import PinholeCamera
    from photogram_ros.errors import PhotogramError
    path = Path(root) / INPUT_CAMERA_FILE
    try:
        return PinholeCamera.from_ros_yaml_dict(json.loads(path.read_text())) if path.exists() else None
    except (OSError, ValueError, KeyError, PhotogramError):
        return None


def save_tie_point_ground(root: str | Path, ground_m: float, tie_points: int) -> None:
    """Keep the median height `ground_m` (map z, m) of the adjuster's latest `tie_points` tie points (each call
    replaces the last)."""
    path = Path(root) / TIE_GROUND_FILE
    tmp = path.with_suffix('.json.tmp')
    tmp.write_text(json.dumps({'ground_m': float(ground_m), 'tie_points': int(tie_points)}))
    tmp.replace(path)


def tie_point_ground(root: str | Path) -> float | None:
    """The ground height save_tie_point_ground kept (map z, m), or None (no file, or not a finite number)."""
    path = Path(root) / TIE_GROUND_FILE
    try:
        z = float(json.loads(path.read_text())['ground_m']) if path.exists() else float('nan')
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return z if np.isfinite(z) else None


def copy_inputs(src_root: str | Path, dst_root: str | Path) -> None:
    """Carry the flight's inputs into another map folder (densify's)."""
    for name in (FIXES_FILE, INPUT_CAMERA_FILE, TIE_GROUND_FILE):
        src = Path(src_root) / name
        if src.exists():
            shutil.copyfile(src, Path(dst_root) / name)
