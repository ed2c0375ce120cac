"""Robust losses rho(s) on the squared residual norm s, with the scale in pixels.

cost = 0.5 * sum rho(s); rho(s) = c^2 rho_1(s / c^2) so that rho ~ s for small residuals.
"""

from __future__ import annotations

import numpy as np

from photogram_ros.errors import ConfigError

LOSSES = ('linear', 'huber', 'cauchy')


def evaluate(name: str, s: np.ndarray, scale):
    """(rho(s), rho'(s)) for squared norms s; `scale` one number or one per residual (like s)."""
    if name == 'linear':
        return s, np.ones_like(s)
    c2 = float(scale) ** 2 if np.ndim(scale) == 0 else np.asarray(scale, float) ** 2
    if name == 'huber':
        inl = s <= c2
        rs = np.sqrt(np.maximum(s, 1e-300))
        rho = np.where(inl, s, 2.0 * np.sqrt(c2) * rs - c2)
        d1 = np.where(inl, 1.0, np.sqrt(c2) / rs)
        return rho, d1
    if name == 'cauchy':
        return c2 * np.log1p(s / c2), 1.0 / (1.0 + s / c2)
    raise ConfigError(f'unknown loss {name!r}: choose one of {LOSSES}')
