"""The one place that converts between ROS 2 messages and numpy / core types.

Nodes, the simulator and the bag tools all go through these functions, so an encoding rule
(image layouts, PointCloud2 fields, NavSatFix covariance) is written exactly once. Images are
converted here because cv_bridge is not available from PyPI.
"""

from __future__ import annotations

import numpy as np

from photogram_ros.core.camera import PinholeCamera
from photogram_ros.errors import DataError

from builtin_interfaces.msg import Time  # noqa: E402  (ROS imports after core on purpose)
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, NavSatFix, NavSatStatus, PointCloud2, PointField
from std_msgs.msg import Header, MultiArrayDimension, String, UInt8MultiArray

# --- time ----------------------------------------------------------------------------------------


def time_from_ns(stamp_ns: int) -> Time:
    stamp_ns = int(stamp_ns)
    return Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)


def ns_from_time(stamp: Time) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def header(stamp_ns: int, frame_id: str) -> Header:
    return Header(stamp=time_from_ns(stamp_ns), frame_id=frame_id)


# --- images --------------------------------------------------------------------------------------

_ENCODINGS = {  # encoding -> (dtype, channels)
    'mono8': (np.uint8, 1), '8UC1': (np.uint8, 1), 'bgr8': (np.uint8, 3), 'rgb8': (np.uint8, 3),
    'bgra8': (np.uint8, 4), 'rgba8': (np.uint8, 4), 'mono16': (np.uint16, 1), '16UC1': (np.uint16, 1),
    '32FC1': (np.float32, 1),
}


def image_msg(image: np.ndarray, stamp_ns: int, frame_id: str = 'camera_optical') -> Image:
    """numpy image (H, W) mono8/mono16/32FC1 or (H, W, 3) BGR -> sensor_msgs/Image."""
    img = np.ascontiguousarray(image)
    if img.ndim == 2:
        enc = {np.dtype(np.uint8): 'mono8', np.dtype(np.uint16): 'mono16',
               np.dtype(np.float32): '32FC1'}.get(img.dtype)
    elif img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
        enc = 'bgr8'
    else:
        enc = None
    if enc is None:
        raise DataError(f'cannot encode an image of shape {img.shape} and type {img.dtype}')
    msg = Image(header=header(stamp_ns, frame_id), height=img.shape[0], width=img.shape[1],
                encoding=enc, is_bigendian=0, step=img.strides[0])
    msg.data = img.tobytes()
    return msg


def compressed_image_msg(image: np.ndarray, stamp_ns: int, frame_id: str = 'camera_optical',
                         quality: int = 90) -> CompressedImage:
    import cv2
    ok, buf = cv2.imencode('.jpg', image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise DataError('JPEG encoding failed')
    msg = CompressedImage(header=header(stamp_ns, frame_id), format='jpeg')
    msg.data = buf.tobytes()
    return msg


def compressed_msg_from_bytes(data, stamp_ns: int, frame_id: str = 'camera_optical',
                              fmt: str = 'jpeg') -> CompressedImage:
    """Already-encoded image bytes (a camera's JPEG as it came) -> sensor_msgs/CompressedImage, not re-encoded."""
    msg = CompressedImage(header=header(stamp_ns, frame_id), format=fmt)
    msg.data = bytes(data)
    return msg


def decode_reduced(data, reduce: int) -> np.ndarray:
    """Encoded image bytes (JPEG, PNG: what cv2.imdecode reads) -> BGR at 1/`reduce` (1, 2, 4 or 8) of the
    full size, (ceil(H/reduce), ceil(W/reduce), 3): a JPEG through libjpeg's DCT scaling (a 20 MP photo at a
    quarter in about 0.06 s instead of 0.25 s for the full decode). EXIF orientation is ignored, as in the
    camera's frames. DataError if undecodable."""
    import cv2
    flags = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
             8: cv2.IMREAD_REDUCED_COLOR_8}
    if reduce not in flags:
        raise DataError(f'reduced decode by {reduce}: use 1, 2, 4 or 8')
    buf = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1)
    img = cv2.imdecode(buf, flags[reduce] | cv2.IMREAD_IGNORE_ORIENTATION) if buf.size else None
    if img is None:
        raise DataError(f'compressed image ({buf.size} bytes) cannot be decoded')
    return img


def image_from_msg(msg) -> np.ndarray:
    """sensor_msgs/Image or CompressedImage -> numpy (BGR uint8 for colour, 2-D for mono)."""
    if hasattr(msg, 'format'):  # CompressedImage
        import cv2
        buf = np.frombuffer(bytes(msg.data), dtype=np.uint8)
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
        if img is None:
            raise DataError(f'compressed image ({msg.format!r}, {buf.size} bytes) cannot be decoded')
        return img
    enc = msg.encoding
    if enc not in _ENCODINGS:
        raise DataError(f'unsupported image encoding {enc!r}; publish mono8, bgr8 or rgb8')
    dtype, ch = _ENCODINGS[enc]
    itemsize = np.dtype(dtype).itemsize
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0 or step < w * ch * itemsize or len(msg.data) < h * step:
        raise DataError(f'image {w}x{h} {enc} with step {step} has {len(msg.data)} bytes: truncated or '
                        'inconsistent')
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8, count=h * step).reshape(h, step)
    raw = raw[:, :w * ch * itemsize]
    img = raw.copy().view(dtype)
    if msg.is_bigendian and itemsize > 1:
        img = img.byteswap()
    img = img.reshape(h, w, ch) if ch > 1 else img.reshape(h, w)
    if enc == 'rgb8':
        img = img[:, :, ::-1].copy()
    elif enc == 'rgba8':
        img = img[:, :, [2, 1, 0]].copy()
    elif enc == 'bgra8':
        img = img[:, :, :3].copy()
    return img


# --- camera info ---------------------------------------------------------------------------------


def camera_info_msg(camera: PinholeCamera, stamp_ns: int, frame_id: str = 'camera_optical') -> CameraInfo:
    f = camera.to_camera_info_fields()
    return CameraInfo(header=header(stamp_ns, frame_id), width=f['width'], height=f['height'],
                      distortion_model=f['distortion_model'], d=f['d'], k=f['k'], r=f['r'], p=f['p'])


def camera_from_info(msg: CameraInfo) -> PinholeCamera:
    return PinholeCamera.from_camera_info_fields(msg.width, msg.height, msg.distortion_model,
                                                 list(msg.d), list(msg.k))


# --- GNSS ----------------------------------------------------------------------------------------


def navsatfix_msg(stamp_ns: int, lat_deg: float, lon_deg: float, h_m: float, status: int,
                  covariance_enu_m2, covariance_type: int, frame_id: str = 'gps',
                  service: int = NavSatStatus.SERVICE_GPS) -> NavSatFix:
    """NavSatFix with the ellipsoidal height (REP-145) and a 3x3 ENU covariance (m^2), or only its
    diagonal: the three variances (var_E, var_N, var_U) of a gnss_fix.GnssFix."""
    cov = np.asarray(covariance_enu_m2, dtype=float).reshape(-1)
    if cov.size == 3:
        cov = np.diag(cov).ravel()
    return NavSatFix(header=header(stamp_ns, frame_id),
                     status=NavSatStatus(status=int(status), service=int(service)),
                     latitude=float(lat_deg), longitude=float(lon_deg), altitude=float(h_m),
                     position_covariance=cov.tolist(), position_covariance_type=int(covariance_type))


def gnss_fix_from_navsatfix(msg: NavSatFix):
    """NavSatFix -> core.gnss_fix.GnssFix (its status as the quality, gnss_fix.quality_of_status; its altitude the
    ellipsoidal height, REP-145; source 'NavSatFix', native scale NavSatStatus)."""
    from photogram_ros.core.gnss_fix import GnssFix
    return GnssFix(msg.latitude, msg.longitude, msg.altitude,
                   np.asarray(msg.position_covariance, dtype=float).reshape(3, 3), ns_from_time(msg.header.stamp),
                   msg.status.status, msg.position_covariance_type, height_source='NavSatFix altitude',
                   source='NavSatFix', quality_native=int(msg.status.status), native_scale='NavSatStatus')


def fix_from_navsatfix(msg: NavSatFix) -> dict:
    """NavSatFix -> dict (stamp_ns, lat_deg, lon_deg, h_m, status, covariance_enu_m2 3x3, covariance_type,
    frame_id): GnssFix.as_dict of gnss_fix_from_navsatfix with the frame, for the callers that keep a dict."""
    return {**gnss_fix_from_navsatfix(msg).as_dict(), 'frame_id': msg.header.frame_id}


def fix_sigmas_m(msg: NavSatFix) -> tuple[float | None, float | None]:
    """(horizontal, vertical) 1-sigma of a NavSatFix's position, m: the larger of the east and north
    standard deviations and the up one; (None, None) when its covariance is unknown or not finite."""
    if msg.position_covariance_type == NavSatFix.COVARIANCE_TYPE_UNKNOWN:
        return None, None
    cov = np.asarray(msg.position_covariance, dtype=float).reshape(-1)
    if cov.size != 9 or not np.all(np.isfinite(cov[[0, 4, 8]])) or min(cov[0], cov[4], cov[8]) < 0:
        return None, None
    return float(np.sqrt(max(cov[0], cov[4]))), float(np.sqrt(cov[8]))


# --- raw bytes (MAVLink in bags) -----------------------------------------------------------------


def bytes_msg(data: bytes) -> UInt8MultiArray:
    msg = UInt8MultiArray()
    msg.layout.dim = [MultiArrayDimension(label='bytes', size=len(data), stride=len(data))]
    msg.data = bytes(data)
    return msg


def bytes_from_msg(msg: UInt8MultiArray) -> bytes:
    return bytes(msg.data)


# --- point clouds --------------------------------------------------------------------------------

_PF = {np.dtype(np.int8): PointField.INT8, np.dtype(np.uint8): PointField.UINT8,
       np.dtype(np.int16): PointField.INT16, np.dtype(np.uint16): PointField.UINT16,
       np.dtype(np.int32): PointField.INT32, np.dtype(np.uint32): PointField.UINT32,
       np.dtype(np.float32): PointField.FLOAT32, np.dtype(np.float64): PointField.FLOAT64}
_PF_INV = {v: k for k, v in _PF.items()}


def pointcloud2_msg(points: np.ndarray, stamp_ns: int, frame_id: str = 'map') -> PointCloud2:
    """Structured numpy array (named scalar fields) -> unordered PointCloud2 (height 1)."""
    arr = np.ascontiguousarray(points)
    if arr.dtype.names is None:
        raise DataError('pointcloud2_msg needs a structured array with named fields (x, y, z, ...)')
    fields = []
    for name in arr.dtype.names:
        dt, offset = arr.dtype.fields[name][:2]
        if dt.base not in _PF or dt.shape:
            raise DataError(f'field {name!r} of type {dt} cannot go into a PointCloud2')
        fields.append(PointField(name=name, offset=offset, datatype=_PF[dt.base], count=1))
    msg = PointCloud2(header=header(stamp_ns, frame_id), height=1, width=arr.shape[0], fields=fields,
                      is_bigendian=False, point_step=arr.dtype.itemsize,
                      row_step=arr.dtype.itemsize * arr.shape[0], is_dense=True)
    msg.data = arr.tobytes()
    return msg


def dense_cloud_msg(cloud: np.ndarray, stamp_ns: int, frame_id: str = 'map') -> PointCloud2:
    """A cloud in local map ENU metres (core.stereo.CLOUD_DTYPE or any structured array with x, y, z)
    -> PointCloud2 with x, y, z FLOAT32, the other fields as they are.

    RViz2's XYZ transformer draws FLOAT32 positions only. float32 rounds a coordinate by at most half
    its spacing: 0.12 mm within 2 km of the map origin, 0.5 mm within 8 km, 1 mm within 16 km; the
    exports keep float64 (they are written from the fused map, not from this message).
    """
    names = cloud.dtype.names or ()
    if not {'x', 'y', 'z'} <= set(names):
        raise DataError(f'a dense cloud needs x, y, z fields; got {names}')
    dtype = np.dtype([(n, np.float32 if n in ('x', 'y', 'z') else cloud.dtype.fields[n][0]) for n in names])
    if dtype == cloud.dtype:
        return pointcloud2_msg(cloud, stamp_ns, frame_id)
    out = np.empty(cloud.shape[0], dtype)
    for n in names:
        out[n] = cloud[n]
    return pointcloud2_msg(out, stamp_ns, frame_id)


def points_from_pointcloud2(msg: PointCloud2) -> np.ndarray:
    """PointCloud2 -> structured numpy array with the message's fields."""
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in _PF_INV:
            raise DataError(f'PointCloud2 field {f.name!r} has unknown datatype {f.datatype}')
        names.append(f.name)
        formats.append(_PF_INV[f.datatype].newbyteorder('>' if msg.is_bigendian else '<'))
        offsets.append(f.offset)
    dtype = np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': msg.point_step})
    n = int(msg.width) * int(msg.height)
    if len(msg.data) < n * msg.point_step:
        raise DataError(f'PointCloud2 has {len(msg.data)} bytes for {n} points of {msg.point_step} bytes')
    return np.frombuffer(bytes(msg.data), dtype=dtype, count=n).copy()


# --- posed keyframes and disparity (stereo) ------------------------------------------------------


def pose_with_covariance_from_T(a_T_b: np.ndarray, stamp_ns: int, frame_id: str = 'map',
                                covariance=None):
    """4x4 transform (child -> frame_id) and an optional 6x6 covariance (x, y, z, rx, ry, rz) ->
    geometry_msgs/PoseWithCovarianceStamped."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from photogram_ros.core.rotations import quat_from_R
    T = np.asarray(a_T_b, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DataError(f'pose must be a finite 4x4 transform, got shape {T.shape}')
    msg = PoseWithCovarianceStamped()
    msg.header = header(stamp_ns, frame_id)
    p, q = T[:3, 3], quat_from_R(T[:3, :3])
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = (float(v) for v in p)
    (msg.pose.pose.orientation.x, msg.pose.pose.orientation.y, msg.pose.pose.orientation.z,
     msg.pose.pose.orientation.w) = (float(v) for v in q)
    if covariance is not None:
        msg.pose.covariance = np.asarray(covariance, dtype=float).reshape(36).tolist()
    return msg


def T_from_pose_with_covariance(msg) -> tuple[np.ndarray, np.ndarray]:
    """geometry_msgs/PoseWithCovarianceStamped -> (4x4 transform child -> header.frame_id, 6x6 covariance)."""
    from photogram_ros.core.rotations import R_from_quat, make_T
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    q = np.array([o.x, o.y, o.z, o.w], dtype=float)
    t = np.array([p.x, p.y, p.z], dtype=float)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))) or np.linalg.norm(q) < 1e-9:
        raise DataError('pose has a non-finite position or a zero quaternion')
    return make_T(R_from_quat(q), t), np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)


def pose_is_provisional(msg) -> bool:
    """Whether a PoseWithCovarianceStamped from the bundle node is provisional (the roll about the first line
    assumed, before the first turn): its covariance carries the label (core/pose_status.py)."""
    from photogram_ros.core.pose_status import is_provisional
    return is_provisional(np.asarray(msg.pose.covariance, dtype=float))


def disparity_image_msg(disparity_px: np.ndarray, stamp_ns: int, f_px: float, baseline_m: float,
                        frame_id: str = 'camera_rect', delta_d: float = 1.0 / 16.0):
    """Float disparity (NaN = none; depth = f * baseline / d) -> stereo_msgs/DisparityImage."""
    from stereo_msgs.msg import DisparityImage
    d = np.asarray(disparity_px, dtype=np.float32)
    finite = np.isfinite(d)
    out = DisparityImage()
    out.header = header(stamp_ns, frame_id)
    # The message marks missing disparities with values below min_disparity.
    lo = float(np.min(d[finite])) if finite.any() else 0.0
    hi = float(np.max(d[finite])) if finite.any() else 0.0
    out.image = image_msg(np.where(finite, d, np.float32(lo - 1.0)).astype(np.float32), stamp_ns, frame_id)
    out.f, out.t = float(f_px), float(baseline_m)
    out.valid_window.width, out.valid_window.height = int(d.shape[1]), int(d.shape[0])
    out.min_disparity, out.max_disparity, out.delta_d = lo, hi, float(delta_d)
    return out


def imu_orientation_msg(stamp_ns: int, q_xyzw, orientation_var_rad2, angular_velocity_rad_s=None,
                        angular_velocity_var=0.0, frame_id: str = 'base_link'):
    """sensor_msgs/Imu carrying an orientation (FLU body in ENU, REP-103) with its covariance.

    Missing angular velocity and the (never sent) linear acceleration are marked unknown the
    sensor_msgs way: covariance element 0 = -1.
    """
    from sensor_msgs.msg import Imu
    q = np.asarray(q_xyzw, dtype=float)
    msg = Imu(header=header(stamp_ns, frame_id))
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = (float(v) for v in q)
    msg.orientation_covariance = np.diag(np.asarray(orientation_var_rad2, dtype=float)).ravel().tolist()
    if angular_velocity_rad_s is None:
        msg.angular_velocity_covariance = [-1.0] + [0.0] * 8
    else:
        w = np.asarray(angular_velocity_rad_s, dtype=float)
        msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = (float(v) for v in w)
        msg.angular_velocity_covariance = np.diag([float(angular_velocity_var)] * 3).ravel().tolist()
    msg.linear_acceleration_covariance = [-1.0] + [0.0] * 8
    return msg


def orientation_from_imu(msg) -> tuple[np.ndarray, np.ndarray]:
    """sensor_msgs/Imu -> (quaternion x, y, z, w; 3x3 orientation covariance)."""
    o = msg.orientation
    return (np.array([o.x, o.y, o.z, o.w], dtype=float),
            np.asarray(msg.orientation_covariance, dtype=float).reshape(3, 3))


# --- sparse map, path, georeference (bundle_node) ---------------------------------------------------


def sparse_cloud_msg(points_map: np.ndarray, stamp_ns: int, track_ids=None, frame_id: str = 'map') -> PointCloud2:
    """(N, 3) tie points in map (m) -> PointCloud2 x, y, z float32 (+ track_id uint32)."""
    p = np.asarray(points_map, dtype=float).reshape(-1, 3)
    dt = [('x', np.float32), ('y', np.float32), ('z', np.float32)]
    if track_ids is not None:
        dt.append(('track_id', np.uint32))
    arr = np.zeros(len(p), dtype=dt)
    arr['x'], arr['y'], arr['z'] = p[:, 0], p[:, 1], p[:, 2]
    if track_ids is not None:
        arr['track_id'] = np.asarray(track_ids, dtype=np.int64).astype(np.uint32)
    return pointcloud2_msg(arr, stamp_ns, frame_id)


def path_msg(map_T_cams, stamps_ns, stamp_ns: int, frame_id: str = 'map'):
    """Camera poses (K, 4, 4) with their stamps -> nav_msgs/Path."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path
    out = Path(header=header(stamp_ns, frame_id))
    for T, s in zip(map_T_cams, stamps_ns):
        pw = pose_with_covariance_from_T(T, s, frame_id)
        out.poses.append(PoseStamped(header=pw.header, pose=pw.pose.pose))
    return out


def georeference_msg(lat_deg: float, lon_deg: float, h_m: float, stamp_ns: int, frame_id: str = 'map') -> NavSatFix:
    """The geodetic origin of the map frame (ENU tangent at lat/lon, ellipsoidal height) as a NavSatFix."""
    return navsatfix_msg(stamp_ns, lat_deg, lon_deg, h_m, NavSatStatus.STATUS_FIX, [0.0, 0.0, 0.0],
                         NavSatFix.COVARIANCE_TYPE_UNKNOWN, frame_id)


# --- keyframe features (tracker -> bundle adjuster) ---------------------------------------------
#
# One PointCloud2 table per keyframe, fields track_id uint32, u, v, xn, yn float64 (FEATURE_DTYPE),
# stamped like the keyframe image. Rows with track_id >= TARGET_TRACK_ID_BASE are not tracks but
# ArUco targets found in the keyframe: marker id = track_id - TARGET_TRACK_ID_BASE, (u, v) the
# marker centre. They ride in the same message so that no second topic has to be paired with the
# keyframe; a reader that ignores them must drop those rows (features_from_keyframe_msg does).
# Tracker ids count up from 0 and would need 4e9 tracks to reach the base.

TARGET_TRACK_ID_BASE = 0xFFFF0000
MAX_MARKER_ID = 0xFFFFFFFF - TARGET_TRACK_ID_BASE


def keyframe_features_msg(observations: np.ndarray, stamp_ns: int, frame_id: str = 'camera_optical',
                          targets: np.ndarray | None = None) -> PointCloud2:
    """Keyframe observation table (core.tracker.FEATURE_DTYPE: track_id uint32, u, v, xn, yn), plus the
    ArUco targets of the keyframe (core.control.TARGET_DTYPE rows) in the reserved id range -> PointCloud2.

    Stamp it exactly like the keyframe image: subscribers pair the two by header stamp.
    """
    from photogram_ros.core.tracker import FEATURE_DTYPE
    names = observations.dtype.names or ()
    missing = [n for n in ('track_id', 'u', 'v', 'xn', 'yn') if n not in names]
    if missing:
        raise DataError(f'keyframe features lack the fields {missing}; build them with core.tracker.FEATURE_DTYPE')
    ids = np.asarray(observations['track_id'], np.int64)
    if len(ids) and ids.max() >= TARGET_TRACK_ID_BASE:
        raise DataError(f'track id {ids.max()} is in the range reserved for targets (>= {TARGET_TRACK_ID_BASE})')
    if targets is None or len(targets) == 0:
        return pointcloud2_msg(observations, stamp_ns, frame_id)
    marker = np.asarray(targets['marker_id'], np.int64)
    if marker.min() < 0 or marker.max() > MAX_MARKER_ID:
        raise DataError(f'marker ids must lie in [0, {MAX_MARKER_ID}], got {marker.min()}..{marker.max()}')
    rows = np.empty(len(observations) + len(targets), FEATURE_DTYPE)
    for n in FEATURE_DTYPE.names:
        if n != 'track_id':
            rows[n] = np.concatenate([observations[n], targets[n]])
    rows['track_id'] = np.concatenate([ids, marker + TARGET_TRACK_ID_BASE])
    return pointcloud2_msg(rows, stamp_ns, frame_id)


def keyframe_table_from_msg(msg: PointCloud2) -> tuple[np.ndarray, np.ndarray]:
    """PointCloud2 of keyframe features -> (tracks as core.tracker.FEATURE_DTYPE, targets as
    core.control.TARGET_DTYPE); float32 fields are widened."""
    from photogram_ros.core.control import TARGET_DTYPE
    from photogram_ros.core.tracker import FEATURE_DTYPE
    pts = points_from_pointcloud2(msg)
    missing = [n for n in FEATURE_DTYPE.names if n not in (pts.dtype.names or ())]
    if missing:
        raise DataError(f'PointCloud2 is not a keyframe feature table: fields {missing} are missing')
    is_target = np.asarray(pts['track_id'], np.int64) >= TARGET_TRACK_ID_BASE
    feats = np.empty(int((~is_target).sum()), FEATURE_DTYPE)
    targets = np.empty(int(is_target.sum()), TARGET_DTYPE)
    for n in FEATURE_DTYPE.names:
        feats[n] = pts[n][~is_target]
        if n != 'track_id':
            targets[n] = pts[n][is_target]
    targets['marker_id'] = np.asarray(pts['track_id'][is_target], np.int64) - TARGET_TRACK_ID_BASE
    return feats, targets


def features_from_keyframe_msg(msg: PointCloud2) -> np.ndarray:
    """PointCloud2 of keyframe features -> the tracks only (core.tracker.FEATURE_DTYPE; target rows dropped)."""
    return keyframe_table_from_msg(msg)[0]


def navsatfix_from_gnss_fix(fix, frame_id: str = 'gps') -> NavSatFix:
    """core.gnss_fix.GnssFix -> NavSatFix (e.g. the fix interpolated to a keyframe's stamp)."""
    return navsatfix_msg(fix.stamp_ns, fix.lat_deg, fix.lon_deg, fix.h_m, fix.status, fix.cov_enu_m2, fix.cov_type,
                         frame_id)


# --- survey quality: ortho tiles, coverage and control points (map_node, bundle_node -> ground station) ----

ORTHO_TILE_PREFIX = 'xyz/'


def ortho_tile_msg(z: int, x: int, y: int, png: bytes, stamp_ns: int) -> CompressedImage:
    """One XYZ / Web Mercator ortho tile (PNG bytes) -> CompressedImage; header.frame_id names the tile
    'xyz/Z/X/Y' (there is no TF frame for a map tile: the name is the whole georeference)."""
    msg = CompressedImage(header=header(stamp_ns, f'{ORTHO_TILE_PREFIX}{int(z)}/{int(x)}/{int(y)}'), format='png')
    msg.data = bytes(png)
    return msg


def ortho_tile_from_msg(msg: CompressedImage) -> tuple[int, int, int, bytes]:
    """CompressedImage of ortho_tile_msg -> (z, x, y, PNG bytes)."""
    name = msg.header.frame_id
    parts = name[len(ORTHO_TILE_PREFIX):].split('/') if name.startswith(ORTHO_TILE_PREFIX) else []
    if len(parts) != 3 or not all(p.isdigit() for p in parts) or msg.format != 'png':
        raise DataError(f'not an ortho tile: frame_id {name!r}, format {msg.format!r} (expected xyz/Z/X/Y, png)')
    z, x, y = (int(p) for p in parts)
    return z, x, y, bytes(msg.data)


def json_msg(obj) -> String:
    """A JSON document (GeoJSON coverage, control-point figures) -> std_msgs/String."""
    import json

    return String(data=json.dumps(obj, allow_nan=False, separators=(',', ':'), default=_json_default))


def json_from_msg(msg):
    """std_msgs/String of json_msg -> the document."""
    import json
    try:
        return json.loads(msg.data)
    except ValueError as exc:
        raise DataError(f'message is not JSON: {exc}') from exc


def _json_default(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(f'{type(v).__name__} is not JSON serialisable')
