"""The scene bound: the axis-aligned box the feature planes cover.

Given by the config when known; otherwise estimated from the first frame (its back-projected depth and the camera
centre, plus a margin). Each axis is grown to a whole number of coarse cells so that every plane grid fits exactly.
"""
from __future__ import annotations

import numpy as np
import torch

from eslam_core.camera import Intrinsics, backproject


def grow_to_multiple(bound: np.ndarray, step: float) -> np.ndarray:
    """Grow each axis symmetrically so its extent is a whole multiple of `step`."""
    bound = np.asarray(bound, dtype=np.float64)
    extent = bound[1] - bound[0]
    target = np.ceil(extent / step - 1e-9) * step
    pad = (target - extent) / 2
    return np.stack([bound[0] - pad, bound[1] + pad])


def estimate_bound(depth: np.ndarray, intr: Intrinsics, pose: np.ndarray, margin: float, step: float) -> np.ndarray:
    """Box around the first frame's observed points (1st-99th percentile, robust to stray depth) and the camera."""
    points = backproject(depth, intr, pose, stride=2)
    if len(points) < 100:
        raise ValueError("cannot estimate the scene bound: the first frame has almost no valid depth; "
                         "set scene.bound in the config or start at a frame with depth (--frames A:B)")
    lo = np.minimum(np.percentile(points, 1, axis=0), pose[:3, 3])
    hi = np.maximum(np.percentile(points, 99, axis=0), pose[:3, 3])
    return grow_to_multiple(np.stack([lo - margin, hi + margin]), step)


def outside_mask(points: torch.Tensor, bound: np.ndarray) -> torch.Tensor:
    """(N,) bool: the point lies outside the axis-aligned bound (2, 3)."""
    lo, hi = (torch.as_tensor(b, dtype=points.dtype) for b in bound)
    return ((points < lo) | (points > hi)).any(-1)
