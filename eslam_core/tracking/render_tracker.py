"""Camera tracking (paper Sec. 3.4): optimise the pose of a frame against the fixed map.

Translation and quaternion are optimised with Adam on ESLAM's loss (`render_tracker.weights`), starting from a constant-
velocity prediction. Each iteration renders rays from random pixels with depth inside the image border, drops rays
whose depth error exceeds `outlier_factor` times the batch median, and the pose with the lowest loss over all
iterations is kept, not the last one.

The tracker works on the device of the map it is given: the frame and the prediction come from the host and move
there once per frame, the best pose and loss are kept there (no host round trip per iteration) and come back once.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from eslam_core.config import Config, RenderConfig, RenderTrackerConfig, TrackingConfig
from eslam_core.cpu import denormals_flushed, flat_nonzero
from eslam_core.representation.field import FoldedMap, FrozenField, SceneField
from eslam_core.frames import PreparedFrame, border_mask
from eslam_core.geometry import depth_points_world, params_to_pose, pose_to_params, rays_to_world, scale_motion, \
    so3_exp
from eslam_core.mapping.extent import draw_in_extent
from eslam_core.mapping.keyframes import Keyframe
from eslam_core.rendering.losses import eslam_losses
from eslam_core.mapping.observed import ObservedSurfaces
from eslam_core.rendering.volume import render_rays, render_samples, sample_depths
from eslam_core.tracking.information import PoseCovariance, pose_covariance
from eslam_core.tracking.result import TrackingResult

COVARIANCE_RAYS = 500  # the normal equations are per residual (information.py): a sample of the rays is enough
STEP_M = 1e-3  # the finite differences' camera move (a turn: this move of a point at the median depth)


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
        `free_prior` are not used (Adam steps along every direction; the normal equations are made once, at the
        end, for the covariance); `map_version` changes whenever the field's values do (None: unknown). Inputs and
        the result are host tensors; the work runs on the field's device."""
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
        covariance = self._covariance(fixed, candidates, depth, rgb, best_pose, rc.outlier_factor)
        return TrackingResult(best_pose.cpu(), float(best_loss), len(candidates), depth_fraction, float(best_inliers),
                              mapped_fraction=inside, covariance=covariance)

    @torch.no_grad()
    def _covariance(self, fixed: FrozenField, candidates: torch.Tensor, depth: torch.Tensor, rgb: torch.Tensor,
                    pose: torch.Tensor, outlier_factor: float) -> PoseCovariance | None:
        """The covariance of `pose` from the normal equations of the rendered depth and colour residuals (outliers
        dropped as in tracking) for a left perturbation (v, w) of the pose (information.py), with the Jacobian by
        forward differences."""
        pix = candidates[torch.linspace(0, len(candidates) - 1, min(COVARIANCE_RAYS, len(candidates)),
                                        device=candidates.device).long()]
        d_gt, c_gt = depth[pix], rgb[pix]
        median_depth = float(d_gt.median())
        origins, dirs = rays_to_world(self.dirs_cam[pix], pose)
        with torch.random.fork_rng(devices=[] if pose.device.type == "cpu" else [pose.device]):
            # (the samples' jitter must not move tracking's own random draws: the paper's tracker is unchanged)
            z = sample_depths(fixed, origins, dirs, d_gt, self.render, self.truncation, pix[:0])

        def residuals(c2w: torch.Tensor) -> torch.Tensor:  # (rays, 4): depth (m) and colour
            out = render_samples(fixed, *rays_to_world(self.dirs_cam[pix], c2w), z)
            return torch.cat([(out.depth - d_gt)[:, None], out.color - c_gt], 1)

        r0 = residuals(pose)
        keep = outlier_mask(r0[:, 0].abs(), outlier_factor) & torch.isfinite(r0).all(1)
        R, t = pose[:3, :3], pose[:3, 3]
        J = []
        for k in range(6):
            h = STEP_M if k < 3 else STEP_M / max(median_depth, 1e-3)
            delta = torch.zeros(6, dtype=pose.dtype, device=pose.device)
            delta[k] = h
            dR = so3_exp(delta[3:])
            moved = pose.clone()
            moved[:3, :3], moved[:3, 3] = dR @ R, dR @ t + delta[:3]
            J.append((residuals(moved) - r0) / h)
        J, r = torch.stack(J, -1)[keep].double().cpu(), r0[keep].double().cpu()  # (rays, 4, 6), (rays, 4)
        if len(r) < 7 or not torch.isfinite(J).all():
            return None
        # Depth and colour differ in units and noise: each kind is weighted by its own mean square (whitened), so
        # the weighted residuals' mean square is 1.
        H = np.zeros((6, 6))
        for kind in (slice(0, 1), slice(1, 4)):
            Jk = J[:, kind].reshape(-1, 6)
            H += (Jk.T @ Jk).numpy() / max(float(r[:, kind].square().mean()), 1e-12)
        covariance = pose_covariance(H, r.numel() - 6.0, r.numel(), t.double().cpu().numpy(), median_depth)
        # Not a reason to degrade a frame (quality.py): per whitened residual the information is low wherever the
        # map is still rough (after 20 warm-up iterations on the room no direction passed the threshold, and no
        # keyframe was made), and on the degenerate stretch that slid the SDF tracker this tracker held (1.3 cm).
        return dataclasses.replace(covariance, free=False, weakest=float("inf"))

    def _in_observed_space(self, candidates: torch.Tensor, depth: torch.Tensor, pose: torch.Tensor,
                           observed: ObservedSurfaces) -> torch.Tensor:
        """The candidate pixels whose depth point lies in observed space, or all of them if that is under half:
        then the frame mostly sees new space, and rays through it still constrain the pose better than few rays."""
        seen = observed.contains(depth_points_world(self.dirs_cam[candidates], depth[candidates], pose))
        return candidates[seen] if 2 * int(seen.sum()) >= len(candidates) else candidates
