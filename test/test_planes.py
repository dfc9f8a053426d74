"""Feature-plane interpolation against a brute-force reference, and the C kernel against the torch version."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from eslam_core.native import load_kernel
from eslam_core.representation.planes import PLANE_AXES, FeaturePlanes, reference_lookup

BOUND = np.array([[-1.0, -0.5, -0.3], [1.4, 1.42, 0.9]])


def brute_force(fp: FeaturePlanes, points: torch.Tensor) -> torch.Tensor:
    """grid_sample (align_corners, border) on every plane, summed per scale, concatenated over scales."""
    unit = (points - fp.bound_min) / fp.bound_extent * 2 - 1
    out = []
    for s in range(len(fp.resolutions)):
        acc = 0
        for k, (a, b) in enumerate(PLANE_AXES):
            grid = unit[:, [a, b]].reshape(1, 1, -1, 2)  # grid_sample's (x, y) = (column axis, row axis)
            acc = acc + F.grid_sample(fp.plane(s, k)[None], grid, align_corners=True, padding_mode="border")[0, :, 0].T
        out.append(acc)
    return torch.cat(out, dim=-1)


@pytest.fixture
def planes():
    torch.manual_seed(0)
    return FeaturePlanes(BOUND, (0.24, 0.06), channels=8, init_std=1.0)


def random_points(n, outside=0.2):
    lo, hi = BOUND[0] - outside, BOUND[1] + outside
    return torch.from_numpy(np.random.default_rng(1).uniform(lo, hi, (n, 3))).float()


def test_layout_spacing_matches_resolution(planes):
    n = planes.layout.sizes[1]
    spacing = (BOUND[1] - BOUND[0]) / (np.array(n) - 1)
    assert np.allclose(spacing, 0.06, atol=0.002)


@pytest.mark.parametrize("native", [False, True])
def test_lookup_matches_grid_sample(planes, native):
    if native and load_kernel("plane_lookup") is None:
        pytest.skip("no C compiler")
    planes.use_native = native
    pts = random_points(3000)
    assert torch.allclose(planes(pts), brute_force(planes, pts), atol=1e-5)


@pytest.mark.parametrize("channels", [8, 16, 32])  # the scalar loops; the vector ones (a folded table, the planes)
def test_native_kernel_matches_reference_with_gradients(channels):
    if load_kernel("plane_lookup") is None:
        pytest.skip("no C compiler")
    torch.manual_seed(0)
    planes = FeaturePlanes(BOUND, (0.24, 0.06), channels=channels, init_std=1.0)
    pts = random_points(4000, outside=0.0).requires_grad_(True)
    g = torch.randn(4000, 2 * planes.channels)
    grads = []
    for native in (True, False):
        planes.use_native = native
        pts.grad, planes.table.grad = None, None
        out = planes(pts) if native else reference_lookup(pts, planes.table, planes.bound_min,
                                                          planes.bound_extent, planes.layout)
        (out * g).sum().backward()
        grads.append((out.detach(), pts.grad.clone(), planes.table.grad.clone()))
    for a, b in zip(*grads):  # to 1e-5 of each quantity's scale (point gradients reach ~500 here)
        assert (a - b).abs().max() <= 1e-5 * b.abs().max()


def test_point_gradient_is_finite_difference(planes):
    planes.use_native = True
    p = torch.tensor([[0.123, 0.456, 0.2101]], requires_grad=True)
    w = torch.randn(1, 2 * planes.channels)
    (planes(p) * w).sum().backward()
    eps = 1e-3
    for ax in range(3):
        d = torch.zeros(1, 3)
        d[0, ax] = eps
        num = ((planes(p + d) - planes(p - d)) * w).sum() / (2 * eps)
        assert abs(num.item() - p.grad[0, ax].item()) < 1e-2 * max(1.0, abs(num.item()))


def test_points_outside_read_the_border(planes):
    inside = torch.tensor([[1.4, 1.42, 0.9]])
    outside = torch.tensor([[3.0, 2.0, 5.0]])
    assert torch.allclose(planes(inside), planes(outside), atol=1e-6)
