"""GNSS receiver errors per fix mode, with scripted outages and mode changes.

Each axis carries white noise plus a first-order Gauss-Markov bias (the slowly wandering error of a
real receiver). The reported accuracy (`h_acc_m`, `v_acc_m`) is the honest 1-sigma of that model
per horizontal axis and vertically, which is how mavros and photogram_ros read GPS_RAW_INT's
h_acc/v_acc (variance of east = variance of north = h_acc^2).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# MAVLink GPS_FIX_TYPE
FIX_NONE, FIX_NO_FIX, FIX_2D, FIX_3D, FIX_DGPS, FIX_RTK_FLOAT, FIX_RTK_FIXED, FIX_STATIC, FIX_PPP = range(9)


@dataclass(frozen=True)
class GnssMode:
    name: str
    fix_type: int
    white_h_m: float
    white_v_m: float
    bias_h_m: float
    bias_v_m: float
    tau_s: float
    hdop: float
    sats: tuple

    @property
    def h_acc_m(self) -> float:
        return float(np.hypot(self.white_h_m, self.bias_h_m))

    @property
    def v_acc_m(self) -> float:
        return float(np.hypot(self.white_v_m, self.bias_v_m))


MODES = {
    # RTK fixed: ~2 cm horizontal (radial), ~3 cm vertical.
    'rtk_fixed': GnssMode('rtk_fixed', FIX_RTK_FIXED, 0.008, 0.012, 0.011, 0.026, 60.0, 0.6, (20, 28)),
    'rtk_float': GnssMode('rtk_float', FIX_RTK_FLOAT, 0.05, 0.08, 0.20, 0.30, 30.0, 0.7, (16, 24)),
    'dgps': GnssMode('dgps', FIX_DGPS, 0.15, 0.25, 0.45, 0.8, 90.0, 0.8, (14, 20)),
    # Plain 3D fix: ~2 m horizontal with a slowly wandering bias.
    '3d': GnssMode('3d', FIX_3D, 0.25, 0.40, 1.40, 2.20, 120.0, 0.9, (10, 16)),
    'none': GnssMode('none', FIX_NO_FIX, 0.0, 0.0, 0.0, 0.0, 1.0, 99.99, (0, 3)),
}


@dataclass
class GnssScript:
    """What the receiver does when: a default mode, mode changes at times, outages as intervals."""

    mode: str = 'rtk_fixed'
    changes: list = field(default_factory=list)   # [(t_s, mode)]
    outages: list = field(default_factory=list)   # [(t0_s, t1_s)]

    def __post_init__(self):
        for m in [self.mode] + [c[1] for c in self.changes]:
            if m not in MODES:
                raise ValueError(f'unknown GNSS mode {m!r}; choose from {sorted(MODES)}')

    def mode_at(self, t_s: float) -> GnssMode:
        if any(t0 <= t_s < t1 for t0, t1 in self.outages):
            return MODES['none']
        name = self.mode
        for tc, m in sorted(self.changes):
            if t_s >= tc:
                name = m
        return MODES[name]


@dataclass
class GnssSample:
    t_s: float
    mode: GnssMode
    error_enu_m: np.ndarray   # (3,), zero-mean model error added to the true antenna position
    sats: int


class GnssErrorModel:
    def __init__(self, script: GnssScript, rng: np.random.Generator):
        self.script = script
        self.rng = rng
        self._bias = np.zeros(3)
        self._t = None
        self._mode = None

    def sample(self, t_s: float) -> GnssSample:
        mode = self.script.mode_at(t_s)
        sig_b = np.array([mode.bias_h_m, mode.bias_h_m, mode.bias_v_m])
        if self._t is None or self._mode is None or self._mode.name != mode.name:
            # A new solution type starts from its own stationary distribution.
            self._bias = self.rng.normal(0.0, 1.0, 3) * sig_b
        else:
            a = np.exp(-(t_s - self._t) / mode.tau_s)
            self._bias = a * self._bias + np.sqrt(1 - a * a) * self.rng.normal(0.0, 1.0, 3) * sig_b
        self._t, self._mode = t_s, mode
        white = self.rng.normal(0.0, 1.0, 3) * np.array([mode.white_h_m, mode.white_h_m, mode.white_v_m])
        sats = int(self.rng.integers(mode.sats[0], mode.sats[1] + 1))
        return GnssSample(t_s, mode, self._bias + white, sats)
