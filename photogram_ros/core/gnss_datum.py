"""The block's GNSS datum: how its fixes meet its cameras.

`GnssDatum` holds what the adjustments estimate of the fixes beside the poses: the antenna's lever arm, the common
bias of the fixes (a receiver without corrections is off by a bias that wanders over minutes; with 3 or more GCPs
it is observable), the tilt of their heights across the block (`slope` about `slope_centre`), the factors on their
stated sigmas that the flight's own noise gives (`sigma_scale_hv`, never below 1 unless tightened), and the
keyframes whose fix is not used (`rejected`). The GNSS rounds (core/gnss_rounds.py) estimate them; the bundle
problem (core/at_problem.py) reads them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from photogram_ros.core.at_geometry import lever_arm_cam_from_frd
from photogram_ros.core.at_store import Keyframe
from photogram_ros.core.part_options import check
from photogram_ros.params import param

# A fix enters the similarity that georeferences the block when its stated sigma is within this factor of the
# precise fixes' (the lower quartile of the flight's): RTK fixed (1-3 cm) beside float (decimetres) stays apart.
PRECISE_FIX_RATIO = 3.0


@dataclass(frozen=True)
class DatumOptions:
    """The options of the fixes' datum (`GnssDatum`): the GNSS lever arm."""
    lever_arm_cam_m: list = param([0.0, 0.0, 0.0], 'GNSS antenna position in the optical camera frame '
                                  '(x right, y down, z forward), m: a camera fixed to the body')
    lever_arm_body_frd_m: list = param([0.0, 0.0, 0.0], 'GNSS antenna position relative to the camera centre in '
                                       'the body frame (forward, right, down), m: a gimballed camera, whose '
                                       'keyframes carry their antenna offset from the attitude (bundle_node follows '
                                       'mavlink/attitude); zeros: lever_arm_cam_m is used')

    @property
    def gimbal(self) -> bool:
        return any(self.lever_arm_body_frd_m)

    def __post_init__(self):
        check(self)


class GnssDatum:
    """The fixes' datum of a block (core/at_block.py `Block`), for the options `opt`."""

    def __init__(self, block, opt: DatumOptions):
        self.block = block
        # A gimbal: the body lever arm as if flying level, image top forward, where a record has no offset.
        self.lever = (lever_arm_cam_from_frd(opt.lever_arm_body_frd_m) if opt.gimbal
                      else np.asarray(opt.lever_arm_cam_m, float))
        self.bias_enu = np.zeros(3)
        self.bias_estimated = False       # a full adjustment with >= 3 GCPs estimated it
        self.tilt_estimated = False       # ... and the tilt of the fixes' heights with it (`slope`)
        # The GNSS noise as the data shows it: factors (horizontal, vertical) on the fixes' stated sigmas.
        self.sigma_scale_hv = np.ones(2)
        self.rejected: set[int] = set()
        # Heights of a consumer geotag wander by tens of metres within a flight: their trend across the
        # block would tilt it. A slope (dz/dE, dz/dN) taken out of the fixes' heights (about their
        # horizontal centre) where the cameras' looking down says the trend is the fixes' (GnssRounds.level_block).
        self.slope = np.zeros(2)
        self.slope_centre = np.zeros(2)

    def adopt(self, sigma_scale_hv, bias_enu_m, rejected_names) -> None:
        """Take the datum of the block's sub-blocks (a split-merge's global adjustment): the sigma factors
        (horizontal, vertical), the bias (ENU m) and the photos whose fix is not used, by name."""
        self.sigma_scale_hv = np.asarray(sigma_scale_hv, float).reshape(2)
        self.bias_enu = np.asarray(bias_enu_m, float).reshape(3)
        names = set(rejected_names)
        self.rejected = {kf.kid for kf in self.block.kfs if kf.name in names}

    def forget_bias(self) -> None:
        """The bias (and the tilt with it) back to none: a final adjustment estimates them afresh."""
        self.bias_enu = np.zeros(3)
        self.bias_estimated = False
        if self.tilt_estimated:
            self.slope, self.tilt_estimated = np.zeros(2), False

    def rejected_names(self) -> list[str]:
        """Names of the keyframes whose fix is not used, in keyframe order."""
        return [self.block.kfs[k].name for k in sorted(self.rejected)]

    def target(self, kf: Keyframe) -> np.ndarray:
        """The fix moved so that `C + map_R_cam @ lever` should meet it (exact offset when known)."""
        fix = kf.fix_enu - self.bias_enu
        if self.slope.any():
            fix = fix + np.array([0.0, 0.0, float(self.slope @ (fix[:2] - self.slope_centre))])
        if kf.antenna_offset is None:
            return fix
        return fix - kf.antenna_offset + kf.map_T_cam[:3, :3] @ self.lever

    def fix_cov_used(self, kf: Keyframe) -> np.ndarray:
        """The fix's covariance (ENU m^2) scaled by the flight's estimated GNSS noise."""
        S = np.diag(self.sigma_scale_hv[[0, 0, 1]])
        return S @ np.asarray(kf.fix_cov, float).reshape(3, 3) @ S

    def stated_sigmas_hv(self, kids) -> np.ndarray:
        """(K, 2) the stated sigmas (m) of keyframes `kids`' fixes: horizontal (per axis, the RMS of E and N) and
        vertical, as their covariances say (the fix's own RtkStd*, sdn/sde/sdu, h_acc...), before any scale."""
        cov = np.array([np.asarray(self.block.kfs[k].fix_cov, float).reshape(3, 3) for k in kids]).reshape(-1, 3, 3)
        return np.maximum(np.column_stack([np.sqrt((cov[:, 0, 0] + cov[:, 1, 1]) / 2.0), np.sqrt(cov[:, 2, 2])]), 1e-6)

    def similarity_fixes(self, kids, min_count: int = 3, ratio: float = PRECISE_FIX_RATIO) -> list:
        """Of keyframes `kids` (each with a fix), those whose fixes are fit to place the block by a similarity:
        the precise ones, whose stated sigma (sqrt of the covariance's trace) is within `ratio` times the lower
        quartile of theirs. A fix that states decimetres beside fixes that state centimetres (a DJI RTK photo
        flagged FLOAT among fixed ones) would have the weight of a centimetre fix in an unweighted similarity:
        on a straight first line, metre errors across it decide the roll about the line and can turn the block
        upside down. All of `kids` when fewer than `min_count` are precise (nothing better to place it by) or
        when their sigmas are all alike."""
        kids = list(kids)
        if len(kids) <= min_count:
            return kids
        sig = np.sqrt([np.trace(np.asarray(self.block.kfs[k].fix_cov, float).reshape(3, 3)) for k in kids])
        keep = sig <= ratio * float(np.percentile(sig, 25))
        if keep.sum() < min_count:
            return kids
        return [k for k, ok in zip(kids, keep) if ok]

    def residuals(self, kids=None) -> dict:
        """Keyframe id -> ENU residual (m) of the adjusted antenna position minus the fix."""
        out = {}
        for k in (self.block.registered if kids is None else kids):
            kf = self.block.kfs[k]
            if kf.fix_enu is not None and kf.map_T_cam is not None:
                out[k] = kf.map_T_cam[:3, 3] + kf.map_T_cam[:3, :3] @ self.lever - self.target(kf)
        return out

    def rms_m(self, kids=None) -> float:
        r = list(self.residuals(kids).values())
        return float(np.sqrt(np.mean(np.sum(np.array(r) ** 2, axis=1)))) if r else float('nan')

    def raw_height_residuals(self, kids: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Vertical residuals (m) of the adjusted antennas against the fixes' own heights (no slope taken
        out), and the fixes' horizontal positions about the slope centre (K, 2), of keyframes `kids`."""
        r = self.residuals(kids)
        x = np.array([self.block.kfs[k].fix_enu[:2] - self.bias_enu[:2] - self.slope_centre for k in r])
        x = x.reshape(-1, 2)
        dz = np.array([r[k][2] for k in r]) + x @ self.slope
        return dz, x

    def antenna_residual(self, kf: Keyframe, map_T_cam: np.ndarray) -> np.ndarray:
        """Antenna of a camera at `map_T_cam` minus kf's fix as adjusted (bias taken off), ENU m."""
        return map_T_cam[:3, 3] + map_T_cam[:3, :3] @ self.lever - self.target(kf)

