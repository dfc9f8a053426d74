"""Camera tracking (paper Sec. 3.4): optimise the pose of a frame against the fixed map.

Translation and quaternion are optimised with Adam on ESLAM's loss (`render_tracker.weights`), starting from a constant-
velocity prediction. Each iteration renders rays from random pixels with depth inside the image border, drops rays
whose depth error exceeds `outlier_factor` times the batch median, and the pose with the lowest loss over all
iterations is kept, not the last one.

The tracker works on the device of the map it is given: the frame and the prediction come from the host and move
there once per frame, the best pose and loss are kept there (no host round trip per iteration) and come back once.
"""
from __future__ import annotations

import numpy as np
import torch

from eslam_core.config import Config, RenderConfig, RenderTrackerConfig, TrackingConfig
from eslam_core.cpu import denormals_flushed, flat_nonzero
from eslam_core.representation.field import FoldedMap, SceneField
from eslam_core.frames import PreparedFrame, border_mask
from eslam_core.geometry import depth_points_world, params_to_pose, pose_to_params, rays_to_world, scale_motion
from eslam_core.mapping.extent import draw_in_extent
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.rendering.losses import eslam_losses
from eslam_core.mapping.observed import ObservedSurfaces
from eslam_core.rendering.volume import render_rays
from eslam_core.tracking.result import TrackingResult


def constant_velocity(prev2: np.ndarray | None, prev: np.ndarray, time_ratio: float = 1.0) -> np.ndarray:
    """Predict the next pose by repeating the last relative motion, scaled by the ratio of the time gaps (frames
    skipped by a live input make the gap to the next frame longer than the last one)."""
    if prev2 is None:
        return prev.copy()
    motion = np.linalg.inv(prev2) @ prev
    if time_ratio != 1.0:
        motion = scale_motion(motion, time_ratio)
    return prev @ motion


def time_ratio(t_prev2: float, t_prev: float, t_next: float, limit: float = 4.0) -> float:
    """(t_next - t_prev) / (t_prev - t_prev2), 1 when the stamps say nothing useful, capped at `limit`."""
    last = t_prev - t_prev2
    if not last > 0 or not t_next > t_prev:
        return 1.0
    return float(min((t_next - t_prev) / last, limit))


def outlier_mask(depth_error: torch.Tensor, factor: float) -> torch.Tensor:
    return depth_error < factor * depth_error.median()


class Tracker:
    def __init__(self, tracking: TrackingConfig, settings: RenderTrackerConfig, render: RenderConfig, truncation: float,
                 dirs_cam: torch.Tensor, height: int, width: int):
        self.tracking, self.settings, self.render, self.truncation = tracking, settings, render, truncation
        self.dirs_cam = dirs_cam  # (H*W, 3)
        self.border = border_mask(height, width, tracking.border).reshape(-1)
        self._folded = FoldedMap()

    @staticmethod
    def of(cfg: Config, dirs_cam: torch.Tensor, height: int, width: int) -> "Tracker":
        """The tracker of `cfg`'s sections."""
        return Tracker(cfg.tracking, cfg.render_tracker, cfg.render, cfg.model.truncation, dirs_cam, height, width)

    def _on(self, device: torch.device) -> None:
        """Keep the per-camera tables on the map's device (moved once)."""
        if self.dirs_cam.device != device:
            self.dirs_cam, self.border = self.dirs_cam.to(device), self.border.to(device)

    @denormals_flushed()  # see cpu.py
    def track(self, field: SceneField, frame: PreparedFrame, init_pose: torch.Tensor,
              extent: np.ndarray | None = None, observed: ObservedSurfaces | None = None,
              keyframe: Keyframe | None = None, map_version: int | None = None,
              free_prior: torch.Tensor | None = None) -> TrackingResult:
        """Rays are drawn from pixels whose depth point lies in `extent` (the map's) at the starting pose, from a
        pool of 8 x `tracking.rays` of them; `observed` restricts the rays with `render_tracker.observed_only`
        (otherwise, as in the paper and the official code, any pixel with depth may be drawn); `keyframe` and
        `free_prior` are not used (Adam has no normal equations to tell the directions the frame constrains); `map_version` changes whenever the field's values do (None: unknown). Inputs and the result are host
        tensors; the work runs on the field's device."""
        tc, rc = self.tracking, self.settings
        device = field.device
        self._on(device)
        rgb, depth = frame.rgb.to(device).reshape(-1, 3), frame.depth.to(device).reshape(-1)
        start = init_pose.to(device)
        candidates = flat_nonzero(self.border & (depth > 0))
        with_depth = len(candidates)
        candidates, inside = draw_in_extent(candidates, 8 * tc.rays, lambda pix: depth_points_world(
            self.dirs_cam[pix], depth[pix], start), extent)
        if rc.observed_only and observed is not None:
            candidates = self._in_observed_space(candidates, depth, start, observed)
        depth_fraction = with_depth * inside / max(int(self.border.sum()), 1)
        if len(candidates) < 10 or tc.iterations == 0:
            return TrackingResult(init_pose.clone(), float("nan"), len(candidates), depth_fraction,
                                  mapped_fraction=inside)
        t, q = pose_to_params(start)
        t.requires_grad_(True)
        q.requires_grad_(True)
        optim = torch.optim.Adam([{"params": [t], "lr": rc.lr_translation}, {"params": [q], "lr": rc.lr_rotation}],
                                 betas=(0.5, 0.999))
        # The best iteration's pose, loss and inlier fraction, kept on the device (no host round trip per iteration).
        best_pose = start.clone()
        best_loss = torch.full((), float("inf"), device=device)
        best_inliers = torch.full((), float("nan"), device=device)
        fixed = self._folded.of(field, map_version)  # the map does not change while tracking
        no_rays = torch.zeros(0, dtype=torch.long, device=device)  # without depth: every candidate pixel has depth
        for _ in range(tc.iterations):
            pix = candidates[torch.randint(len(candidates), (tc.rays,), device=device)]
            c2w = params_to_pose(t, q)
            origins, dirs = rays_to_world(self.dirs_cam[pix], c2w)
            d_gt = depth[pix]
            out = render_rays(fixed, origins, dirs, d_gt, self.render, self.truncation, no_rays)
            error = (out.depth.detach() - d_gt).abs()
            keep = outlier_mask(error, rc.outlier_factor)
            loss = eslam_losses(out, d_gt, rgb[pix], self.truncation, keep).total(rc.weights)
            better = loss.detach() < best_loss  # (a NaN loss is never better)
            best_loss = torch.where(better, loss.detach(), best_loss)
            best_pose = torch.where(better, c2w.detach(), best_pose)
            best_inliers = torch.where(better, (error < self.truncation).float().mean(), best_inliers)
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
        return TrackingResult(best_pose.cpu(), float(best_loss), len(candidates), depth_fraction, float(best_inliers),
                              mapped_fraction=inside)

    def _in_observed_space(self, candidates: torch.Tensor, depth: torch.Tensor, pose: torch.Tensor,
                           observed: ObservedSurfaces) -> torch.Tensor:
        """The candidate pixels whose depth point lies in observed space, or all of them if that is under half:
        then the frame mostly sees new space, and rays through it still constrain the pose better than few rays."""
        seen = observed.contains(depth_points_world(self.dirs_cam[candidates], depth[candidates], pose))
        return candidates[seen] if 2 * int(seen.sum()) >= len(candidates) else candidates
