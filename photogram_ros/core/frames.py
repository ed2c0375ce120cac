"""The TF frame tree of a mapping drone (REP-103 axes, REP-105 frames), from its adjusted camera poses.

    map                       ENU, the block's world-fixed frame (its origin: map/georeference)
    └ <ns>/odom               identity: the adjusted block has no odometry drift for map -> odom to correct
      └ <ns>/base_link        the body, FLU (REP-103); one transform per keyframe
        └ <ns>/camera_optical the camera, optical axes (z along the view, x right, y down: REP-103's
                              "_optical" convention), fixed to the body: the nominal nadir mount, image top
                              toward the nose (as core/incremental.lever_arm_cam_from_frd)

<ns> is the drone's namespace without slashes ('' for one drone: odom, base_link, camera_optical, the frame
the camera's images and camera_info are stamped with). map -> camera_optical composes to the keyframe's
adjusted pose exactly, whatever the mount: base_link is that pose seen through the nominal mount.
"""

from __future__ import annotations

import numpy as np

MAP = 'map'

# base_link (FLU) <- camera_optical for a nadir camera, image top forward: optical x = body right (-y),
# optical y = body backward (-x), optical z = body down (-z).
BASE_T_OPTICAL_NADIR = np.array([[0.0, -1.0, 0.0, 0.0],
                                 [-1.0, 0.0, 0.0, 0.0],
                                 [0.0, 0.0, -1.0, 0.0],
                                 [0.0, 0.0, 0.0, 1.0]])


def frame_names(namespace: str = '') -> dict:
    """{'map', 'odom', 'base_link', 'camera_optical'} -> the frame ids for a drone's namespace ('/drone1' or '')."""
    ns = namespace.strip('/')
    prefix = f'{ns}/' if ns else ''
    return {'map': MAP, 'odom': f'{prefix}odom', 'base_link': f'{prefix}base_link',
            'camera_optical': f'{prefix}camera_optical'}


def map_T_base(map_T_cam: np.ndarray, base_T_cam: np.ndarray = BASE_T_OPTICAL_NADIR) -> np.ndarray:
    """The body's pose in map (4x4) from the camera's, through the camera's mount on the body."""
    return np.asarray(map_T_cam, float) @ np.linalg.inv(base_T_cam)
