"""Depth L1 (NICE-SLAM / ESLAM 2D metric): render both meshes from random views inside the scene, compare depth.

Views follow NICE-SLAM's recipe: a random position inside the ground-truth bounding box (shrunk by a margin, so the
camera is inside the room rather than on its walls) looking at a random point of the box. A view whose ground-truth
render is mostly empty (looking out of a hole of a culled mesh) is skipped and replaced by the next random one.
The per-view error is the mean |depth_gt - depth_rec| over pixels where both meshes have a surface; the metric is
the mean over views. Pixels where only the ground truth has a surface are reported separately (missing fraction):
completion measures holes, depth L1 measures the geometry that is there.

Rendering is Embree ray casting on the CPU (eslam_core.rendering.raycast), so it runs headless.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import trimesh

from eslam_core.camera import Intrinsics
from eslam_core.rendering.raycast import render_depth
from eslam_core.evaluation.reconstruction import MeshError, check_mesh


@dataclass(frozen=True, eq=False)
class DepthView:
    pose: np.ndarray  # 4x4 camera-to-world
    gt_depth: np.ndarray  # H x W metres, 0 = no surface
    rec_depth: np.ndarray


@dataclass(frozen=True, eq=False)
class DepthL1Result:
    mean: float  # metres, mean over views of the per-view mean |difference|
    per_view: np.ndarray  # (n_views,) metres; nan for a view where the two renders share no pixel
    missing_fraction: float  # of ground-truth surface pixels, those where the reconstruction shows nothing
    n_views: int  # accepted views
    n_skipped: int  # random views rejected for too little ground-truth depth
    intrinsics: Intrinsics
    poses: np.ndarray  # (n_views, 4, 4)
    seconds: float  # wall time of the rendering
    examples: tuple[DepthView, ...]  # the first few views, for plots


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: z forward, y down) at `position` looking at `target`.

    Roll is fixed by keeping the image x axis horizontal in the world x-y plane (world z as "up"), or, when looking
    along z, by world x; depth L1 does not depend on roll.
    """
    forward = np.asarray(target, dtype=np.float64) - np.asarray(position, dtype=np.float64)
    norm = np.linalg.norm(forward)
    if norm < 1e-9:
        raise ValueError("look_at needs a target distinct from the camera position")
    forward /= norm
    up = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, position
    return pose


def random_view(bounds: np.ndarray, margin: float, rng: np.random.Generator) -> np.ndarray:
    """One random pose: position uniform in `bounds` shrunk by `margin` (a fraction of each side, per end),
    looking at a point uniform in `bounds`."""
    low, high = bounds
    extent = high - low
    position = low + extent * (margin + (1 - 2 * margin) * rng.random(3))
    while True:
        target = low + extent * rng.random(3)
        if np.linalg.norm(target - position) > 1e-3 * max(float(extent.max()), 1e-3):
            return look_at(position, target)


def default_intrinsics(width: int = 160, height: int = 120) -> Intrinsics:
    """A 90 degree horizontal field of view, like the virtual camera of NICE-SLAM's evaluation."""
    return Intrinsics(width, height, fx=width / 2, fy=width / 2, cx=(width - 1) / 2, cy=(height - 1) / 2)


def depth_l1(
    rec_mesh: trimesh.Trimesh,
    gt_mesh: trimesh.Trimesh,
    n_views: int = 1000,
    seed: int = 0,
    width: int = 160,
    height: int = 120,
    fx: Optional[float] = None,
    fy: Optional[float] = None,
    cx: Optional[float] = None,
    cy: Optional[float] = None,
    margin: float = 0.1,
    min_valid_fraction: float = 0.5,
    poses: Optional[np.ndarray] = None,
    n_examples: int = 3,
    max_attempts_factor: int = 20,
) -> DepthL1Result:
    """Mean L1 depth difference (metres) between the two meshes over `n_views` random views (or the given `poses`).

    Default camera: 160x120 with a 90 degree field of view (small, so 1000 views take seconds on a CPU). A random
    view is accepted when at least `min_valid_fraction` of its ground-truth pixels see a surface; at most
    `max_attempts_factor * n_views` views are tried. Seeded: the same meshes give the same figure on every run.
    """
    check_mesh(rec_mesh, "reconstructed mesh", warn=False)
    check_mesh(gt_mesh, "ground-truth mesh", warn=False)
    base = default_intrinsics(width, height)
    fx = base.fx if fx is None else fx
    intr = Intrinsics(
        width,
        height,
        fx=fx,
        fy=fx if fy is None else fy,
        cx=base.cx if cx is None else cx,
        cy=base.cy if cy is None else cy,
    )
    if not 0 <= margin < 0.5:
        raise ValueError(f"margin is a fraction of the bounding box per side, in [0, 0.5), got {margin}")

    if poses is not None:
        candidates = iter(np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4))
        max_attempts = len(poses)
        n_views = len(poses)
    else:
        if n_views <= 0:
            raise ValueError(f"n_views must be positive, got {n_views}")
        rng = np.random.default_rng(seed)
        bounds = np.asarray(gt_mesh.bounds, dtype=np.float64)
        max_attempts = max_attempts_factor * n_views
        candidates = (random_view(bounds, margin, rng) for _ in range(max_attempts))

    start = time.perf_counter()
    accepted, errors, examples = [], [], []
    n_gt_pixels = n_missing = n_skipped = 0
    for pose in candidates:
        gt_depth, _ = render_depth(gt_mesh, intr, pose)
        gt_valid = gt_depth > 0
        if poses is None and gt_valid.mean() < min_valid_fraction:
            n_skipped += 1
            continue
        rec_depth, _ = render_depth(rec_mesh, intr, pose)
        rec_valid = rec_depth > 0
        both = gt_valid & rec_valid
        n_gt_pixels += int(gt_valid.sum())
        n_missing += int((gt_valid & ~rec_valid).sum())
        diff = np.abs(gt_depth[both].astype(np.float64) - rec_depth[both].astype(np.float64))
        errors.append(diff.mean() if diff.size else np.nan)
        accepted.append(pose)
        if len(examples) < n_examples:
            examples.append(DepthView(pose, gt_depth, rec_depth))
        if len(accepted) == n_views:
            break
    seconds = time.perf_counter() - start

    if not accepted:
        raise MeshError(
            f"none of {max_attempts} random views sees the ground-truth mesh over {min_valid_fraction:.0%} of the "
            "image: is the mesh a closed scene (a room)? lower min_valid_fraction for open or sparse meshes"
        )
    per_view = np.array(errors)
    valid_views = np.isfinite(per_view)
    return DepthL1Result(
        mean=float(per_view[valid_views].mean()) if valid_views.any() else float("nan"),
        per_view=per_view,
        missing_fraction=n_missing / n_gt_pixels if n_gt_pixels else 0.0,
        n_views=len(accepted),
        n_skipped=n_skipped,
        intrinsics=intr,
        poses=np.stack(accepted),
        seconds=seconds,
        examples=tuple(examples),
    )
