"""One GNSS fix type for every reader and every consumer (no ROS here): `GnssFix`.

Every reader of positions returns it (MAVLink GPS_RAW_INT / GPS2_RAW and a dataflash log's GPS+GPA through
`make_fix`, a NavSatFix through msgs.py, a photo's EXIF GPS or DJI RTK XMP, a geo.txt line, a map folder's stored
fix, a fix log CSV), and the tracker, the adjustment, the MAVLink node and `photogram-ros fixes` take it:

- position: `lat_deg`, `lon_deg` (WGS84) and `h_m` above `height_datum` ('ellipsoid': WGS84, REP-145, what
  every consumer wants; 'exif': a photo's GPSAltitude as the camera wrote it, its reference not yet known, made
  ellipsoidal by `GnssFix.at` with the reading the user gives); `height_source` says how an ellipsoidal height was
  found ('alt_ellipsoid', 'msl+EGM2008', ...);
- time: `stamp_ns` on the ROS (UNIX) clock, ns (0 where the position has no time of its own);
- accuracy: `cov_enu_m2`, the (3, 3) covariance in the local east-north-up frame (per-axis 1-sigma:
  `sigma_enu_m`), and `cov_type` (sensor_msgs/NavSatFix.position_covariance_type: COV_*);
- quality on one scale, `quality`: RTKLIB's Q (1 fix, 2 float, 3 sbas, 4 dgps, 5 single, 6 ppp), 0 for no
  position: the scale of the trajectory readers, of DJI's RTK flags and of `--accept`. The source's own
  number stays beside it (`quality_native` on `native_scale`: a MAVLink GPS_FIX_TYPE, a DJI RtkFlag, a
  NavSatStatus); `status` (NavSatStatus) and `fix_type` (MAVLink GPS_FIX_TYPE) are read from them;
- `source`: what it came from ('GPS_RAW_INT', 'NavSatFix', 'EXIF', 'geo.txt', ...), and for a receiver its
  index, satellites and HDOP.

- Quality maps: MAVLink RTK fixed -> 1, RTK float -> 2, DGPS -> 4, PPP -> 6, 2D / 3D / static -> 5, no fix -> 0.
  A NavSatStatus alone says less: GBAS (RTK, fixed or float) -> 2, SBAS -> 3, FIX -> 5, NO_FIX -> 0; back to
  NavSatStatus: 1, 2 -> GBAS, 3, 4, 6 -> SBAS, 5 -> FIX, 0 -> NO_FIX (a NavSatStatus goes there and back unchanged).
- Covariance of a receiver fix (ENU, m^2, diagonal): from h_acc/v_acc when the receiver sends them (per-axis
  1-sigma, DIAGONAL_KNOWN), else HDOP/VDOP times a per-fix-type user range error (APPROXIMATED), else UNKNOWN.
- Height of a receiver fix: alt_ellipsoid when sent, else the MSL altitude plus the EGM2008 geoid undulation
  (photogram_ros.core.geoid).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from photogram_ros.core import geoid
from photogram_ros.errors import ConfigError, DataError

FIX_NAMES = ('NO_GPS', 'NO_FIX', '2D', '3D', 'DGPS', 'RTK_FLOAT', 'RTK_FIXED', 'STATIC', 'PPP')
NO_GPS, NO_FIX, FIX_2D, FIX_3D, DGPS, RTK_FLOAT, RTK_FIXED, STATIC, PPP = range(9)

# sensor_msgs/NavSatStatus and NavSatFix constants, copied so the core stays ROS-free.
STATUS_NO_FIX, STATUS_FIX, STATUS_SBAS_FIX, STATUS_GBAS_FIX = -1, 0, 1, 2
COV_UNKNOWN, COV_APPROXIMATED, COV_DIAGONAL_KNOWN = 0, 1, 2

# The one quality scale (RTKLIB's Q; core/exposure_positions.py's floors and the trajectory readers use it).
Q_NONE, Q_FIX, Q_FLOAT, Q_SBAS, Q_DGPS, Q_SINGLE, Q_PPP = range(7)
Q_NAMES = {Q_FIX: 'fix', Q_FLOAT: 'float', Q_SBAS: 'sbas', Q_DGPS: 'dgps', Q_SINGLE: 'single', Q_PPP: 'ppp'}
# MAVLink GPS_FIX_TYPE -> quality.
_FIX_TYPE_Q = {NO_GPS: Q_NONE, NO_FIX: Q_NONE, FIX_2D: Q_SINGLE, FIX_3D: Q_SINGLE, DGPS: Q_DGPS, RTK_FLOAT: Q_FLOAT,
               RTK_FIXED: Q_FIX, STATIC: Q_SINGLE, PPP: Q_PPP}
# quality -> the MAVLink GPS_FIX_TYPE of a fix from another source (what `fix_type` reads).
_Q_FIX_TYPE = {Q_NONE: NO_FIX, Q_FIX: RTK_FIXED, Q_FLOAT: RTK_FLOAT, Q_SBAS: DGPS, Q_DGPS: DGPS, Q_SINGLE: FIX_3D,
               Q_PPP: PPP}
# RTK (float or fixed) needs a ground base station -> GBAS; SBAS, DGPS and PPP use wide-area corrections -> SBAS
# (the closest NavSatStatus word); single-point solutions -> FIX.
_Q_STATUS = {Q_NONE: STATUS_NO_FIX, Q_FIX: STATUS_GBAS_FIX, Q_FLOAT: STATUS_GBAS_FIX, Q_SBAS: STATUS_SBAS_FIX,
             Q_DGPS: STATUS_SBAS_FIX, Q_SINGLE: STATUS_FIX, Q_PPP: STATUS_SBAS_FIX}
# A NavSatStatus alone: GBAS may be fixed or float -> float.
_STATUS_Q = {STATUS_NO_FIX: Q_NONE, STATUS_FIX: Q_SINGLE, STATUS_SBAS_FIX: Q_SBAS, STATUS_GBAS_FIX: Q_FLOAT}
# Rank for choosing among receivers: better solution first (then smaller horizontal sigma, choose_best).
_Q_RANK = {Q_NONE: 0, Q_SINGLE: 2, Q_SBAS: 3, Q_DGPS: 3, Q_PPP: 4, Q_FLOAT: 5, Q_FIX: 6}

UINT16_UNKNOWN = 65535

# Readings of a photo's EXIF GPSAltitude (`exif_altitude_to_ellipsoidal_m`); 'orthometric' is 'msl' (EGM2008).
EXIF_ALTITUDE_REFERENCES = ('msl', 'ellipsoidal', 'relative')
EXIF_ALTITUDE_SPELLINGS = {'orthometric': 'msl'}
HEIGHT_DATUMS = ('ellipsoid', 'exif')


def fix_name(fix_type: int) -> str:
    return FIX_NAMES[fix_type] if 0 <= fix_type < len(FIX_NAMES) else f'UNKNOWN({fix_type})'


def quality_of_fix_type(fix_type: int) -> int:
    """MAVLink GPS_FIX_TYPE -> quality (Q_*; an unknown fix type is no position)."""
    return _FIX_TYPE_Q.get(int(fix_type), Q_NONE)


def quality_of_status(status: int) -> int:
    """NavSatStatus.status -> quality (GBAS, fixed or float, reads as float)."""
    return _STATUS_Q.get(int(status), Q_NONE if int(status) < 0 else Q_SINGLE)


def navsat_status(fix_type: int) -> int:
    """MAVLink GPS_FIX_TYPE -> NavSatStatus.status."""
    return _Q_STATUS[quality_of_fix_type(fix_type)]


def quality_status(quality: int) -> int:
    """quality -> NavSatStatus.status."""
    return _Q_STATUS.get(int(quality), STATUS_FIX)


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
    """The fields of GPS_RAW_INT / GPS2_RAW (or a dataflash GPS+GPA pair) that make a fix: the input of
    `make_fix`, not a fix."""

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
    source: str = ''              # the message: '' is GPS_RAW_INT / GPS2_RAW by receiver


# Before 2001-09-09 in microseconds: anything larger is a UNIX time, anything smaller a boot time.
UNIX_THRESHOLD_US = 1_000_000_000_000_000


@dataclass(init=False)
class GnssFix:
    """A GNSS position, as every reader gives it and every consumer takes it (see the module docstring).

    `GnssFix(lat, lon, h, cov[, stamp_ns, status, cov_type, interpolated])` reads as the NavSatFix-shaped fix
    did: a NavSatStatus given there becomes `quality` (quality_of_status) unless `quality` is given.
    """

    lat_deg: float                 # WGS84 geodetic, degrees (NaN: no position)
    lon_deg: float
    h_m: float                     # above `height_datum`, m
    cov_enu_m2: np.ndarray         # (3, 3) ENU covariance at the fix, m^2
    stamp_ns: int                  # on the ROS (UNIX) clock, ns; 0: no time of its own
    quality: int                   # Q_*: 1 fix, 2 float, 3 sbas, 4 dgps, 5 single, 6 ppp; 0 no position
    cov_type: int                  # sensor_msgs/NavSatFix.position_covariance_type (COV_*)
    interpolated: bool             # made from two bracketing fixes (keyframes.FixBuffer)
    height_datum: str              # 'ellipsoid' (WGS84) or 'exif' (a photo's GPSAltitude as written)
    height_source: str               # how the height was found ('alt_ellipsoid', 'msl+EGM2008', ...; '' unsaid)
    source: str                    # what the fix came from ('GPS_RAW_INT', 'NavSatFix', 'EXIF', 'geo.txt', ...)
    quality_native: int | None     # the source's own quality number (None: it had none)
    native_scale: str              # the scale of quality_native ('GPS_FIX_TYPE', 'DJI RtkFlag', 'NavSatStatus')
    receiver: int                  # receiver index (0 GPS_RAW_INT, 1 GPS2_RAW; -1 not a receiver's)
    sats: int                      # satellites (-1 unknown)
    hdop: float                    # NaN unknown
    sysid: int
    compid: int

    def __init__(self, lat_deg: float, lon_deg: float, h_m: float, cov_enu_m2, stamp_ns: int = 0,
                 status: int | None = None, cov_type: int = COV_UNKNOWN, interpolated: bool = False, *,
                 quality: int | None = None, height_datum: str = 'ellipsoid', height_source: str = '',
                 source: str = '', quality_native: int | None = None, native_scale: str = '', receiver: int = -1,
                 sats: int = -1, hdop: float = math.nan, sysid: int = 0, compid: int = 0):
        cov = np.asarray(cov_enu_m2, dtype=float)
        if cov.shape != (3, 3):
            raise DataError(f'a GNSS covariance cov_enu_m2 is 3x3 (m^2, ENU), got shape {cov.shape}; three '
                            'variances go on its diagonal (np.diag)')
        if height_datum not in HEIGHT_DATUMS:
            raise DataError(f'height datum {height_datum!r} unknown; one of {HEIGHT_DATUMS}')
        if quality is None:
            quality = quality_of_status(STATUS_FIX if status is None else status)
        if quality not in _Q_STATUS:
            raise DataError(f'fix quality {quality} is not on the scale 0 none, 1 fix, 2 float, 3 sbas, 4 dgps, '
                            '5 single, 6 ppp')
        self.lat_deg, self.lon_deg, self.h_m, self.cov_enu_m2 = float(lat_deg), float(lon_deg), float(h_m), cov
        self.stamp_ns, self.quality, self.cov_type = int(stamp_ns), int(quality), int(cov_type)
        self.interpolated, self.height_datum, self.height_source = bool(interpolated), height_datum, height_source
        self.source, self.quality_native, self.native_scale = source, quality_native, native_scale
        self.receiver, self.sats, self.hdop, self.sysid, self.compid = receiver, sats, hdop, sysid, compid

    # --- read from the state -------------------------------------------------------------------------

    @property
    def status(self) -> int:
        """sensor_msgs/NavSatStatus.status (STATUS_*): < 0 is no fix."""
        return _Q_STATUS[self.quality]

    @property
    def fix_type(self) -> int:
        """MAVLink GPS_FIX_TYPE: the receiver's own for a MAVLink / dataflash fix, else the quality's."""
        if self.native_scale == 'GPS_FIX_TYPE' and self.quality_native is not None:
            return int(self.quality_native)
        return _Q_FIX_TYPE[self.quality]

    @property
    def t_s(self) -> float:
        """stamp_ns in seconds, correctly rounded (an int divided by an int: round(t_s * 1e9) gives stamp_ns back,
        and a receiver fix's t_s is its time to the bit, stamp_ns_of)."""
        return self.stamp_ns / 1_000_000_000

    @property
    def has_position(self) -> bool:
        return self.quality != Q_NONE and math.isfinite(self.lat_deg)

    @property
    def sigma_enu_m(self) -> np.ndarray:
        """(3,) per-axis 1-sigma east, north, up, m."""
        return np.sqrt(np.maximum(np.diag(self.cov_enu_m2), 0.0))

    @property
    def var_enu_m2(self) -> tuple:
        """(var_E, var_N, var_U), m^2."""
        return tuple(float(v) for v in np.diag(self.cov_enu_m2))

    @property
    def sigma_h_m(self) -> float:
        """1-sigma east, m; inf when the covariance is unknown (ranks receivers, choose_best)."""
        return math.sqrt(max(self.cov_enu_m2[0, 0], 0.0)) if self.cov_type != COV_UNKNOWN else math.inf

    @property
    def horizontal_sigma_m(self) -> float:
        """1-sigma of the worse horizontal axis, m (whatever cov_type says: 0 for an all-zero covariance)."""
        c = self.cov_enu_m2
        return float(np.sqrt(max(c[0, 0], c[1, 1], 0.0)))

    # --- the same fix, at a time / in a datum ---------------------------------------------------------

    def at(self, stamp_ns: int, sigma_h_m: float = 0.0, sigma_v_m: float = 0.0, reference: str = 'msl',
           takeoff_h_m: float | None = None, takeoff_reference: str = 'msl') -> 'GnssFix':
        """This fix at `stamp_ns`, ellipsoidal: a fix whose covariance is unknown takes the per-axis 1-sigmas
        given (horizontal, vertical; APPROXIMATED), and an EXIF height is read as `reference` says
        (exif_altitude_to_ellipsoidal_m)."""
        h_m, datum = self.h_m, self.height_datum
        if datum == 'exif':
            h_m = float(exif_altitude_to_ellipsoidal_m(self.lat_deg, self.lon_deg, self.h_m, reference, takeoff_h_m,
                                                       takeoff_reference))
            datum = 'ellipsoid'
        cov, cov_type = self.cov_enu_m2, self.cov_type
        if cov_type == COV_UNKNOWN:
            sh, sv = float(sigma_h_m), float(sigma_v_m)
            cov, cov_type = np.diag([sh * sh, sh * sh, sv * sv]), COV_APPROXIMATED
        return replace(self, stamp_ns=int(stamp_ns), h_m=h_m, height_datum=datum, cov_enu_m2=cov, cov_type=cov_type)

    # The name the camera node calls (frame.gps.gnss_fix(stamp_ns, sigma_h, sigma_v, *exif_reading)).
    gnss_fix = at

    # For io/photo_block.exif_position, which reads a photo's EXIF fix by these two names (its own change:
    # `fix.at(0, EXIF_SIGMA_H_M, EXIF_SIGMA_V_M, altitude, takeoff_h_m, takeoff_heights)`).
    @property
    def alt_msl_m(self) -> float:
        """An EXIF fix's height as written (h_m, datum 'exif')."""
        return self.h_m

    def sigmas_m(self, sigma_h_m: float, sigma_v_m: float) -> tuple[float, float]:
        """(per-axis horizontal, vertical) 1-sigma: the fix's own when its covariance is known, else those given."""
        if self.cov_type == COV_UNKNOWN:
            return float(sigma_h_m), float(sigma_v_m)
        s = self.sigma_enu_m
        return float(np.sqrt(0.5 * (s[0] ** 2 + s[1] ** 2))), float(s[2])

    # --- NavSatFix-shaped dict (msgs.py) ---------------------------------------------------------------

    @classmethod
    def from_dict(cls, d: dict) -> 'GnssFix':
        """From the dict of msgs.fix_from_navsatfix (keeps core free of ROS types)."""
        return cls(float(d['lat_deg']), float(d['lon_deg']), float(d['h_m']),
                   np.asarray(d['covariance_enu_m2'], float).reshape(3, 3), int(d['stamp_ns']),
                   int(d.get('status', STATUS_FIX)), int(d.get('covariance_type', COV_UNKNOWN)),
                   source=str(d.get('source', 'NavSatFix')))

    def as_dict(self) -> dict:
        """The keys of msgs.fix_from_navsatfix (frame_id aside): `from_dict(as_dict())` is this fix."""
        return {'stamp_ns': self.stamp_ns, 'lat_deg': self.lat_deg, 'lon_deg': self.lon_deg, 'h_m': self.h_m,
                'status': self.status, 'covariance_enu_m2': self.cov_enu_m2.copy(),
                'covariance_type': self.cov_type}

    @staticmethod
    def from_fix(fix: 'GnssFix') -> 'GnssFix':
        """The fix itself: the decoded receiver fix is this type now (io/bag_keyframes.py still calls it)."""
        return fix


def exif_altitude_to_ellipsoidal_m(lat_deg, lon_deg, alt_m, reference: str = 'msl',
                                   takeoff_h_m: float | None = None, takeoff_reference: str = 'msl'):
    """EXIF GPSAltitude (m, as written) -> WGS84 ellipsoidal height (m); scalars or arrays.

    `reference` says what the camera meant: 'msl' or 'orthometric' (EXIF 2.3; through EGM2008 at the photo),
    'ellipsoidal' (some PPK/RTK geotaggers write the WGS84 height) or 'relative' (above the take-off
    point, as many drones write it). 'relative' needs `takeoff_h_m`, the take-off point's height,
    above mean sea level or the ellipsoid as `takeoff_reference` ('msl' | 'ellipsoidal') says.
    """
    reference = EXIF_ALTITUDE_SPELLINGS.get(reference, reference)
    takeoff_reference = EXIF_ALTITUDE_SPELLINGS.get(takeoff_reference, takeoff_reference)
    if reference not in EXIF_ALTITUDE_REFERENCES:
        raise ConfigError(f'EXIF altitude reference {reference!r} unknown; choose from {EXIF_ALTITUDE_REFERENCES}')
    if takeoff_reference not in ('msl', 'ellipsoidal'):
        raise ConfigError(f"take-off height reference {takeoff_reference!r} unknown; choose 'msl' or 'ellipsoidal'")
    alt = np.asarray(alt_m, dtype=float)
    if reference == 'ellipsoidal':
        return alt
    if reference == 'msl':
        return geoid.msl_to_ellipsoid_m(lat_deg, lon_deg, alt)
    if takeoff_h_m is None:
        raise ConfigError('EXIF altitudes relative to take-off need the take-off point\'s height: give it '
                          '(triangulate --takeoff-altitude-m H, MSL unless --takeoff-heights ellipsoidal), '
                          'e.g. from a map, a survey of the launch point or the first photo\'s GNSS fix')
    if not np.isfinite(takeoff_h_m):
        raise ConfigError(f'take-off height {takeoff_h_m} m is not a number')
    if takeoff_reference == 'ellipsoidal':
        # A height difference is the same above the geoid or the ellipsoid to the geoid's slope
        # across the flight: millimetres over a few km.
        return float(takeoff_h_m) + alt
    return geoid.msl_to_ellipsoid_m(lat_deg, lon_deg, float(takeoff_h_m) + alt)


@dataclass
class FixResult:
    fix: GnssFix | None
    problem: str = ''         # why the input could not become a fix ('' when fine)


@lru_cache(maxsize=4096)
def _undulation_cached(lat_key: int, lon_key: int) -> float:
    # Keyed on 1e-3 degree cells (~100 m): the geoid changes by millimetres over that distance.
    return float(geoid.undulation_m(lat_key * 1e-3, lon_key * 1e-3))


def undulation_m(lat_deg: float, lon_deg: float) -> float:
    return _undulation_cached(int(round(lat_deg * 1000)), int(round(lon_deg * 1000)))


def stamp_ns_of(t_s: float) -> int:
    """A time in seconds (a double) -> the nearest ns, exactly: the whole seconds apart from the fraction, so that
    `t_s` of the fix (stamp_ns / 1e9) is this double again (t_s * 1e9 rounds to 256 ns at UNIX times)."""
    whole = math.floor(t_s)
    return int(whole) * 1_000_000_000 + int(round((t_s - whole) * 1e9))


def make_fix(raw: RawGnss, t_s: float, model: ErrorModel | None = None) -> FixResult:
    """RawGnss at output time `t_s` (UNIX s) -> GnssFix (position NaN when there is no fix), or a problem."""
    model = model or ErrorModel()
    ft = int(raw.fix_type)
    hdop = raw.eph / 100.0 if raw.eph not in (0, UINT16_UNKNOWN) else math.nan
    base = dict(stamp_ns=stamp_ns_of(t_s) if math.isfinite(t_s) else 0, receiver=raw.receiver,
                quality_native=ft, native_scale='GPS_FIX_TYPE',
                source=raw.source or ('GPS_RAW_INT' if raw.receiver == 0 else 'GPS2_RAW'), sats=raw.sats, hdop=hdop,
                sysid=raw.sysid, compid=raw.compid)
    if not math.isfinite(t_s):
        return FixResult(None, 'fix time is not finite')
    if ft < FIX_2D or ft >= len(FIX_NAMES):
        nan = math.nan
        return FixResult(GnssFix(nan, nan, nan, np.diag([nan, nan, nan]), cov_type=COV_UNKNOWN,
                                 quality=Q_NONE, **base),
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
    return FixResult(GnssFix(lat, lon, h, np.diag(cov), cov_type=ctype, quality=quality_of_fix_type(ft),
                             height_source=src, **base))


def choose_best(latest: dict, now_s: float, max_age_s: float = 1.0) -> int | None:
    """Receiver id of the best recent fix: best quality, then smallest horizontal sigma."""
    best, best_key = None, None
    for rx, fx in latest.items():
        if fx is None or not fx.has_position or now_s - fx.t_s > max_age_s:
            continue
        key = (_Q_RANK.get(fx.quality, 0), -fx.sigma_h_m, -rx)
        if best_key is None or key > best_key:
            best, best_key = rx, key
    return best


def interpolate(fix_a: GnssFix, fix_b: GnssFix, t_s: float) -> tuple[float, float, float]:
    """Linear interpolation of lat, lon, h between two fixes (fixes 0.2 s apart move < a few m)."""
    dt = fix_b.t_s - fix_a.t_s
    w = 0.0 if dt <= 0 else min(max((t_s - fix_a.t_s) / dt, 0.0), 1.0)
    return (fix_a.lat_deg + w * (fix_b.lat_deg - fix_a.lat_deg), fix_a.lon_deg + w * (fix_b.lon_deg - fix_a.lon_deg),
            fix_a.h_m + w * (fix_b.h_m - fix_a.h_m))
