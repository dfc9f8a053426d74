"""SDF-based volume rendering of known surfaces gives their depth; the losses see the right regions."""
import numpy as np
import pytest
import torch

from eslam_core.config import RenderConfig
from eslam_core.rendering.losses import sdf_losses
from eslam_core.rendering.volume import alpha_from_sdf, render_rays, render_weights

T = 0.06


class AnalyticField:
    """A field whose TSDF is a known signed distance, truncated and normalised as ESLAM's decoder output is."""

    def __init__(self, distance, beta=10.0, bound=((-3, -3, -1), (3, 3, 5))):
        self.distance = distance
        self.beta = torch.tensor(beta)
        self.bound_min = torch.tensor(bound[0], dtype=torch.float32)
        self.bound_max = torch.tensor(bound[1], dtype=torch.float32)

    def sdf(self, p):
        return (self.distance(p) / T).clamp(-1, 1)

    def color(self, p):
        return torch.stack([torch.full_like(p[:, 0], 0.25), (p[:, 0] > 0).float(), torch.full_like(p[:, 0], 0.75)], -1)


def plane_distance(p):
    return 2.0 - p[:, 2]  # wall at z = 2 facing the camera at the origin


def sphere_distance(p, c=torch.tensor([0.1, -0.1, 2.0]), r=0.5):
    return (p - c).norm(dim=-1) - r


def camera_rays(n=400, fov=0.3):
    g = torch.linspace(-fov, fov, int(np.sqrt(n)))
    x, y = torch.meshgrid(g, g, indexing="ij")
    dirs = torch.stack([x.reshape(-1), y.reshape(-1), torch.ones(x.numel())], -1)  # unit z: planar depth
    return torch.zeros_like(dirs), dirs


def sphere_depth(dirs, c=np.array([0.1, -0.1, 2.0]), r=0.5):
    d = dirs.numpy() / np.linalg.norm(dirs.numpy(), axis=1, keepdims=True)
    b = d @ c
    disc = b**2 - (c @ c - r * r)
    t = b - np.sqrt(np.where(disc > 0, disc, np.nan))
    return torch.from_numpy(t * d[:, 2]).float()  # planar depth; nan where the ray misses


def test_plane_depth_sharp_surface():
    o, d = camera_rays()
    gt = torch.full((len(d),), 2.0)
    out = render_rays(AnalyticField(plane_distance, 40.0), o, d, gt, RenderConfig(n_importance=32), T)
    assert (out.depth - 2.0).abs().max() < 0.008
    assert torch.allclose(out.weights.sum(-1), torch.ones(len(d)), atol=1e-3)  # opaque surface


def test_plane_depth_paper_settings_bias():
    """With beta = 10 and no interval length, opacity builds up in front of the surface: the rendered depth is a
    little short (the learned SDF and beta absorb this in practice). It stays within half a truncation."""
    o, d = camera_rays()
    gt = torch.full((len(d),), 2.0)
    out = render_rays(AnalyticField(plane_distance, 10.0), o, d, gt, RenderConfig(), T)
    err = out.depth - 2.0
    assert err.max() < 0.002 and err.min() > -T / 2 and err.mean() < -0.005


def test_sphere_depth_and_colour():
    o, d = camera_rays(900, fov=0.35)
    gt = sphere_depth(d)
    hit = ~torch.isnan(gt)
    assert hit.sum() > 100 and (~hit).sum() > 100
    out = render_rays(AnalyticField(sphere_distance, 40.0), o[hit], d[hit], gt[hit], RenderConfig(n_importance=32), T)
    err = (out.depth - gt[hit]).abs()
    assert err.median() < 0.01
    assert err.quantile(0.9) < 0.03  # grazing rays at the silhouette cross the truncation band obliquely
    expected = torch.stack([torch.full_like(gt[hit], 0.25), (d[hit][:, 0] * gt[hit] > 0).float(),
                            torch.full_like(gt[hit], 0.75)], -1)
    assert (out.color - expected).abs().median() < 0.01


def test_rays_without_depth_find_the_surface_by_importance_sampling():
    o, d = camera_rays()
    out = render_rays(AnalyticField(plane_distance, 40.0), o, d, torch.zeros(len(d)),
                      RenderConfig(n_stratified=48, n_importance=16), T)
    assert (out.depth - 2.0).abs().median() < 0.02


def test_weights_formula():
    sdf = torch.tensor([[1.0, 0.5, 0.0, -0.5]])
    alpha = alpha_from_sdf(sdf, torch.tensor(10.0))
    w = render_weights(alpha)
    expected = [alpha[0, 0], alpha[0, 1] * (1 - alpha[0, 0]), alpha[0, 2] * (1 - alpha[0, 0]) * (1 - alpha[0, 1])]
    assert torch.allclose(w[0, :3], torch.stack(expected), atol=1e-6)
    assert torch.allclose(alpha[0, 2], 1 - torch.exp(torch.tensor(-5.0)))  # beta * sigmoid(0) = beta / 2


def test_sdf_losses_regions():
    z = torch.tensor([[1.0, 1.98, 2.0, 2.05, 2.5]])
    depth = torch.tensor([2.0])
    perfect = ((depth[:, None] - z) / T).clamp(-1, 1)
    fs, center, tail = sdf_losses(z, perfect, depth, T)
    assert fs == 0 and center < 1e-12 and tail < 1e-12
    fs, center, tail = sdf_losses(z, torch.zeros_like(z), depth, T)
    assert fs == pytest.approx(1.0)  # z=1.0 is free space: (0 - 1)^2
    assert center == pytest.approx((0.02**2 + 0.0) / 2, rel=1e-4)  # z=1.98 and 2.0 lie within 0.4 T
    assert tail == pytest.approx(0.05**2, rel=1e-4)  # z=2.05: only the tail; z=2.5 is behind d + T and ignored
