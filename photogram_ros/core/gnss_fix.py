"""GNSS fixes as a flight controller reports them -> positions with honest accuracy (no ROS here).

Two fix types, one per stage:
- `Fix`: a decoded receiver fix (receiver, MAVLink fix type, DOP, satellites, height source), its
  accuracy as three ENU variances `var_enu_m2`. Made by `make_fix` from a `RawGnss`.
- `GnssFix`: a position as the tracker and the adjustment consume it (what a NavSatFix carries):
  stamp, WGS84 position, ellipsoidal height and the full 3x3 ENU covariance `cov_enu_m2`.
  `GnssFix.from_fix` converts the first into the second; `from_dict` / `as_dict` read and write the
  dict that `msgs.fix_from_navsatfix` makes from a NavSatFix.

- Fix type: MAVLink GPS_FIX_TYPE (0..8) is kept in full; the NavSatFix status is a lossy summary of
  it (RTK float and fixed are both GBAS), so consumers that care read the fix type or the covariance.
- Covariance (ENU, m^2, diagonal): from h_acc/v_acc when the receiver sends them (per-axis 1-sigma,
  DIAGONAL_KNOWN), else HDOP/VDOP times a per-fix-type user range error (APPROXIMATED), else UNKNOWN.
- Height: above the WGS84 ellipsoid (REP-145): alt_ellipsoid when sent, else the MSL altitude plus
  the EGM2008 geoid undulation (photogram_ros.core.geoid).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from photogram_ros.core import geoid
from photogram_ros.errors import DataError

FIX_NAMES = ('NO_GPS', 'NO_FIX', '2D', '3D', 'DGPS', 'RTK_FLOAT', 'RTK_FIXED', 'STATIC', 'PPP')
NO_GPS, NO_FIX, FIX_2D, FIX_3D, DGPS, RTK_FLOAT, RTK_FIXED, STATIC, PPP = range(9)

# sensor_msgs/NavSatStatus and NavSatFix constants, copied so the core stays ROS-free.
STATUS_NO_FIX, STATUS_FIX, STATUS_SBAS_FIX, STATUS_GBAS_FIX = -1, 0, 1, 2
COV_UNKNOWN, COV_APPROXIMATED, COV_DIAGONAL_KNOWN = 0, 1, 2

# RTK (float or fixed) needs a ground base station -> GBAS; DGPS and PPP use wide-area corrections ->
# SBAS (the closest NavSatStatus word); 2D/3D/static single-point solutions -> FIX.
_STATUS = {NO_GPS: STATUS_NO_FIX, NO_FIX: STATUS_NO_FIX, FIX_2D: STATUS_FIX, FIX_3D: STATUS_FIX,
           DGPS: STATUS_SBAS_FIX, RTK_FLOAT: STATUS_GBAS_FIX, RTK_FIXED: STATUS_GBAS_FIX, STATIC: STATUS_FIX,
           PPP: STATUS_SBAS_FIX}
# Rank for choosing among receivers: better solution first, then smaller horizontal sigma.
_RANK = {NO_GPS: 0, NO_FIX: 0, FIX_2D: 1, FIX_3D: 2, STATIC: 2, DGPS: 3, PPP: 4, RTK_FLOAT: 5, RTK_FIXED: 6}

UINT16_UNKNOWN = 65535


def fix_name(fix_type: int) -> str:
    return FIX_NAMES[fix_type] if 0 <= fix_type < len(FIX_NAMES) else f'UNKNOWN({fix_type})'


def navsat_status(fix_type: int) -> int:
    return _STATUS.get(int(fix_type), STATUS_NO_FIX)


@dataclass
class ErrorModel:
    """User equivalent range error per fix type (m): sigma per horizontal axis = HDOP * uere."""

    uere_m: tuple = (0.0, 0.0, 5.0, 2.5, 0.7, 0.25, 0.015, 2.5, 0.1)
    vdop_over_hdop: float = 1.5    # used when VDOP (epv) is not sent

    def sigma_m(self, fix_type: int, eph: int, epv: int):
        if not 0 <= fix_type < len(self.uere_m) or eph in (0, UINT16_UNKNOWN):
            return None
        hdop = eph / 100.0
        vdop = epv / 100.0 if epv not in (0, UINT16_UNKNOWN) else hdop * self.vdop_over_hdop
        u = self.uere_m[fix_type]
        return hdop * u, vdop * u


@dataclass(frozen=True)
class RawGnss:
    """The fields of GPS_RAW_INT / GPS2_RAW (or a dataflash GPS+GPA pair) that make a fix."""

    receiver: int             # 0 = GPS_RAW_INT, 1 = GPS2_RAW
    time_usec: int            # boot time, or UNIX time if > UNIX_THRESHOLD_US
    fix_type: int
    lat_e7: int
    lon_e7: int
    alt_msl_mm: int
    alt_ellipsoid_mm: int = 0     # 0 = not sent
    eph: int = UINT16_UNKNOWN
    epv: int = UINT16_UNKNOWN
    h_acc_mm: int = 0             # 0 = not sent
    v_acc_mm: int = 0
    sats: int = 255
    sysid: int = 0
    compid: int = 0


# Before 2001-09-09 in microseconds: anything larger is a UNIX time, anything smaller a boot time.
UNIX_THRESHOLD_US = 1_000_000_000_000_000


@dataclass
class Fix:
    """A decoded receiver fix (see the module docstring); NaN position when the receiver has none."""

    t_s: float                # fix epoch on the output clock (UNIX / ROS)
    receiver: int
    fix_type: int
    status: int
    lat_deg: float            # NaN without a position fix
    lon_deg: float
    h_m: float                # above the WGS84 ellipsoid
    var_enu_m2: tuple         # (var_E, var_N, var_U), m^2
    cov_type: int
    height_source: str        # 'alt_ellipsoid', 'msl+EGM2008' or ''
    sats: int
    hdop: float
    sysid: int = 0
    compid: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def has_position(self) -> bool:
        return self.fix_type >= FIX_2D and math.isfinite(self.lat_deg)

    @property
    def sigma_h_m(self) -> float:
        return math.sqrt(self.var_enu_m2[0]) if self.cov_type != COV_UNKNOWN else math.inf

    def as_dict(self) -> dict:
        return {'t_s': self.t_s, 'receiver': self.receiver, 'fix_type': self.fix_type,
                'fix_name': fix_name(self.fix_type), 'status': self.status, 'lat_deg': self.lat_deg,
                'lon_deg': self.lon_deg, 'h_m': self.h_m, 'var_e_m2': self.var_enu_m2[0],
                'var_n_m2': self.var_enu_m2[1], 'var_u_m2': self.var_enu_m2[2], 'cov_type': self.cov_type,
                'height_source': self.height_source, 'sats': self.sats, 'hdop': self.hdop,
                'sysid': self.sysid, 'compid': self.compid}


@dataclass
class GnssFix:
    """A GNSS position as the tracker and the adjustment consume it.

    lat_deg, lon_deg  WGS84 geodetic, degrees
    h_m               above the WGS84 ellipsoid (REP-145), m
    cov_enu_m2        (3, 3) covariance of the position in the local east-north-up frame at the fix, m^2
    stamp_ns          fix epoch on the ROS (UNIX) clock, ns; 0 where the position has no time of its own
    status            sensor_msgs/NavSatStatus.status (STATUS_*): < 0 is no fix
    cov_type          sensor_msgs/NavSatFix.position_covariance_type (COV_*)
    interpolated      made from two bracketing fixes (keyframes.FixBuffer)
    The first four fields come first so that `GnssFix(lat, lon, h, cov)` reads as before.
    """

    lat_deg: float
    lon_deg: float
    h_m: float
    cov_enu_m2: np.ndarray
    stamp_ns: int = 0
    status: int = STATUS_FIX
    cov_type: int = COV_UNKNOWN
    interpolated: bool = False

    def __post_init__(self):
        cov = np.asarray(self.cov_enu_m2, dtype=float)
        if cov.shape != (3, 3):
            raise DataError(f'a GNSS covariance cov_enu_m2 is 3x3 (m^2, ENU), got shape {cov.shape}; three '
                            'variances go on its diagonal (np.diag)')
        self.cov_enu_m2 = cov

    @classmethod
    def from_fix(cls, fix: Fix) -> 'GnssFix':
        """A decoded receiver fix -> the consumed fix (stamp = the fix epoch rounded to ns)."""
        return cls(fix.lat_deg, fix.lon_deg, fix.h_m, np.diag(np.asarray(fix.var_enu_m2, dtype=float)),
                   int(round(fix.t_s * 1e9)), fix.status, fix.cov_type)

    @classmethod
    def from_dict(cls, d: dict) -> 'GnssFix':
        """From the dict of msgs.fix_from_navsatfix (keeps core free of ROS types)."""
        return cls(float(d['lat_deg']), float(d['lon_deg']), float(d['h_m']),
                   np.asarray(d['covariance_enu_m2'], float).reshape(3, 3), int(d['stamp_ns']),
                   int(d.get('status', STATUS_FIX)), int(d.get('covariance_type', COV_UNKNOWN)))

    def as_dict(self) -> dict:
        """The keys of msgs.fix_from_navsatfix (frame_id aside): `from_dict(as_dict())` is this fix."""
        return {'stamp_ns': self.stamp_ns, 'lat_deg': self.lat_deg, 'lon_deg': self.lon_deg, 'h_m': self.h_m,
                'status': self.status, 'covariance_enu_m2': self.cov_enu_m2.copy(),
                'covariance_type': self.cov_type}

    @property
    def horizontal_sigma_m(self) -> float:
        """1-sigma of the worse horizontal axis, m (whatever cov_type says: 0 for an all-zero covariance)."""
        c = self.cov_enu_m2
        return float(np.sqrt(max(c[0, 0], c[1, 1], 0.0)))


@dataclass
class FixResult:
    fix: Fix | None
    problem: str = ''         # why the input could not become a fix ('' when fine)


@lru_cache(maxsize=4096)
def _undulation_cached(lat_key: int, lon_key: int) -> float:
    # Keyed on 1e-3 degree cells (~100 m): the geoid changes by millimetres over that distance.
    return float(geoid.undulation_m(lat_key * 1e-3, lon_key * 1e-3))


def undulation_m(lat_deg: float, lon_deg: float) -> float:
    return _undulation_cached(int(round(lat_deg * 1000)), int(round(lon_deg * 1000)))


def make_fix(raw: RawGnss, t_s: float, model: ErrorModel | None = None) -> FixResult:
    """RawGnss at output time `t_s` -> Fix (position NaN when there is no fix), or a problem."""
    model = model or ErrorModel()
    ft = int(raw.fix_type)
    hdop = raw.eph / 100.0 if raw.eph not in (0, UINT16_UNKNOWN) else math.nan
    base = dict(t_s=t_s, receiver=raw.receiver, fix_type=ft, status=navsat_status(ft), sats=raw.sats, hdop=hdop,
                sysid=raw.sysid, compid=raw.compid)
    if not math.isfinite(t_s):
        return FixResult(None, 'fix time is not finite')
    if ft < FIX_2D or ft >= len(FIX_NAMES):
        nan = math.nan
        return FixResult(Fix(lat_deg=nan, lon_deg=nan, h_m=nan, var_enu_m2=(nan, nan, nan), cov_type=COV_UNKNOWN,
                             height_source='', **{**base, 'status': STATUS_NO_FIX}),
                         '' if ft < FIX_2D else f'unknown fix type {ft}')
    lat, lon = raw.lat_e7 * 1e-7, raw.lon_e7 * 1e-7
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0) or (raw.lat_e7 == 0 and raw.lon_e7 == 0):
        return FixResult(None, f'fix type {fix_name(ft)} with impossible position lat={lat} lon={lon}')
    if raw.alt_ellipsoid_mm != 0:
        h, src = raw.alt_ellipsoid_mm * 1e-3, 'alt_ellipsoid'
    else:
        h, src = raw.alt_msl_mm * 1e-3 + undulation_m(lat, lon), 'msl+EGM2008'
    if not -1000.0 < h < 100000.0:
        return FixResult(None, f'fix height {h:.1f} m is out of range')
    if raw.h_acc_mm > 0 and raw.v_acc_mm > 0:
        sh, sv = raw.h_acc_mm * 1e-3, raw.v_acc_mm * 1e-3
        cov, ctype = (sh * sh, sh * sh, sv * sv), COV_DIAGONAL_KNOWN
    else:
        sig = model.sigma_m(ft, raw.eph, raw.epv)
        if sig is None:
            cov, ctype = (0.0, 0.0, 0.0), COV_UNKNOWN
        else:
            cov, ctype = (sig[0] ** 2, sig[0] ** 2, sig[1] ** 2), COV_APPROXIMATED
    return FixResult(Fix(lat_deg=lat, lon_deg=lon, h_m=h, var_enu_m2=cov, cov_type=ctype, height_source=src,
                         **base))


def choose_best(latest: dict, now_s: float, max_age_s: float = 1.0) -> int | None:
    """Receiver id of the best recent fix: best solution type, then smallest horizontal sigma."""
    best, best_key = None, None
    for rx, fx in latest.items():
        if fx is None or not fx.has_position or now_s - fx.t_s > max_age_s:
            continue
        key = (_RANK.get(fx.fix_type, 0), -fx.sigma_h_m, -rx)
        if best_key is None or key > best_key:
            best, best_key = rx, key
    return best


def interpolate(fix_a: Fix, fix_b: Fix, t_s: float) -> tuple[float, float, float]:
    """Linear interpolation of lat, lon, h between two fixes (fixes 0.2 s apart move < a few m)."""
    dt = fix_b.t_s - fix_a.t_s
    w = 0.0 if dt <= 0 else min(max((t_s - fix_a.t_s) / dt, 0.0), 1.0)
    return (fix_a.lat_deg + w * (fix_b.lat_deg - fix_a.lat_deg), fix_a.lon_deg + w * (fix_b.lon_deg - fix_a.lon_deg),
            fix_a.h_m + w * (fix_b.h_m - fix_a.h_m))
