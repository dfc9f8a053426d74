"""Pinhole camera and RGB-D frame types shared by every module.

Conventions (used everywhere in eslam_core):
- Poses are camera-to-world 4x4 matrices in OpenCV camera axes (x right, y down, z forward).
- Depth is float32 metres; 0 means "no measurement".
- Colour is uint8 RGB, H x W x 3.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Optional

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx} fy={self.fy}")

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project(self, p_cam):
        """Pixel coordinates (u, v) of camera points (..., 3) (torch tensors). Depth is clamped to 1e-6 so that
        points behind the camera give finite values: callers test z themselves."""
        z = p_cam[..., 2].clamp_min(1e-6)
        return self.fx * p_cam[..., 0] / z + self.cx, self.fy * p_cam[..., 1] / z + self.cy

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics of the image resized by `factor` (pixel-centre convention)."""
        return replace(
            self,
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
        )


@dataclass
class Frame:
    index: int  # position in the sequence as read (0-based)
    timestamp: float  # seconds (or the data set's frame number when it has no clock)
    rgb: np.ndarray  # H x W x 3 uint8
    depth: np.ndarray  # H x W float32 metres, 0 = missing
    pose: Optional[np.ndarray] = None  # 4x4 float64 camera-to-world (OpenCV axes), None = no ground truth
    # 4x4 float64 camera-to-odom from an external odometry (wheel, VIO) at this frame's stamp, OpenCV axes; its
    # motion between frames is the tracker's prior (and, with tracking.mode "external", the pose). None = none.
    odom_pose: Optional[np.ndarray] = None
    # The caller's own record of the frame (a ROS node: the image's stamp and frame id), handed back with the frame's
    # pose (PoseUpdate.tag); SLAM never reads it.
    tag: Any = None


def backproject(depth: np.ndarray, intr: Intrinsics, pose: Optional[np.ndarray] = None, stride: int = 1) -> np.ndarray:
    """3D points (N x 3) of the valid depth pixels, in world coordinates when `pose` is given."""
    d = depth[::stride, ::stride]
    v, u = np.nonzero(d > 0)
    z = d[v, u].astype(np.float64)
    u = u * stride
    v = v * stride
    pts = np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], axis=1)
    if pose is not None:
        pts = pts @ pose[:3, :3].T + pose[:3, 3]
    return pts


def register_colour(rgb: np.ndarray, depth: np.ndarray, depth_intr: Intrinsics, colour_intr: Intrinsics,
                    depth_to_colour: Optional[np.ndarray] = None) -> np.ndarray:
    """The colour image resampled onto the depth camera's pixels (H x W x 3 uint8, the depth image's size).

    Each depth pixel takes the colour where its point projects into the colour camera; `depth_to_colour` is the
    4x4 pose of the depth camera in the colour camera's frame (None: the same centre and axes). A pixel without
    depth has no point and is taken at infinity, where only the rotation counts. Occlusion between the two views
    is ignored: at a Kinect's 2.5 cm baseline it affects a few pixels along depth edges.
    """
    import cv2  # (opencv-python-headless, a dependency of the relocalizer)

    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(u - depth_intr.cx) / depth_intr.fx, (v - depth_intr.cy) / depth_intr.fy, np.ones_like(u)], -1)
    R, t = (np.eye(3), np.zeros(3)) if depth_to_colour is None else (depth_to_colour[:3, :3], depth_to_colour[:3, 3])
    z = depth.astype(np.float64)
    has_depth = (z > 0)[..., None]
    points = np.where(has_depth, rays * z[..., None] @ R.T + t, rays @ R.T)
    in_front = np.maximum(points[..., 2], 1e-6)
    map_u = (colour_intr.fx * points[..., 0] / in_front + colour_intr.cx).astype(np.float32)
    map_v = (colour_intr.fy * points[..., 1] / in_front + colour_intr.cy).astype(np.float32)
    return cv2.remap(np.ascontiguousarray(rgb), map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
