"""ESLAM's objective (paper Sec. 3.3): free-space, truncation-centre, truncation-tail, depth and colour losses.

Following the official implementation, each per-point loss is a mean over the points in its own region (not a
per-ray mean), and nothing is imposed behind d + T.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from eslam_core.config import LossWeights
from eslam_core.rendering.volume import RenderOutput


@dataclass
class LossTerms:
    free_space: torch.Tensor
    truncation_center: torch.Tensor
    truncation_tail: torch.Tensor
    depth: torch.Tensor
    color: torch.Tensor

    def total(self, w: LossWeights) -> torch.Tensor:
        return (w.free_space * self.free_space + w.truncation_center * self.truncation_center
                + w.truncation_tail * self.truncation_tail + w.depth * self.depth + w.color * self.color)

    def as_floats(self) -> dict:
        return {k: float(v) for k, v in self.__dict__.items()}


def masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over the masked entries; 0 (with gradient structure kept) when the mask is empty."""
    return (values * mask).sum() / mask.sum().clamp_min(1)


def sdf_losses(z: torch.Tensor, sdf: torch.Tensor, depth_gt: torch.Tensor, truncation: float
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Free-space, truncation-centre and truncation-tail losses for rays with depth. z, sdf: (R, N); depth: (R,)."""
    d = depth_gt[:, None]
    valid = d > 0
    free = valid & (z < d - truncation)
    dist = (z - d).abs()
    center = valid & (dist < 0.4 * truncation)
    tail = valid & (dist < truncation) & ~center
    # z + phi * T - d: the sensor's depth turned into a signed-distance target along the ray.
    sdf_residual_sq = (z + sdf * truncation - d) ** 2
    return (masked_mean((sdf - 1.0) ** 2, free), masked_mean(sdf_residual_sq, center),
            masked_mean(sdf_residual_sq, tail))


def eslam_losses(out: RenderOutput, depth_gt: torch.Tensor, rgb_gt: torch.Tensor, truncation: float,
                 ray_mask: torch.Tensor | None = None) -> LossTerms:
    """All five terms. Colour on all (masked-in) rays; the others only where depth > 0."""
    if ray_mask is None:
        ray_mask = torch.ones_like(depth_gt, dtype=torch.bool)
    d_gt = torch.where(ray_mask, depth_gt, torch.zeros_like(depth_gt))
    fs, center, tail = sdf_losses(out.z, out.sdf, d_gt, truncation)
    has_depth = d_gt > 0
    depth = masked_mean((out.depth - d_gt) ** 2, has_depth)
    color = masked_mean(((out.color - rgb_gt) ** 2).mean(-1), ray_mask)
    return LossTerms(fs, center, tail, depth, color)
