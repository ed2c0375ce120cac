"""Reader for Bundle Adjustment in the Large problems (Agarwal et al. 2010), plain or .bz2.

Format: header `n_cameras n_points n_observations`, then `camera point x y` per observation, then
9 numbers per camera (Rodrigues rotation, translation, f, k1, k2) and 3 per point, all whitespace
separated. The camera maps world X to P = R X + t, so (R, t) is cam_T_map in our naming.
"""

from __future__ import annotations

import bz2
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from photogram_ros.errors import DataError


@dataclass
class BalData:
    cam_rotvec: np.ndarray    # (C, 3) Rodrigues, world -> camera
    cam_t: np.ndarray         # (C, 3)
    intrinsics: np.ndarray    # (C, 3) f, k1, k2
    points: np.ndarray        # (P, 3)
    obs_cam: np.ndarray       # (N,)
    obs_pt: np.ndarray        # (N,)
    obs_uv: np.ndarray        # (N, 2) image-centred, y up

    @property
    def cam_R(self) -> np.ndarray:
        return Rotation.from_rotvec(self.cam_rotvec).as_matrix()

    @property
    def map_T_cams(self) -> np.ndarray:
        R = self.cam_R
        T = np.zeros((len(R), 4, 4))
        T[:, :3, :3] = np.transpose(R, (0, 2, 1))
        T[:, :3, 3] = -np.einsum('cji,cj->ci', R, self.cam_t)
        T[:, 3, 3] = 1.0
        return T

    def problem(self, **kw):
        """A BundleProblem with the BAL camera model, one intrinsics group per camera."""
        from photogram_ros.core.bundle import BALModel, BundleProblem
        return BundleProblem(camera=None, map_T_cams=self.map_T_cams, points_map=self.points,
                             obs_cam=self.obs_cam, obs_pt=self.obs_pt, obs_uv=self.obs_uv,
                             model=BALModel(), intrinsics=self.intrinsics,
                             cam_intrinsics_group=np.arange(len(self.cam_t)), **kw)


def read_bal(path) -> BalData:
    path = Path(path)
    if not path.exists():
        raise DataError(f'BAL file {path} does not exist')
    opener = bz2.open if path.suffix == '.bz2' else open
    try:
        with opener(path, 'rt') as fh:
            header = fh.readline().split()
            C, P, N = (int(v) for v in header[:3])
            obs = np.loadtxt(fh, max_rows=N, dtype=float, ndmin=2)
            rest = np.fromstring(fh.read(), sep=' ')
    except (OSError, ValueError, EOFError) as exc:
        raise DataError(f'{path} is not a readable BAL file: {exc}') from exc
    if obs.shape != (N, 4) or rest.size != 9 * C + 3 * P:
        raise DataError(f'{path}: expected {N} observations and {9 * C + 3 * P} parameters, '
                        f'got {obs.shape[0]} and {rest.size}: the file is truncated or not BAL')
    cams = rest[:9 * C].reshape(C, 9)
    return BalData(cam_rotvec=cams[:, :3].copy(), cam_t=cams[:, 3:6].copy(), intrinsics=cams[:, 6:9].copy(),
                   points=rest[9 * C:].reshape(P, 3).copy(), obs_cam=obs[:, 0].astype(np.int64),
                   obs_pt=obs[:, 1].astype(np.int64), obs_uv=obs[:, 2:4].copy())
