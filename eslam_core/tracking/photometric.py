"""Photometric alignment to a reference keyframe, for the fast SDF tracker (not part of the paper's method).

The SDF residuals of back-projected depth leave the pose free along directions in which the visible surfaces slide
along themselves (a wall and a floor fix only three or four of the six degrees of freedom), and the map's colour is
too blurred to hold it there. The sensor's own images are sharp: the last keyframe (its colour, depth and pose) is
the reference, and a point x of the current frame should have the grey level of the reference pixel it projects to,
I_r(pi(R_r^T (x - t_r))) = I_c(u). Both images are turned into a pyramid (2x2 averages) so that the first
iterations see a blurred image whose basin covers the error of the constant-velocity prediction; the gradients are
central differences, given in full-resolution pixel units at every level so that the Jacobian is level-independent.
"""
from __future__ import annotations

import ctypes
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from eslam_core.camera import Intrinsics
from eslam_core.native import load_kernel, pointer

GREY = torch.tensor([0.299, 0.587, 0.114])
_GREY_ON: dict = {}  # device -> GREY there (copied once: a copy per call would make the host wait for a GPU)


def to_grey(rgb: torch.Tensor) -> torch.Tensor:
    """(..., 3) colour -> (...) grey level, on the colour's device."""
    weights = _GREY_ON.get(rgb.device)
    if weights is None:
        weights = _GREY_ON[rgb.device] = GREY.to(rgb.device)
    return rgb @ weights


def grey_pyramid(rgb: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """(H, W, 3) colour in [0, 1] -> grey images, full resolution first, each next one half the size (2 x 2
    averages)."""
    if rgb.device.type == "cpu" and rgb.dtype == torch.float32:
        return _grey_pyramid_cv(rgb.contiguous().numpy(), levels)
    grey = to_grey(rgb)[None, None]
    pyramid = [grey]
    for _ in range(levels - 1):
        if min(grey.shape[-2:]) < 8:
            break
        grey = F.avg_pool2d(grey, 2)
        pyramid.append(grey)
    return [g[0, 0] for g in pyramid]


def _grey_pyramid_cv(rgb: np.ndarray, levels: int) -> list[torch.Tensor]:
    """The same with OpenCV, 5x faster on a CPU (a tracked frame's pyramid: 1.5 -> 0.2 ms). Its RGB2GRAY weights are
    GREY's; INTER_AREA at half size is the 2 x 2 average (avg_pool2d's floor of odd sizes included)."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    pyramid = [grey]
    for _ in range(levels - 1):
        if min(grey.shape) < 8:
            break
        h, w = grey.shape[0] // 2, grey.shape[1] // 2
        grey = cv2.resize(grey[:2 * h, :2 * w], (w, h), interpolation=cv2.INTER_AREA)
        pyramid.append(grey)
    return [torch.from_numpy(g) for g in pyramid]


def with_gradients(grey: torch.Tensor, scale: float) -> torch.Tensor:
    """(h, w) grey at 1/scale resolution -> (1, 3, h, w): grey, dI/du, dI/dv per full-resolution pixel."""
    padded = F.pad(grey[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    du = (padded[1:-1, 2:] - padded[1:-1, :-2]) / (2.0 * scale)
    dv = (padded[2:, 1:-1] - padded[:-2, 1:-1]) / (2.0 * scale)
    return torch.stack([grey, du, dv])[None]


def sample(image: torch.Tensor, u: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    """Bilinear samples (N, C) of a (1, C, h, w) level at full-resolution pixel coordinates (u, v)."""
    h, w = image.shape[-2:]
    # Pixel centres: full-resolution pixel u covers level coordinates around (u + 0.5) / scale - 0.5.
    gu = ((u + 0.5) / scale - 0.5) / max(w - 1, 1) * 2.0 - 1.0
    gv = ((v + 0.5) / scale - 0.5) / max(h - 1, 1) * 2.0 - 1.0
    grid = torch.stack([gu, gv], -1)[None, None]
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=True)[0, :, 0].T


@dataclass
class Reference:
    """A keyframe prepared for alignment: levels of (grey, gradients) and its depth and pose."""

    frame_index: int
    levels: list[torch.Tensor]  # (1, 3, h, w) per level, full resolution first
    depth: torch.Tensor  # (H, W) metres
    pose: torch.Tensor  # (4, 4) camera-to-world

    @staticmethod
    def build(frame_index: int, rgb: torch.Tensor, depth: torch.Tensor, pose: torch.Tensor,
              levels: int) -> "Reference":
        pyramid = grey_pyramid(rgb, levels)
        return Reference(frame_index, [with_gradients(g, 2.0**i) for i, g in enumerate(pyramid)], depth,
                         pose.double())


def photometric_residuals(x: torch.Tensor, grey_current: torch.Tensor, ref: Reference, level: int,
                          intr: Intrinsics, occlusion: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Residuals I_r(pi(x)) - I_c (N,), their gradients in the world point x (N, 3) and which are valid (N,).

    A point is valid when it lands inside the reference image in front of the camera and the reference saw the
    same surface there: its depth agrees with the reference depth to within `occlusion` metres. On CPU tensors
    (double points) one pass of the C kernel (kernels/photometric.c) computes the same.
    """
    native = _native_residuals(x, grey_current, ref, level, intr, occlusion)
    if native is not None:
        return native
    pose = ref.pose.to(x.dtype)
    p = (x - pose[:3, 3]) @ pose[:3, :3]  # R^T (x - t) for row vectors: the point in the reference camera
    u, v = intr.project(p)
    z = p[:, 2]
    valid = (z > 0.05) & (u >= 1) & (u <= intr.width - 2) & (v >= 1) & (v <= intr.height - 2)
    ui = u.round().long().clamp(0, intr.width - 1)
    vi = v.round().long().clamp(0, intr.height - 1)
    d_ref = ref.depth[vi, ui].to(x.dtype)
    valid &= (d_ref > 0) & ((d_ref - z).abs() < occlusion)
    scale = 2.0**level
    s = sample(ref.levels[level], u.float(), v.float(), scale).to(x.dtype)
    residual = s[:, 0] - grey_current
    iu, iv = s[:, 1], s[:, 2]
    zc = z.clamp_min(1e-6)
    grad_cam = torch.stack([iu * intr.fx / zc, iv * intr.fy / zc,
                            -(iu * intr.fx * p[:, 0] + iv * intr.fy * p[:, 1]) / zc**2], -1)
    return residual, grad_cam @ pose[:3, :3].T, valid


def _native_residuals(x: torch.Tensor, grey_current: torch.Tensor, ref: Reference, level: int, intr: Intrinsics,
                      occlusion: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    image, depth = ref.levels[level], ref.depth
    if not (x.device.type == depth.device.type == image.device.type == "cpu" and x.dtype == grey_current.dtype
            == torch.float64 and image.dtype == depth.dtype == torch.float32
            and tuple(depth.shape) == (intr.height, intr.width)):
        return None
    lib = load_kernel("photometric")
    if lib is None:
        return None
    x, grey_current = x.contiguous(), grey_current.contiguous()
    image, depth, pose = image.contiguous(), depth.contiguous(), ref.pose.double().contiguous()
    n, (h, w) = len(x), image.shape[-2:]
    residual, grad = torch.empty(n, dtype=torch.float64), torch.empty(n, 3, dtype=torch.float64)
    valid = torch.empty(n, dtype=torch.bool)
    c_double, c_int64 = ctypes.c_double, ctypes.c_int64
    lib.photometric_residuals(
        pointer(x), c_int64(n), pointer(pose), c_double(intr.fx), c_double(intr.fy), c_double(intr.cx),
        c_double(intr.cy), c_int64(intr.width), c_int64(intr.height), pointer(depth), pointer(image), c_int64(h),
        c_int64(w), c_double(2.0**level), pointer(grey_current), c_double(occlusion), pointer(residual),
        pointer(grad), pointer(valid))
    return residual, grad, valid
