"""SDF-based volume rendering (paper Sec. 3.2, after StyleSDF).

sigma(p) = beta * sigmoid(-beta * phi_g(p)); as in the official implementation the interval length is not used:
alpha_n = 1 - exp(-sigma_n), w_n = alpha_n * prod_{k<n} (1 - alpha_k). Depth = sum w z, colour = sum w c; the weights
are not normalised.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from eslam_core.config import RenderConfig
from eslam_core.representation.field import RadianceField
from eslam_core.rendering.sampling import far_in_bound, importance, near_surface, stratified


@dataclass
class RenderOutput:
    z: torch.Tensor  # (R, N) sample depths
    sdf: torch.Tensor  # (R, N) normalised TSDF at the samples
    weights: torch.Tensor  # (R, N)
    depth: torch.Tensor  # (R,)
    color: torch.Tensor  # (R, 3)


def alpha_from_sdf(sdf: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
    return 1.0 - torch.exp(-beta * torch.sigmoid(-beta * sdf))


def render_weights(alpha: torch.Tensor) -> torch.Tensor:
    """w_n = alpha_n * prod_{k<n} (1 - alpha_k)."""
    transmittance = torch.cumprod(
        torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha[:, :-1] + 1e-10], dim=-1), dim=-1)
    return alpha * transmittance


def sample_depths(field: RadianceField, origins: torch.Tensor, dirs: torch.Tensor, depth_gt: torch.Tensor,
                  cfg: RenderConfig, truncation: float, missing: torch.Tensor | None = None) -> torch.Tensor:
    """Sorted sample depths (R, N_strat + N_imp): stratified plus near-surface (with depth) or importance samples.

    `missing`: the indices of the rays without depth, on the rays' device, when the caller knows them from host
    data; finding them here makes the host wait for the device's queued work (each GPU tracking or mapping
    iteration would).
    """
    has_depth = depth_gt > 0
    if missing is None:
        missing = torch.nonzero(~has_depth).squeeze(1)
    if len(missing) == 0:
        far = cfg.depth_far_factor * depth_gt
    else:
        bmin, bmax = field.bound_min, field.bound_max
        far = torch.where(has_depth, cfg.depth_far_factor * depth_gt, far_in_bound(origins, dirs, bmin, bmax))
        far = far.clamp_min(1e-3)
    z = stratified(torch.zeros_like(far), far, cfg.n_stratified)
    if cfg.n_importance == 0:
        return z
    z_extra = near_surface(depth_gt, cfg.n_importance, cfg.surface_band * truncation)
    if len(missing):
        with torch.no_grad():
            o, d, zs = origins[missing], dirs[missing], z[missing]
            sdf = field.sdf((o[:, None, :] + zs[..., None] * d[:, None, :]).reshape(-1, 3)).reshape(zs.shape)
            w = render_weights(alpha_from_sdf(sdf, field.beta))
        z_extra = z_extra.clone()
        z_extra[missing] = importance(zs, w, cfg.n_importance)
    return torch.sort(torch.cat([z, z_extra], dim=-1), dim=-1).values


def render_rays(field: RadianceField, origins: torch.Tensor, dirs: torch.Tensor, depth_gt: torch.Tensor,
                cfg: RenderConfig, truncation: float, missing: torch.Tensor | None = None) -> RenderOutput:
    """Render depth and colour of rays (R,3) origins / directions with planar-unit directions (on the field's
    device). `missing`: see sample_depths."""
    z = sample_depths(field, origins.detach(), dirs.detach(), depth_gt, cfg, truncation, missing)
    return render_samples(field, origins, dirs, z)


def render_samples(field: RadianceField, origins: torch.Tensor, dirs: torch.Tensor, z: torch.Tensor) -> RenderOutput:
    """Render depth and colour of rays at given sample depths z (R, N) along them."""
    points = origins[:, None, :] + z[..., None] * dirs[:, None, :]
    flat = points.reshape(-1, 3)
    sdf = field.sdf(flat).reshape(z.shape)
    rgb = field.color(flat).reshape(z.shape + (3,))
    weights = render_weights(alpha_from_sdf(sdf, field.beta))
    depth = (weights * z).sum(-1)
    color = (weights[..., None] * rgb).sum(-2)
    return RenderOutput(z=z, sdf=sdf, weights=weights, depth=depth, color=color)
