"""Input frames turned into the tensors the method works on (resizing, depth cut)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np
import torch
from PIL import Image

from eslam_core.camera import Frame, Intrinsics
from eslam_core.config import CameraConfig


@dataclass
class PreparedFrame:
    index: int
    timestamp: float
    rgb: torch.Tensor  # (H, W, 3) float32 in [0, 1]
    depth: torch.Tensor  # (H, W) float32 metres, 0 = missing
    gt_pose: Optional[np.ndarray]
    odom_pose: Optional[np.ndarray] = None  # see Frame.odom_pose


def working_intrinsics(intr: Intrinsics, cam: CameraConfig) -> Intrinsics:
    return intr if cam.image_scale == 1.0 else intr.scaled(cam.image_scale)


def working_images(frame: Frame, intr: Intrinsics, cam: CameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """Check the frame against the camera, resize it to the working resolution and cut far depth: colour (H, W, 3)
    uint8 and depth (H, W) float32 metres, 0 = missing. (Numpy only: the runtime's parent process calls it per
    frame, and torch's threads there would wait for cores the workers hold.)"""
    rgb, depth = frame.rgb, frame.depth
    if rgb.shape[:2] != depth.shape or rgb.shape[:2] != (intr.height, intr.width):
        raise ValueError(f"frame {frame.index}: image sizes rgb {rgb.shape[:2]} / depth {depth.shape} do not match "
                         f"the camera ({intr.height}, {intr.width}); check the camera section of the config")
    if rgb.dtype != np.uint8:
        raise ValueError(f"frame {frame.index}: rgb is {rgb.dtype}, expected uint8 (0-255) colour")
    work = working_intrinsics(intr, cam)
    if (work.width, work.height) != (intr.width, intr.height):
        rgb = np.asarray(Image.fromarray(rgb).resize((work.width, work.height), Image.BILINEAR))
        # Nearest neighbour for depth: averaging across a depth edge would invent surfaces in between.
        depth = np.asarray(Image.fromarray(depth).resize((work.width, work.height), Image.NEAREST))
    depth = np.nan_to_num(depth.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    depth[depth < 0] = 0
    if cam.max_depth > 0:
        depth[depth > cam.max_depth] = 0
    return rgb, depth


def prepare_frame(frame: Frame, intr: Intrinsics, cam: CameraConfig) -> PreparedFrame:
    """The frame at the working resolution (working_images) as the method's tensors."""
    rgb, depth = working_images(frame, intr, cam)
    return PreparedFrame(frame.index, frame.timestamp, torch.from_numpy(rgb.astype(np.float32) / 255.0),
                         torch.from_numpy(depth), frame.pose, frame.odom_pose)


def rgb_uint8(rgb: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) colour in [0, 1] -> uint8 (host), rounded to nearest: keyframes store it, ORB reads it. OpenCV
    does it 15x faster than torch's three passes on a CPU (0.2 vs 3 ms for 640x480)."""
    if rgb.device.type == "cpu" and rgb.dtype == torch.float32:
        return torch.from_numpy(cv2.convertScaleAbs(rgb.contiguous().numpy(), alpha=255.0))
    return (rgb * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).cpu()


def pixel_directions_table(intr: Intrinsics) -> torch.Tensor:
    """(H*W, 3) camera-frame ray directions with unit z, row-major pixel order."""
    v, u = torch.meshgrid(torch.arange(intr.height, dtype=torch.float32),
                          torch.arange(intr.width, dtype=torch.float32), indexing="ij")
    return torch.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, torch.ones_like(u)], -1).reshape(-1, 3)


def border_mask(height: int, width: int, border: int) -> torch.Tensor:
    m = torch.zeros(height, width, dtype=torch.bool)
    b = min(border, (min(height, width) - 1) // 2)
    m[b: height - b, b: width - b] = True
    return m
