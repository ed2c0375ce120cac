"""What an offline aerial triangulation starts from: keyframe records, a camera, a map origin.

Two readers make a `KeyframeBlock`: io/bag_keyframes.py (a flight bag through the tracker) and
io/photo_block.py (a folder of geotagged photos); io/aerial_triangulation.py adjusts it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.core.geodesy import LocalFrame
from photogram_ros.core.incremental import KeyframeRecord
from photogram_ros.errors import CalibrationError


@dataclass
class KeyframeBlock:
    camera: PinholeCamera
    origin: LocalFrame                   # the map frame: ENU at the first position
    records: list[KeyframeRecord]        # in adjustment order
    assumptions: list[str] = field(default_factory=list)   # for the report, in the order they were made
    n_inputs: int | None = None          # images given (photos); None: one per record
    # Photos' EXIF positions (M, 3: lat_deg, lon_deg, h_m ellipsoidal) read as MSL without the user
    # saying so: checked against the adjusted ground (aerial_triangulation.relative_exif_note).
    exif_geodetic: np.ndarray | None = None
    camera_from_exif: bool = False       # intrinsics from the photos' EXIF (distortion unknown)
    stats: dict = field(default_factory=dict)            # what reading it did (features, pairs: the report's)
    damage: list = field(default_factory=list)           # a damaged bag: what was read and what was lost
    # Whether the flight looked down (a mapping survey; a DJI XMP gimbal pitch says otherwise): the
    # block check expects its cameras near nadir. None: not known, not checked.
    expect_nadir: bool | None = True
    excluded: dict = field(default_factory=dict)         # photo name -> why it is not in the block


def camera_from_yaml(path: str | Path) -> PinholeCamera:
    """A calibration YAML (ROS camera_calibration layout) -> PinholeCamera."""
    import yaml
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise CalibrationError(f'cannot read the calibration {path}: {exc}') from exc
    return PinholeCamera.from_ros_yaml_dict(yaml.safe_load(text))
