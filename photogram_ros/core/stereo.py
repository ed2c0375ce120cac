"""Dense stereo depth from posed keyframe pairs (no ROS here)."""
from __future__ import annotations

import numpy as np

# The one cloud layout exchanged between stereo and map: positions in map ENU metres,
# colour packed 0x00RRGGBB as PCL/RViz expect, and a per-point confidence in [0, 1].
CLOUD_DTYPE = np.dtype([
    ("x", np.float64),
    ("y", np.float64),
    ("z", np.float64),
    ("rgb", np.uint32),
    ("confidence", np.float32),
])
