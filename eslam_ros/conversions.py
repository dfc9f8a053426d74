"""Conversions between ROS 2 messages and the arrays / types of eslam_core.

Images: sensor_msgs/Image <-> numpy (colour HxWx3 uint8 RGB; depth HxW float32 metres, 0 = no measurement).
Depth follows REP 118: 16UC1 / mono16 hold millimetres, 32FC1 holds metres with NaN/inf for "no measurement".
Rows may be padded (`step` > width * bytes per pixel) and multi-byte pixels may be big-endian; both are honoured.

Camera: sensor_msgs/CameraInfo <-> eslam_core.camera.Intrinsics (pinhole K; distortion is ignored, so feed
rectified images, e.g. image_rect topics).

Poses: ESLAM poses are 4x4 camera-to-world matrices with the camera in the OpenCV *optical* frame (x right, y down,
z forward). That is REP 103's `<camera>_optical_frame`, the frame_id that drivers put on image headers. So a pose
converted here and published in the map frame is the pose of the image's frame_id in the map frame; no axis swap
is needed as long as the image frame_id is an optical frame. (ESLAM's world frame is the first camera pose squared
with the scene, so the map frame has near-optical axes too, y pointing down, unless the caller seeds the first pose
otherwise.)

Input messages are read by attribute only, so both rclpy messages and rosbags' deserialised dataclasses work.
Output messages are rclpy message objects.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Union

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, Quaternion
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest
from std_msgs.msg import Header

from eslam_core.camera import Intrinsics
from eslam_core.geometry import matrix_to_quaternion_xyzw, orthonormalize, quaternion_xyzw_to_matrix
from eslam_ros.cdr import CdrWriter


class UnsupportedImageError(ValueError):
    """The image encoding is not one this module converts."""


class MalformedImageError(ValueError):
    """The image's size fields and data disagree, or an array has the wrong shape / type."""


class InvalidCameraInfoError(ValueError):
    """The CameraInfo message does not describe a usable pinhole camera."""


class InvalidPoseError(ValueError):
    """A pose matrix or message is not a rigid transform."""


class InvalidStampError(ValueError):
    """A time stamp cannot be represented as a ROS time."""


Stamp = Union[float, Time]


@dataclass(frozen=True)
class _PixelFormat:
    channels: int
    dtype: np.dtype  # of one channel, little-endian; the message's is_bigendian flag decides the byte order


COLOR_ENCODINGS: dict[str, _PixelFormat] = {
    "rgb8": _PixelFormat(3, np.dtype(np.uint8)),
    "bgr8": _PixelFormat(3, np.dtype(np.uint8)),
    "rgba8": _PixelFormat(4, np.dtype(np.uint8)),
    "bgra8": _PixelFormat(4, np.dtype(np.uint8)),
    "mono8": _PixelFormat(1, np.dtype(np.uint8)),
}
DEPTH_ENCODINGS: dict[str, _PixelFormat] = {
    "16UC1": _PixelFormat(1, np.dtype("<u2")),
    "mono16": _PixelFormat(1, np.dtype("<u2")),
    "32FC1": _PixelFormat(1, np.dtype("<f4")),
}
# Units per metre of each depth encoding when the caller gives no depth_scale (REP 118).
DEFAULT_DEPTH_SCALE = {"16UC1": 1000.0, "mono16": 1000.0, "32FC1": 1.0}
_UINT16_MAX = 65535


# ------------------------------------------------------------------------------------------------ time stamps


def stamp_to_sec(stamp: Any) -> float:
    """Seconds of a builtin_interfaces/Time (or anything with `sec` and `nanosec`)."""
    return int(stamp.sec) + int(stamp.nanosec) * 1e-9


def sec_to_stamp(seconds: float) -> Time:
    """builtin_interfaces/Time of `seconds`, nanoseconds rounded to the nearest."""
    seconds = float(seconds)
    if not math.isfinite(seconds):
        raise InvalidStampError(f"time stamp must be a finite number of seconds, got {seconds!r}")
    sec = math.floor(seconds)
    nanosec = round((seconds - sec) * 1e9)
    if nanosec >= 1_000_000_000:  # rounding carried into the next second
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    if not -(2**31) <= sec < 2**31:
        raise InvalidStampError(
            f"time stamp {seconds} s does not fit a ROS time (int32 seconds); pass seconds since the epoch"
        )
    return Time(sec=sec, nanosec=nanosec)


def to_time(stamp: Stamp) -> Time:
    """builtin_interfaces/Time of seconds or of any time message (anything with `sec` and `nanosec`)."""
    if hasattr(stamp, "sec") and hasattr(stamp, "nanosec"):
        return Time(sec=int(stamp.sec), nanosec=int(stamp.nanosec))
    return sec_to_stamp(stamp)


def _header(stamp: Stamp, frame_id: str) -> Header:
    return Header(stamp=to_time(stamp), frame_id=str(frame_id))


# ------------------------------------------------------------------------------------------------ images in


def _pixels(msg: Any, fmt: _PixelFormat) -> np.ndarray:
    """(H, W, C) read-only view of the message's pixels, after checking its size fields against its data."""
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    bytes_per_pixel = fmt.channels * fmt.dtype.itemsize
    where = f"image ({msg.encoding}, {width}x{height})"
    if height <= 0 or width <= 0:
        raise MalformedImageError(f"{where} has zero size; the publisher sent an empty image")
    if step < width * bytes_per_pixel:
        raise MalformedImageError(
            f"{where}: step {step} bytes is smaller than width * bytes per pixel = {width} * {bytes_per_pixel} = "
            f"{width * bytes_per_pixel}; the step or encoding field of the publisher is wrong"
        )
    data = _byte_buffer(msg.data)
    if data.size != step * height:
        raise MalformedImageError(
            f"{where}: data has {data.size} bytes but step * height = {step} * {height} = {step * height}; "
            f"the message is truncated or its step / height fields are wrong"
        )
    dtype = fmt.dtype.newbyteorder(">" if msg.is_bigendian else "<")
    return np.ndarray(
        (height, width, fmt.channels),
        dtype=dtype,
        buffer=data,
        strides=(step, bytes_per_pixel, fmt.dtype.itemsize),
    )


def _byte_buffer(data: Any) -> np.ndarray:
    """The message's data as a flat uint8 array, without copying when the buffer protocol allows it."""
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:  # a plain list of ints
        return np.asarray(data, dtype=np.uint8)


def image_to_rgb(msg: Any) -> np.ndarray:
    """H x W x 3 uint8 RGB copy of a colour sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8 or mono8)."""
    fmt = COLOR_ENCODINGS.get(msg.encoding)
    if fmt is None:
        raise UnsupportedImageError(
            f"colour image encoding '{msg.encoding}' is not supported; accepted encodings: "
            f"{', '.join(COLOR_ENCODINGS)} (check that the rgb topic is not a depth or compressed image)"
        )
    pixels = _pixels(msg, fmt)
    if msg.encoding in ("rgb8", "rgba8"):
        rgb = pixels[..., :3]
    elif msg.encoding in ("bgr8", "bgra8"):
        rgb = pixels[..., 2::-1]
    else:  # mono8: grey replicated into the three channels
        rgb = np.broadcast_to(pixels, pixels.shape[:2] + (3,))
    return np.array(rgb, dtype=np.uint8, order="C", copy=True)


def image_to_depth(msg: Any, depth_scale: float | None = None) -> np.ndarray:
    """H x W float32 depth in metres (0 = no measurement) of a 16UC1, mono16 or 32FC1 sensor_msgs/Image.

    depth_scale: stored units per metre; default 1000 for 16-bit images (millimetres) and 1 for 32FC1 (metres).
    """
    fmt = DEPTH_ENCODINGS.get(msg.encoding)
    if fmt is None:
        raise UnsupportedImageError(
            f"depth image encoding '{msg.encoding}' is not supported; accepted encodings: "
            f"{', '.join(DEPTH_ENCODINGS)} (check that the depth topic is not a colour or compressed image)"
        )
    scale = DEFAULT_DEPTH_SCALE[msg.encoding] if depth_scale is None else float(depth_scale)
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"depth_scale must be a positive number of units per metre, got {depth_scale!r}")
    depth = _pixels(msg, fmt)[..., 0].astype(np.float32) / np.float32(scale)
    # NaN, +-inf and non-positive values all mean "no measurement" in REP 118; eslam_core uses 0 for that.
    depth[~(np.isfinite(depth) & (depth > 0))] = 0.0
    return depth


# ------------------------------------------------------------------------------------------------ images out


def rgb_to_image(rgb: np.ndarray, stamp: Stamp, frame_id: str, encoding: str = "rgb8") -> Image:
    """sensor_msgs/Image of an H x W x 3 uint8 RGB array (mono8 stores ITU-R BT.601 luma)."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8 or rgb.size == 0:
        raise MalformedImageError(
            f"colour image must be a non-empty H x W x 3 uint8 array, got shape {rgb.shape} dtype {rgb.dtype}"
        )
    if encoding in ("rgb8", "rgba8"):
        channels = rgb
    elif encoding in ("bgr8", "bgra8"):
        channels = rgb[..., ::-1]
    elif encoding == "mono8":
        luma = rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
        channels = np.clip(np.round(luma), 0, 255).astype(np.uint8)[..., None]
    else:
        raise UnsupportedImageError(f"cannot encode colour as '{encoding}'; choose one of {', '.join(COLOR_ENCODINGS)}")
    if encoding in ("rgba8", "bgra8"):
        opaque = np.full(rgb.shape[:2] + (1,), 255, dtype=np.uint8)
        channels = np.concatenate([channels, opaque], axis=2)
    return _image(channels, stamp, frame_id, encoding)


def depth_to_image(depth_m: np.ndarray, stamp: Stamp, frame_id: str, encoding: str = "16UC1") -> Image:
    """sensor_msgs/Image of an H x W depth array in metres (0 / non-finite = no measurement).

    16UC1 stores whole millimetres (depths beyond 65.535 m cannot be stored and become 0); 32FC1 stores metres
    with NaN for "no measurement".
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.ndim != 2 or depth.size == 0:
        raise MalformedImageError(f"depth image must be a non-empty H x W array of metres, got shape {depth.shape}")
    valid = np.isfinite(depth) & (depth > 0)
    if encoding == "16UC1":
        millimetres = np.round(np.where(valid, depth, 0.0) * 1000.0)
        millimetres[millimetres > _UINT16_MAX] = 0.0
        pixels = millimetres.astype("<u2")
    elif encoding == "32FC1":
        pixels = np.where(valid, depth, np.nan).astype("<f4")
    else:
        raise UnsupportedImageError(
            f"cannot encode depth as '{encoding}'; choose 16UC1 (millimetres) or 32FC1 (metres)"
        )
    return _image(pixels[..., None], stamp, frame_id, encoding)


def _image(pixels: np.ndarray, stamp: Stamp, frame_id: str, encoding: str) -> Image:
    """Little-endian, unpadded Image of an H x W x C array."""
    height, width = pixels.shape[:2]
    return Image(
        header=_header(stamp, frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * pixels.shape[2] * pixels.dtype.itemsize,
        data=np.ascontiguousarray(pixels).tobytes(),
    )


# ------------------------------------------------------------------------------------------------ camera info


def intrinsics_from_camera_info(msg: Any) -> Intrinsics:
    """Pinhole intrinsics of the images that go with `msg`, from its K matrix.

    K describes the full-resolution sensor; when the driver bins or crops (binning_x/y, roi) the published images
    are smaller, and K is mapped to them the way image_geometry does it.
    """
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    if k.size != 9 or not np.all(np.isfinite(k)):
        raise InvalidCameraInfoError(f"camera_info K must hold 9 finite numbers, got {list(k)}")
    if not np.any(k):
        raise InvalidCameraInfoError(
            "camera_info K matrix is all zeros: the camera is uncalibrated; calibrate it (camera_calibration) or "
            "set the intrinsics explicitly in the configuration"
        )
    fx, cx, fy, cy = k[0], k[2], k[4], k[5]
    bin_x, bin_y = max(int(msg.binning_x), 1), max(int(msg.binning_y), 1)
    roi = msg.roi
    cropped = int(roi.width) > 0 and int(roi.height) > 0
    x0, y0 = (int(roi.x_offset), int(roi.y_offset)) if cropped else (0, 0)
    width, height = (int(roi.width), int(roi.height)) if cropped else (int(msg.width), int(msg.height))
    try:
        return Intrinsics(
            width=width // bin_x,
            height=height // bin_y,
            fx=float(fx / bin_x),
            fy=float(fy / bin_y),
            cx=float((cx - x0) / bin_x),
            cy=float((cy - y0) / bin_y),
        )
    except ValueError as error:
        raise InvalidCameraInfoError(f"camera_info does not describe a usable pinhole camera: {error}") from error


def camera_info_from_intrinsics(intr: Intrinsics, stamp: Stamp, frame_id: str) -> CameraInfo:
    """CameraInfo of an undistorted pinhole camera (plumb_bob with zero coefficients, P = [K | 0])."""
    k = intr.matrix()
    p = np.hstack([k, np.zeros((3, 1))])
    return CameraInfo(
        header=_header(stamp, frame_id),
        height=intr.height,
        width=intr.width,
        distortion_model="plumb_bob",
        d=[0.0] * 5,
        k=k.reshape(-1).tolist(),
        r=np.eye(3).reshape(-1).tolist(),
        p=p.reshape(-1).tolist(),
        binning_x=0,
        binning_y=0,
        roi=RegionOfInterest(),
    )


# ------------------------------------------------------------------------------------------------ poses


# One home for the quaternion formulas (eslam_core.geometry); these are the names the node and tests use.
rotation_to_quaternion = matrix_to_quaternion_xyzw
quaternion_to_rotation = quaternion_xyzw_to_matrix


# Rotations drift from orthonormal (float32 optimiser output, poses composed over thousands of frames): the nearest
# rigid transform is published. A matrix further than this from a rotation is not a drifted pose but a wrong one.
_ROTATION_DRIFT_LIMIT = 1e-2


def rigid_transforms(poses: np.ndarray) -> np.ndarray:
    """(..., 4, 4) -> (...) bool: finite, a rotation within the drift limit of orthonormal, bottom row 0 0 0 1."""
    t = np.asarray(poses, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        rotation = t[..., :3, :3]
        error = np.abs(np.swapaxes(rotation, -1, -2) @ rotation - np.eye(3)).max(axis=(-2, -1))
        bottom_error = np.abs(t[..., 3, :] - [0, 0, 0, 1]).max(axis=-1)
        return (np.isfinite(t).all(axis=(-2, -1)) & (error <= _ROTATION_DRIFT_LIMIT)
                & (bottom_error <= _ROTATION_DRIFT_LIMIT) & (np.linalg.det(np.nan_to_num(rotation)) > 0))


def path_cdr(timestamps: np.ndarray, poses: np.ndarray, frame_id: str) -> bytes:
    """nav_msgs/Path of (N,) stamps in seconds and (N, 4, 4) poses as CDR bytes, for Publisher.publish. A pose that
    is not a rigid transform, or a stamp that is no ROS time, is left out; the others are re-orthonormalised. The
    header's stamp is the last pose's."""
    ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    with np.errstate(invalid="ignore"):
        sec = np.floor(ts)
        nanosec = np.round((ts - sec) * 1e9)
        carry = nanosec >= 1e9  # rounding carried into the next second
        sec, nanosec = sec + carry, np.where(carry, nanosec - 1e9, nanosec)
        keep = rigid_transforms(poses) & np.isfinite(ts) & (sec >= -(2**31)) & (sec < 2**31)
    poses, sec, nanosec = orthonormalize(poses[keep]), sec[keep], nanosec[keep]
    pose7 = np.concatenate([poses[:, :3, 3], matrix_to_quaternion_xyzw(poses[:, :3, :3])], axis=1)
    w = CdrWriter()
    w.primitives("i", int(sec[-1]) if len(sec) else 0)
    w.primitives("I", int(nanosec[-1]) if len(sec) else 0)
    w.string(frame_id)
    w.primitives("I", len(sec))
    if len(sec):  # the first PoseStamped by hand: where it starts decides its padding; after it, every one is alike
        w.primitives("i", int(sec[0]))
        w.primitives("I", int(nanosec[0]))
        w.string(frame_id)
        w.primitives("d", *pose7[0])
        name = frame_id.encode("utf-8") + b"\x00"
        before_pose = 12 + len(name)  # sec, nanosec, string length, string (records start 8-aligned from here on)
        pose_at = before_pose + (-before_pose % 8)
        record = np.dtype({"names": ["sec", "nanosec", "length", "frame_id", "pose"],
                           "formats": ["<i4", "<u4", "<u4", f"S{len(name)}", ("<f8", (7,))],
                           "offsets": [0, 4, 8, 12, pose_at], "itemsize": pose_at + 56})
        rest = np.zeros(len(sec) - 1, record)
        rest["sec"], rest["nanosec"], rest["length"] = sec[1:], nanosec[1:], len(name)
        rest["frame_id"], rest["pose"] = name, pose7[1:]
        w.structs(rest, 8)
    return w.getvalue()


def pose_to_msg(pose: np.ndarray) -> Pose:
    """geometry_msgs/Pose of a 4x4 rigid transform (camera-to-world, camera = optical frame), re-orthonormalised."""
    t = np.asarray(pose, dtype=np.float64)
    if t.shape != (4, 4):
        raise InvalidPoseError(f"pose must be a 4x4 matrix, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise InvalidPoseError(f"pose contains NaN or inf (tracking diverged?): {t.tolist()}")
    if not rigid_transforms(t)[()]:
        rotation = t[:3, :3]
        error = np.abs(rotation.T @ rotation - np.eye(3)).max()
        raise InvalidPoseError(
            f"pose is not a rigid transform (|R^T R - I| = {error:.2e}, det R = {np.linalg.det(rotation):.3f}, "
            f"bottom row {t[3].tolist()}); pass a camera-to-world [R t; 0 0 0 1] matrix"
        )
    t = orthonormalize(t)
    rotation = t[:3, :3]
    x, y, z, w = rotation_to_quaternion(rotation)
    return Pose(
        position=Point(x=float(t[0, 3]), y=float(t[1, 3]), z=float(t[2, 3])),
        orientation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)),
    )


def msg_to_pose(msg: Any) -> np.ndarray:
    """4x4 float64 rigid transform of a geometry_msgs/Pose (the quaternion is normalised)."""
    o, p = msg.orientation, msg.position
    q = np.array([o.x, o.y, o.z, o.w], dtype=np.float64)
    norm = np.linalg.norm(q)
    if not (np.all(np.isfinite(q)) and norm > 1e-9):
        raise InvalidPoseError(
            f"pose orientation {q.tolist()} is not a valid quaternion (x, y, z, w); it must have norm 1"
        )
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_rotation(q / norm)
    pose[:3, 3] = [p.x, p.y, p.z]
    if not np.all(np.isfinite(pose)):
        raise InvalidPoseError(f"pose position {pose[:3, 3].tolist()} is not finite")
    return pose
