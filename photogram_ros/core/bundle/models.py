"""Pluggable camera models for the bundle adjuster.

A model maps points in its camera frame (N, 3) and per-observation intrinsics (N, n) to pixels,
with analytic d(uv)/d(point) (N, 2, 3) and d(uv)/d(intrinsics) (N, 2, n). The solver only ever sees
these three arrays, so the OpenCV pinhole (optical frame, y down) and the BAL camera (-z forward,
y up, image-centred) are two models for one code path.
"""

from __future__ import annotations

import numpy as np

from photogram_ros.errors import ConfigError


class CameraModel:
    name = 'abstract'
    param_names: tuple = ()
    # Aliases for refine_intrinsics: each name maps to a weighting over param_names, so that e.g.
    # 'f' moves fx and fy together.
    aliases: dict = {}

    def project(self, p_cam: np.ndarray, prm: np.ndarray, jac: bool = True):
        raise NotImplementedError

    def selector(self, names) -> np.ndarray:
        """(n_params, n_free) matrix: full intrinsics delta = selector @ free delta."""
        cols = []
        for nm in names:
            w = np.zeros(len(self.param_names))
            if nm in self.aliases:
                for sub in self.aliases[nm]:
                    w[self.param_names.index(sub)] = 1.0
            elif nm in self.param_names:
                w[self.param_names.index(nm)] = 1.0
            else:
                raise ConfigError(f'intrinsic {nm!r} is not a parameter of the {self.name} camera model; '
                                  f'choose from {list(self.param_names) + list(self.aliases)}')
            cols.append(w)
        return np.array(cols).T if cols else np.zeros((len(self.param_names), 0))


class BrownModel(CameraModel):
    """OpenCV pinhole + 5-term Brown-Conrady, optical frame (z forward), as PinholeCamera."""
    name = 'pinhole_brown'
    param_names = ('fx', 'fy', 'cx', 'cy', 'k1', 'k2', 'p1', 'p2', 'k3')
    aliases = {'f': ('fx', 'fy')}

    @staticmethod
    def params_of(camera) -> np.ndarray:
        return np.array([camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist], dtype=float)

    def project(self, p_cam, prm, jac=True):
        X, Y, Z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
        fx, fy, cx, cy, k1, k2, p1, p2, k3 = prm.T
        iz = 1.0 / Z
        x, y = X * iz, Y * iz
        r2 = x * x + y * y
        r4 = r2 * r2
        radial = 1.0 + k1 * r2 + k2 * r4 + k3 * r4 * r2
        xy2 = 2.0 * x * y
        xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
        uv = np.stack([fx * xd + cx, fy * yd + cy], axis=1)
        if not jac:
            return uv, None, None
        dr = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4        # d radial / d r2
        j11 = radial + 2.0 * dr * x * x + 2.0 * p1 * y + 6.0 * p2 * x
        j12 = 2.0 * dr * x * y + 2.0 * p1 * x + 2.0 * p2 * y
        j22 = radial + 2.0 * dr * y * y + 6.0 * p1 * y + 2.0 * p2 * x
        # d(x, y)/dP = [[iz, 0, -x iz], [0, iz, -y iz]]
        n = len(X)
        J_p = np.empty((n, 2, 3))
        a11, a12, a21, a22 = fx * j11, fx * j12, fy * j12, fy * j22
        J_p[:, 0, 0] = a11 * iz
        J_p[:, 0, 1] = a12 * iz
        J_p[:, 0, 2] = -(a11 * x + a12 * y) * iz
        J_p[:, 1, 0] = a21 * iz
        J_p[:, 1, 1] = a22 * iz
        J_p[:, 1, 2] = -(a21 * x + a22 * y) * iz
        J_k = np.zeros((n, 2, 9))
        J_k[:, 0, 0] = xd
        J_k[:, 1, 1] = yd
        J_k[:, 0, 2] = 1.0
        J_k[:, 1, 3] = 1.0
        J_k[:, 0, 4], J_k[:, 1, 4] = fx * x * r2, fy * y * r2
        J_k[:, 0, 5], J_k[:, 1, 5] = fx * x * r4, fy * y * r4
        J_k[:, 0, 6], J_k[:, 1, 6] = fx * xy2, fy * (r2 + 2.0 * y * y)
        J_k[:, 0, 7], J_k[:, 1, 7] = fx * (r2 + 2.0 * x * x), fy * xy2
        J_k[:, 0, 8], J_k[:, 1, 8] = fx * x * r4 * r2, fy * y * r4 * r2
        return uv, J_p, J_k


class BALModel(CameraModel):
    """Bundle Adjustment in the Large: p = -P/P.z, uv = f (1 + k1|p|^2 + k2|p|^4) p (y up, centred)."""
    name = 'bal'
    param_names = ('f', 'k1', 'k2')

    def project(self, p_cam, prm, jac=True):
        X, Y, Z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
        f, k1, k2 = prm.T
        iz = -1.0 / Z
        px, py = X * iz, Y * iz
        n2 = px * px + py * py
        r = 1.0 + n2 * (k1 + k2 * n2)
        fr = f * r
        uv = np.stack([fr * px, fr * py], axis=1)
        if not jac:
            return uv, None, None
        g = 2.0 * f * (k1 + 2.0 * k2 * n2)              # f d r/d n2 * 2
        a11 = fr + g * px * px
        a12 = g * px * py
        a22 = fr + g * py * py
        # d(px, py)/dP = [[iz, 0, px iz], [0, iz, py iz]] with iz = -1/Z
        m = len(X)
        J_p = np.empty((m, 2, 3))
        J_p[:, 0, 0] = a11 * iz
        J_p[:, 0, 1] = a12 * iz
        J_p[:, 0, 2] = (a11 * px + a12 * py) * iz
        J_p[:, 1, 0] = a12 * iz
        J_p[:, 1, 1] = a22 * iz
        J_p[:, 1, 2] = (a12 * px + a22 * py) * iz
        J_k = np.empty((m, 2, 3))
        J_k[:, 0, 0], J_k[:, 1, 0] = r * px, r * py
        J_k[:, 0, 1], J_k[:, 1, 1] = f * n2 * px, f * n2 * py
        J_k[:, 0, 2], J_k[:, 1, 2] = f * n2 * n2 * px, f * n2 * n2 * py
        return uv, J_p, J_k
