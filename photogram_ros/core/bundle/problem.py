"""The bundle-adjustment problem and options: the public API of photogram_ros.core.bundle.

Conventions. Poses come in and go out as map_T_cam (camera -> map). Internally each camera is
cam_T_map = (R, t) with X_cam = R X_map + t, updated on the left: R <- exp([dw]x) R, t <- t + dt,
so the 6 pose unknowns per camera are (dw, dt) in the camera frame. Points are map coordinates.
Gauge: fixed by GNSS priors (>= 3 non-collinear fixes), point priors (GCPs), or fixed cameras and
points. With none of these the 7-DoF similarity gauge stays free: Levenberg-Marquardt damping keeps
the steps bounded and the cost converges, but covariances are then undefined and not returned.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from photogram_ros.core.bundle.losses import LOSSES
from photogram_ros.core.bundle.models import BrownModel, CameraModel
from photogram_ros.errors import ConfigError, DataError


def _arr(x, shape_tail, name, dtype=float):
    a = np.asarray(x, dtype=dtype)
    if a.ndim != len(shape_tail) + 1 or a.shape[1:] != tuple(shape_tail):
        raise DataError(f'{name} must have shape (n, {", ".join(map(str, shape_tail))}), got {a.shape}')
    return a


@dataclass
class BundleOptions:
    loss: str = 'huber'                      # 'huber' | 'cauchy' | 'linear' on reprojection errors
    loss_scale_px: float = 1.0
    max_iterations: int = 50
    refine_intrinsics: tuple = ()            # e.g. ('f', 'cx', 'cy', 'k1', 'k2', 'p1', 'p2', 'k3')
    function_tolerance: float = 1e-6         # stop when a step lowers the cost by less than this fraction
    gradient_tolerance: float = 1e-10
    parameter_tolerance: float = 1e-8
    compute_covariance: bool = False
    # With compute_covariance, the points' marginal covariances too: a dense product of the reduced camera
    # system's inverse with every point's columns, whose cost grows with cameras^2 x points.
    point_covariance: bool = False
    # With compute_covariance, the covariances as if a constant offset of all GNSS fixes (the GNSS bias, ENU m)
    # were one more unknown: what a block that estimates its GNSS bias from GCPs knows. The fixes then hold the
    # cameras relative to each other only, and a focal length that trades off with the block's height shows it.
    gnss_bias_free: bool = False
    # A constant offset of all GNSS fixes (the GNSS bias, ENU m) as 3 more unknowns, from zero: each fix's
    # residual is antenna - (gnss_pos_map - bias). Only the GCPs (point priors) or fixed cameras then hold the
    # block's position: without them the bias and the block's translation trade off freely.
    estimate_gnss_bias: bool = False
    # With estimate_gnss_bias, a tilt of the fixes' heights as 2 more unknowns (dU/dE, dU/dN, m/m, from zero):
    # each fix's height residual also has + tilt . (fix_EN - centre), the centre BundleProblem.gnss_tilt_centre_m
    # or the fixes' mean. A GNSS error that wanders between strips flown minutes apart leans the fixes across
    # them; GCPs spread over the block in both directions observe it, GCPs on one line do not.
    estimate_gnss_tilt: bool = False
    initial_trust_radius: float = 1e4
    dense_limit: int = 3000                  # reduced camera systems larger than this are solved sparsely

    def validate(self):
        if self.loss not in LOSSES:
            raise ConfigError(f'loss {self.loss!r} unknown: choose one of {LOSSES}')
        if not self.loss_scale_px > 0:
            raise ConfigError(f'loss_scale_px must be > 0, got {self.loss_scale_px}')
        if int(self.max_iterations) < 0:
            raise ConfigError('max_iterations must be >= 0')


@dataclass
class BundleProblem:
    camera: object                           # PinholeCamera (shared intrinsics), or None with model=...
    map_T_cams: np.ndarray                   # (C, 4, 4)
    points_map: np.ndarray                   # (P, 3)
    obs_cam: np.ndarray                      # (N,) int
    obs_pt: np.ndarray                       # (N,) int
    obs_uv: np.ndarray                       # (N, 2) observed (distorted) pixels
    # (N,) robust-loss scale of each observation, px (None: BundleOptions.loss_scale_px for all); e.g.
    # points measured by hand, whose loss is not the automatic tie points'.
    obs_loss_scale_px: np.ndarray | None = None
    fixed_cams: np.ndarray | None = None
    fixed_points: np.ndarray | None = None
    gnss_cam: np.ndarray | None = None       # (M,) camera index of each fix
    gnss_pos_map: np.ndarray | None = None   # (M, 3) antenna position in map
    gnss_cov_map: np.ndarray | None = None   # (M, 3, 3) m^2
    lever_arm_cam_m: np.ndarray | None = None  # (3,) antenna in the camera frame
    gnss_tilt_centre_m: np.ndarray | None = None  # (2,) E, N map: where the GNSS tilt is zero (None: the fixes' mean)
    point_priors_idx: np.ndarray | None = None   # (G,) GCP point indices
    point_priors_map: np.ndarray | None = None   # (G, 3)
    point_priors_sigma_m: np.ndarray | None = None  # (G, 3)
    attitude_cam: np.ndarray | None = None   # (A,) camera index of each attitude prior
    attitude_map_R_cam: np.ndarray | None = None  # (A, 3, 3)
    attitude_sigma_rad: np.ndarray | None = None  # (A, 3) or (3,)
    # Advanced: another camera model (e.g. BALModel) with intrinsics per group of cameras.
    model: CameraModel | None = None
    intrinsics: np.ndarray | None = None     # (K, n_params) of model
    cam_intrinsics_group: np.ndarray | None = None  # (C,) int into intrinsics
    extra: dict = field(default_factory=dict)

    def resolved(self):
        """Validated arrays for the solver (raises DataError/ConfigError on bad input)."""
        T = np.asarray(self.map_T_cams, dtype=float)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise DataError(f'map_T_cams must be (C, 4, 4), got {T.shape}')
        C = len(T)
        X = _arr(self.points_map, (3,), 'points_map')
        P = len(X)
        oc = np.asarray(self.obs_cam, dtype=np.int64).ravel()
        op = np.asarray(self.obs_pt, dtype=np.int64).ravel()
        uv = _arr(self.obs_uv, (2,), 'obs_uv')
        if not (len(oc) == len(op) == len(uv)):
            raise DataError(f'obs_cam, obs_pt and obs_uv differ in length ({len(oc)}, {len(op)}, {len(uv)})')
        if len(oc) and (oc.min() < 0 or oc.max() >= C or op.min() < 0 or op.max() >= P):
            raise DataError('observation indices out of range of cameras or points')
        if not (np.all(np.isfinite(T)) and np.all(np.isfinite(X)) and np.all(np.isfinite(uv))):
            raise DataError('poses, points or observations contain NaN or infinite values')
        scale = None
        if self.obs_loss_scale_px is not None:
            scale = np.asarray(self.obs_loss_scale_px, float).ravel()
            if len(scale) != len(oc) or not np.all(scale > 0):
                raise DataError(f'obs_loss_scale_px must give each of the {len(oc)} observations a scale > 0')
        if self.model is None:
            if self.camera is None:
                raise ConfigError('give camera=PinholeCamera(...) or model= with intrinsics=')
            model = BrownModel()
            intr = BrownModel.params_of(self.camera)[None, :]
            group = np.zeros(C, dtype=np.int64)
        else:
            model = self.model
            intr = np.atleast_2d(np.asarray(self.intrinsics, dtype=float))
            if intr.shape[1] != len(model.param_names):
                raise DataError(f'intrinsics must be (K, {len(model.param_names)}) for the {model.name} model')
            group = (np.zeros(C, dtype=np.int64) if self.cam_intrinsics_group is None
                     else np.asarray(self.cam_intrinsics_group, dtype=np.int64).ravel())
            if len(group) != C or group.min() < 0 or group.max() >= len(intr):
                raise DataError('cam_intrinsics_group must give each camera an index into intrinsics')
        fc = np.zeros(C, bool) if self.fixed_cams is None else np.asarray(self.fixed_cams, bool).ravel()
        fp = np.zeros(P, bool) if self.fixed_points is None else np.asarray(self.fixed_points, bool).ravel()
        if len(fc) != C or len(fp) != P:
            raise DataError('fixed_cams must be (C,) and fixed_points (P,) booleans')
        R_mc = T[:, :3, :3]
        R = np.transpose(R_mc, (0, 2, 1))
        t = -np.einsum('cij,cj->ci', R, T[:, :3, 3])
        out = dict(model=model, intr=intr.copy(), group=group, R=R.copy(), t=t, X=X.copy(),
                   obs_cam=oc, obs_pt=op, obs_uv=uv, fixed_cams=fc, fixed_points=fp)
        if scale is not None:
            out['obs_scale'] = scale
        # GNSS priors
        if self.gnss_cam is not None and len(self.gnss_cam):
            gc = np.asarray(self.gnss_cam, dtype=np.int64).ravel()
            gp = _arr(self.gnss_pos_map, (3,), 'gnss_pos_map')
            cov = np.asarray(self.gnss_cov_map, dtype=float)
            if cov.shape != (len(gc), 3, 3) or len(gp) != len(gc):
                raise DataError('gnss_pos_map must be (M, 3) and gnss_cov_map (M, 3, 3) for M = len(gnss_cam)')
            if gc.min() < 0 or gc.max() >= C:
                raise DataError('gnss_cam index out of range')
            try:
                L = np.linalg.cholesky(cov)
            except np.linalg.LinAlgError:
                raise DataError('a GNSS covariance is not positive definite: check the fix covariances') from None
            lever = np.zeros(3) if self.lever_arm_cam_m is None else np.asarray(self.lever_arm_cam_m, float).reshape(3)
            out.update(gnss_cam=gc, gnss_pos=gp, gnss_W=np.linalg.inv(L), lever=lever,
                       gnss_tilt_centre=(None if self.gnss_tilt_centre_m is None else
                                         np.asarray(self.gnss_tilt_centre_m, float).reshape(2)))
        # Point priors (GCPs)
        if self.point_priors_idx is not None and len(self.point_priors_idx):
            gi = np.asarray(self.point_priors_idx, dtype=np.int64).ravel()
            gx = _arr(self.point_priors_map, (3,), 'point_priors_map')
            gs = np.broadcast_to(np.asarray(self.point_priors_sigma_m, float), gx.shape).copy()
            if len(gx) != len(gi) or gi.min() < 0 or gi.max() >= P:
                raise DataError('point_priors_idx/point_priors_map mismatch or index out of range')
            if not np.all(gs > 0):
                raise DataError('point_priors_sigma_m must be > 0 (fix a point with fixed_points instead)')
            out.update(pp_idx=gi, pp_pos=gx, pp_sigma=gs)
        # Attitude priors
        if self.attitude_cam is not None and len(self.attitude_cam):
            ac = np.asarray(self.attitude_cam, dtype=np.int64).ravel()
            aR = np.asarray(self.attitude_map_R_cam, float)
            asg = np.broadcast_to(np.asarray(self.attitude_sigma_rad, float), (len(ac), 3)).copy()
            if aR.shape != (len(ac), 3, 3) or ac.min() < 0 or ac.max() >= C or not np.all(asg > 0):
                raise DataError('attitude priors need attitude_map_R_cam (A, 3, 3) and sigma > 0')
            out.update(att_cam=ac, att_R=np.transpose(aR, (0, 2, 1)), att_sigma=asg)
        return out


@dataclass
class BundleResult:
    status: str                      # 'converged' | 'max_iterations' | 'failed'
    reason: str
    initial_cost: float
    final_cost: float
    iterations: int                  # linear solves, accepted or not (as Ceres counts)
    successful_steps: int
    map_T_cams: np.ndarray
    points_map: np.ndarray
    camera: object                   # PinholeCamera with the refined intrinsics (None for other models)
    intrinsics: np.ndarray           # (K, n) raw model intrinsics
    rms: dict
    # Covariances (compute_covariance=True). Camera centres and points: unscaled inverse normal
    # matrix (pixel residuals taken at unit weight, priors at their sigma); multiply by
    # variance_factor for the a-posteriori figures. Intrinsics: already scaled, C = s0^2 Q with the
    # a-posteriori variance of unit weight s0^2 = v^T P v / r (r = residuals - unknowns), the usual
    # figure of least-squares adjustment in photogrammetry (e.g. Luhmann et al., Close-Range
    # Photogrammetry, ch. 2.4): sigmas then follow the actual image noise, not a nominal 1 px.
    cam_centre_cov: np.ndarray | None = None
    point_cov: np.ndarray | None = None              # only with BundleOptions.point_covariance
    intrinsics_cov: np.ndarray | None = None         # (K, kf, kf) over intrinsics_names, scaled
    intrinsics_names: tuple = ()                     # BundleOptions.refine_intrinsics ('f' = fx and fy)
    # (K, kf) correlation of each intrinsic with the block's height (mean camera-centre height minus
    # mean point height, map z): near +-1 the intrinsic is not determined (focal vs the ground's depth).
    intrinsics_height_corr: np.ndarray | None = None
    # (3,) ENU m: the GNSS bias estimated (BundleOptions.estimate_gnss_bias; None when not, or no fix): the fixes
    # adjusted are gnss_pos_map minus it.
    gnss_bias_enu_m: np.ndarray | None = None
    # (2,) m/m: the tilt of the fixes' heights estimated (dU/dE, dU/dN; BundleOptions.estimate_gnss_tilt, else None):
    # the fixes' heights adjusted are also less it . (fix_EN - its centre).
    gnss_tilt: np.ndarray | None = None
    # (3, 3) ENU m^2, scaled: the GNSS bias's covariance as an unknown (BundleOptions.estimate_gnss_bias or
    # gnss_bias_free).
    gnss_bias_cov: np.ndarray | None = None
    variance_factor: float | None = None             # s0^2 (None without redundancy)
    seconds: float = 0.0
    cost_history: list = field(default_factory=list)     # cost after each accepted step
    time_history: list = field(default_factory=list)     # seconds since the start, per entry above

    def intrinsics_sigma(self, group: int = 0) -> dict:
        """name -> a-posteriori standard deviation of each self-calibrated intrinsic ({} if none)."""
        if self.intrinsics_cov is None:
            return {}
        sd = np.sqrt(np.clip(np.diagonal(self.intrinsics_cov[group]), 0.0, None))
        return {n: float(v) for n, v in zip(self.intrinsics_names, sd)}

    def intrinsics_height_correlation(self, group: int = 0) -> dict:
        """name -> correlation of each self-calibrated intrinsic with the block's height ({} if none)."""
        if self.intrinsics_height_corr is None:
            return {}
        return {n: float(v) for n, v in zip(self.intrinsics_names, self.intrinsics_height_corr[group])}
