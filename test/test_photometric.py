"""Photometric alignment to a keyframe (fast tracker): residuals, their gradients, occlusion, coarse-to-fine."""
import numpy as np
import pytest
import torch

from eslam_core.camera import Intrinsics
from eslam_core.tracking.photometric import Reference, grey_pyramid, photometric_residuals
from eslam_core.tracking.sdf_tracker import pyramid_level

INTR = Intrinsics(width=160, height=120, fx=150.0, fy=150.0, cx=79.5, cy=59.5)
PLANE_Z = 2.0  # the reference camera looks at a textured wall, fronto-parallel at this depth


def texture(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Grey level of the wall as the reference camera sees it at pixel (u, v): smooth, so that the sampled
    image's central differences approximate its derivative well."""
    return 0.5 + 0.2 * torch.sin(u / 6.0) + 0.2 * torch.cos(v / 8.0)


@pytest.fixture()
def reference():
    v, u = torch.meshgrid(torch.arange(INTR.height, dtype=torch.float32),
                          torch.arange(INTR.width, dtype=torch.float32), indexing="ij")
    rgb = texture(u, v)[..., None].expand(-1, -1, 3).contiguous()
    depth = torch.full((INTR.height, INTR.width), PLANE_Z)
    return Reference.build(0, rgb, depth, torch.eye(4), levels=3)


def wall_points(n: int, seed: int = 0) -> torch.Tensor:
    """World points on the wall, inside the reference view."""
    g = torch.Generator().manual_seed(seed)
    x = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 1.6
    y = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 1.2
    return torch.stack([x, y, torch.full_like(x, PLANE_Z)], -1)


def reference_grey(x: torch.Tensor) -> torch.Tensor:
    """The true grey level of world wall points (what the current camera measures there)."""
    u = INTR.fx * x[:, 0] / x[:, 2] + INTR.cx
    v = INTR.fy * x[:, 1] / x[:, 2] + INTR.cy
    return texture(u, v)


def test_residual_is_zero_where_the_current_frame_sees_what_the_keyframe_saw(reference):
    x = wall_points(500)
    r, _, valid = photometric_residuals(x, reference_grey(x), reference, 0, INTR, occlusion=0.06)
    assert valid.float().mean() > 0.9
    assert r[valid].abs().max() < 5e-3  # bilinear interpolation of a smooth texture
    # A point 2 cm off along the wall reads another grey level.
    r_off, _, _ = photometric_residuals(x + torch.tensor([0.02, 0.0, 0.0], dtype=torch.float64),
                                        reference_grey(x), reference, 0, INTR, occlusion=0.06)
    assert r_off[valid].abs().mean() > 10 * r[valid].abs().mean()


@pytest.mark.parametrize("level", [0, 1, 2])
def test_gradient_matches_finite_differences(reference, level):
    x = wall_points(400, seed=1)
    grey = reference_grey(x)
    _, grad, valid = photometric_residuals(x, grey, reference, level, INTR, occlusion=0.06)
    eps = 2e-4  # metres: a fraction of a pixel at 2 m
    numeric = torch.zeros_like(grad)
    for k in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[k] = eps
        plus, _, _ = photometric_residuals(x + step, grey, reference, level, INTR, 0.06)
        minus, _, _ = photometric_residuals(x - step, grey, reference, level, INTR, 0.06)
        numeric[:, k] = (plus - minus) / (2 * eps)
    err = (grad - numeric)[valid].norm(dim=1) / numeric[valid].norm(dim=1).clamp_min(1e-3)
    # Central differences of a sampled image against finite differences of its bilinear interpolation: they
    # agree up to the texture's curvature within a (level) pixel.
    assert err.median() < 0.05 * 2**level
    # Moving along the optical axis of a fronto-parallel wall changes the grey level much less than sideways.
    assert grad[valid][:, 2].abs().median() < grad[valid][:, :2].norm(dim=1).median()


def test_points_the_keyframe_did_not_see_are_not_valid(reference):
    x = wall_points(500, seed=2)
    occluded = reference.depth.clone()
    occluded[:, : INTR.width // 2] = 1.0  # something in front of the left half of the wall
    ref = Reference(0, reference.levels, occluded, reference.pose)
    _, _, valid = photometric_residuals(x, reference_grey(x), ref, 0, INTR, occlusion=0.06)
    left = INTR.fx * x[:, 0] / x[:, 2] + INTR.cx < INTR.width // 2 - 1
    assert not valid[left].any() and valid[~left].float().mean() > 0.9
    behind = x.clone()
    behind[:, 2] = -1.0  # behind the reference camera
    assert not photometric_residuals(behind, reference_grey(x), reference, 0, INTR, 0.06)[2].any()


@pytest.mark.parametrize("level", [0, 1, 2])
def test_c_kernel_matches_the_torch_reference(reference, level, monkeypatch):
    from eslam_core.native import load_kernel
    from eslam_core.tracking import photometric

    if load_kernel("photometric") is None:
        pytest.skip("no C compiler: the torch implementation is the only one")
    g = torch.Generator().manual_seed(level)
    turn = torch.tensor([[0.995, -0.0998, 0.0], [0.0998, 0.995, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    ref = Reference(0, reference.levels, reference.depth.clone(), torch.eye(4, dtype=torch.float64))
    ref.pose[:3, :3], ref.pose[:3, 3] = turn, torch.tensor([0.05, -0.02, 0.01], dtype=torch.float64)
    ref.depth[:40] = 1.0  # occluded in part
    # Points inside, near the border of and outside the view, some behind the camera.
    p = wall_points(600, seed=3)
    p[:, :2] *= 1.3
    p[:20, 2] = -0.5
    x = p @ turn.T + ref.pose[:3, 3]
    grey = torch.rand(len(x), generator=g, dtype=torch.float64)
    native = photometric_residuals(x, grey, ref, level, INTR, occlusion=0.06)
    monkeypatch.setattr(photometric, "load_kernel", lambda name: None)
    torch_ref = photometric_residuals(x, grey, ref, level, INTR, occlusion=0.06)
    assert 0.3 < native[2].float().mean() < 0.9  # a mix of valid and invalid points
    assert torch.equal(native[2], torch_ref[2])
    # The torch version samples in float32.
    torch.testing.assert_close(native[0], torch_ref[0], rtol=0, atol=1e-5)
    torch.testing.assert_close(native[1], torch_ref[1], rtol=1e-4, atol=1e-3)


def test_pyramid_halves_each_level_and_keeps_the_mean():
    rgb = torch.rand(120, 160, 3)
    levels = grey_pyramid(rgb, 3)
    assert [tuple(g.shape) for g in levels] == [(120, 160), (60, 80), (30, 40)]
    assert levels[2].mean() == pytest.approx(float(levels[0].mean()), abs=1e-5)
    assert len(grey_pyramid(torch.rand(12, 12, 3), 4)) == 2  # stops before a level gets too small


def test_coarse_to_fine_schedule():
    assert [pyramid_level(i, 6, 3) for i in range(6)] == [2, 2, 1, 1, 0, 0]
    assert [pyramid_level(i, 4, 1) for i in range(4)] == [0, 0, 0, 0]
    assert pyramid_level(0, 1, 3) == 0  # a single iteration works at full resolution
    assert np.all(np.diff([pyramid_level(i, 10, 3) for i in range(10)]) <= 0)
