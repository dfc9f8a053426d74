"""The tracker's snapshot of the map (decoders' first layer folded into the planes) against the field itself."""
import numpy as np
import pytest
import torch

from eslam_core.config import load_config
from eslam_core.representation.field import FoldedMap, FrozenField, SceneField
from eslam_core.native import load_kernel

BOUND = np.array([[-1.0, -0.5, -0.3], [1.4, 1.42, 0.9]])


@pytest.fixture
def field():
    torch.manual_seed(0)
    f = SceneField(BOUND, load_config("replica").model)
    with torch.no_grad():  # planes as after mapping: features of order 0.1, so the decoders are far from linear
        for table in f.plane_parameters():
            table.normal_(0.0, 0.1)
    return f


@pytest.mark.parametrize("native", [False, True])
def test_frozen_field_equals_field_with_point_gradients(field, native):
    if native and load_kernel("plane_lookup") is None:
        pytest.skip("no C compiler")
    for planes in (field.geometry_planes, field.appearance_planes):
        planes.use_native = native
    fixed = FrozenField(field)
    x = torch.from_numpy(np.random.default_rng(2).uniform(BOUND[0], BOUND[1], (5000, 3))).float()
    for which in ("sdf", "color"):
        xa, xb = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
        a, b = getattr(field, which)(xa), getattr(fixed, which)(xb)
        assert a.shape == b.shape
        assert (a - b).abs().max() <= 1e-5
        assert a.std() > 0.01  # the comparison is not between two constants
        (ga,) = torch.autograd.grad(a.sum(), xa)
        (gb,) = torch.autograd.grad(b.sum(), xb)
        assert (ga - gb).abs().max() <= 1e-5 * ga.abs().max()


def test_frozen_field_sends_no_gradient_into_the_map(field):
    x = torch.zeros(10, 3, requires_grad=True)
    fixed = FrozenField(field)
    (fixed.sdf(x).sum() + fixed.color(x).sum()).backward()
    assert x.grad is not None and all(p.grad is None for p in field.parameters())


def test_a_folded_map_is_kept_while_the_map_version_stays_and_refolded_when_it_changes(field):
    folded = FoldedMap()
    points = torch.tensor([[0.1, 0.2, 0.3], [-0.4, 0.9, 0.0]])
    first = folded.of(field, 1)
    before = first.sdf(points)
    assert folded.of(field, 1) is first  # the same map version: no second pass over the planes
    with torch.no_grad():
        field.geometry_planes.table.add_(0.05)  # mapping changed the map ...
    torch.testing.assert_close(folded.of(field, 1).sdf(points), before)  # ... unseen while its version is the same
    changed = folded.of(field, 2)
    assert changed is not first
    torch.testing.assert_close(changed.sdf(points), field.sdf(points), atol=1e-5, rtol=1e-5)
    assert not torch.allclose(changed.sdf(points), before)
    other = SceneField(BOUND, load_config("replica").model)
    assert folded.of(other, 2) is not changed  # another field (a grown map) at the same version number
    assert folded.of(other, None) is not folded.of(other, None)  # no version: folded afresh each time


@pytest.mark.parametrize("native", [False, True])
@pytest.mark.parametrize("hidden, layers", [(16, 2), (24, 3)])  # the kernel's vector and scalar layers
def test_sdf_with_gradient_equals_autograd(native, hidden, layers):
    if native and load_kernel("plane_lookup") is None:
        pytest.skip("no C compiler")
    torch.manual_seed(0)
    field = SceneField(BOUND, load_config("replica", {"model": {"decoder_hidden": hidden,
                                                                "decoder_layers": layers}}).model)
    with torch.no_grad():
        field.geometry_planes.table.normal_(0.0, 0.1)
    field.geometry_planes.use_native = native
    fixed = FrozenField(field)
    x = torch.from_numpy(np.random.default_rng(3).uniform(BOUND[0], BOUND[1], (5000, 3))).float()
    sdf, grad = fixed.sdf_with_gradient(x)
    table, bias, _ = fixed._fold("sdf")
    fused = field.geometry_planes.tsdf_with_gradient(x, table, bias, *fixed._packed("sdf"))
    assert (fused is not None) == native  # the C kernel's one pass, or torch's chain rule
    xa = x.clone().requires_grad_(True)
    expected = field.sdf(xa)
    (expected_grad,) = torch.autograd.grad(expected.sum(), xa)
    assert (sdf - expected.detach()).abs().max() <= 1e-5
    assert expected_grad.abs().max() > 0.1  # a gradient worth comparing
    assert (grad - expected_grad).abs().max() <= 1e-4 * expected_grad.abs().max()
