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
    lo, hi = (torch.as_tensor(b, dtype=points.dtype, device=points.device) for b in bound)
    if len(points) > 0:  # usually all inside: one pass for the box of the points instead of six comparisons
        low, high = torch.aminmax(points, dim=0)
        if bool((low >= lo).all() & (high <= hi).all()):
            return torch.zeros(len(points), dtype=torch.bool, device=points.device)
    return ((points < lo) | (points > hi)).any(-1)


def grown_extent(extent: np.ndarray, points: torch.Tensor, step: float, margin: float,
                 max_extent: float) -> tuple[np.ndarray, int]:
    """The extent grown by whole `step` cells on each side that `points` (N, 3) leave, with `margin` metres to
    spare, each axis capped at `max_extent` metres (growth towards the side of the points stops there). Returns the
    new extent and how many points it still leaves out."""
    if len(points) == 0:
        return extent, 0
    lo, hi = points.amin(0).double().numpy(), points.amax(0).double().numpy()
    new = extent.copy()
    below, above = lo < extent[0], hi > extent[1]
    new[0, below] -= np.ceil((extent[0, below] - lo[below] + margin) / step - 1e-9) * step
    new[1, above] += np.ceil((hi[above] - extent[1, above] + margin) / step - 1e-9) * step
    for axis in range(3):  # over the cap: keep the side that grew least (the stray side is cut first)
        while new[1, axis] - new[0, axis] > max_extent + 1e-9:
            grow_lo, grow_hi = extent[0, axis] - new[0, axis], new[1, axis] - extent[1, axis]
            if grow_lo <= 0 and grow_hi <= 0:
                break
            side = 0 if grow_lo >= grow_hi else 1
            new[side, axis] += step if side == 0 else -step
    return new, int(outside_mask(points, new).sum())


def draw_in_extent(candidates: torch.Tensor, n: int, world_points, extent: np.ndarray | None
                   ) -> tuple[torch.Tensor, float]:
    """Up to n pixels drawn at random (with replacement) from `candidates` whose depth point (`world_points(pixels)`
    at the starting pose) lies inside the map's extent (the field knows nothing beyond it), and the fraction of the
    candidates inside, estimated from the draw. Testing only drawn pixels costs 2n points instead of every pixel
    (12 ms for a 640x480 frame on one core); a frame mostly outside gets a second, larger draw (up to 16n)."""
    if len(candidates) == 0:
        return candidates, 0.0

    def draw(k: int) -> torch.Tensor:
        return candidates[torch.randint(len(candidates), (k,), device=candidates.device)]  # (randperm: 2 ms)

    first = draw(2 * n)
    if extent is None:
        return first[:n], 1.0
    inside = ~outside_mask(world_points(first), extent)
    share, kept = float(inside.float().mean()), first[inside]
    if 0 < len(kept) < n:
        more = draw(min(16 * n, int(1.2 * (n - len(kept)) / share) + 1))
        kept = torch.cat([kept, more[~outside_mask(world_points(more), extent)]])
    return kept[:n], share
