"""Sample depths along camera rays (paper Sec. 3.2).

Depths `z` are planar (along the camera's optical axis): ray directions have unit z in the camera frame, so the point
of sample z is `origin + z * direction`, and z compares directly with the sensor depth.
"""
from __future__ import annotations

import torch


def stratified(near: torch.Tensor, far: torch.Tensor, n: int, jitter: bool = True) -> torch.Tensor:
    """n depths per ray in [near, far], one uniformly placed in each of n equal intervals. (R,) -> (R, n)."""
    steps = torch.arange(n, dtype=near.dtype, device=near.device)
    offset = torch.rand(len(near), n, dtype=near.dtype, device=near.device) if jitter else torch.full(
        (len(near), n), 0.5, dtype=near.dtype, device=near.device)
    t = (steps + offset) / n
    return near[:, None] + (far - near)[:, None] * t


def near_surface(depth: torch.Tensor, n: int, half_width: float, jitter: bool = True) -> torch.Tensor:
    """n depths per ray uniformly covering [d - half_width, d + half_width] around the measured depth d."""
    return stratified(depth - half_width, depth + half_width, n, jitter)


def importance(bins: torch.Tensor, weights: torch.Tensor, n: int) -> torch.Tensor:
    """n depths per ray drawn from the piecewise-constant distribution of `weights` over sorted sample depths.

    Used for rays without a depth measurement, where the surface must be found from the rendering weights.
    """
    w = weights.detach() + 1e-5  # keeps every interval reachable so no ray degenerates
    mids = 0.5 * (bins[:, 1:] + bins[:, :-1])
    pdf = w[:, 1:-1] / w[:, 1:-1].sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), pdf.cumsum(-1)], dim=-1)  # (R, len(mids))
    u = torch.rand(len(bins), n, dtype=bins.dtype, device=bins.device)
    hi = torch.searchsorted(cdf.contiguous(), u.contiguous(), right=True).clamp(1, cdf.shape[-1] - 1)
    lo = hi - 1
    c_lo, c_hi = cdf.gather(1, lo), cdf.gather(1, hi)
    m_lo, m_hi = mids.gather(1, lo), mids.gather(1, hi)
    t = (u - c_lo) / (c_hi - c_lo).clamp_min(1e-8)
    return (m_lo + t * (m_hi - m_lo)).detach()


def far_in_bound(origins: torch.Tensor, dirs: torch.Tensor, bound_min: torch.Tensor,
                 bound_max: torch.Tensor) -> torch.Tensor:
    """Planar depth at which each ray leaves the axis-aligned scene bound (slab method); 0 if it never enters."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    t0 = (bound_min - origins) * inv
    t1 = (bound_max - origins) * inv
    t_near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(-1)
    return torch.where(t_far > t_near, t_far, torch.zeros_like(t_far))
