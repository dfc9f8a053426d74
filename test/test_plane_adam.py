"""Mapping's row-sparse Adam on the feature planes: the same optimisation as torch's dense Adam, step by step."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from eslam_core.mapping.plane_adam import RowSparseAdam
from eslam_core.native import load_kernel
from eslam_core.representation.planes import FeaturePlanes

needs_kernel = pytest.mark.skipif(load_kernel("plane_lookup") is None, reason="no C compiler for the plane kernel")


def _planes() -> FeaturePlanes:
    torch.manual_seed(0)
    return FeaturePlanes(np.array([[-1.0, -0.5, 0.0], [1.0, 0.5, 2.0]]), (0.5, 0.1), 8, 0.1)


def _loss(planes: FeaturePlanes, points: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return ((planes(points) - target) ** 2).sum()


@needs_kernel
def test_row_sparse_adam_moves_every_row_as_dense_adam_does():
    """Each iteration looks up a different region, so rows reached early and never again must keep moving with their
    momentum, and rows never reached must not move at all; a second step starts from fresh moments."""
    sparse, dense = _planes(), _planes()
    start = dense.table.detach().clone()
    adam = RowSparseAdam()
    g = torch.Generator().manual_seed(1)
    regions = [torch.tensor([[-1.0, -0.5, 0.0], [0.0, 0.5, 1.0]]), torch.tensor([[0.0, -0.5, 1.0], [1.0, 0.5, 2.0]])]
    for step in range(2):
        optim = torch.optim.Adam([dense.table], lr=0.01, betas=(0.9, 0.999), fused=True)
        with adam.fresh([sparse], lr=0.01):
            for it in range(5):
                lo, hi = regions[it % 2 if step == 0 else 0]
                points = lo + (hi - lo) * torch.rand(200, 3, generator=g)
                target = torch.randn(200, 16, generator=g)
                optim.zero_grad(set_to_none=True)
                _loss(dense, points, target).backward()
                optim.step()
                _loss(sparse, points, target).backward()
                assert sparse.table.grad is None  # the gradient went to the optimizer's rows instead
                adam.step()
                torch.testing.assert_close(sparse.table.detach(), dense.table.detach(), rtol=1e-5, atol=1e-6)
        assert sparse.row_gradients is None
    moved = (dense.table.detach() != start).any(dim=1)
    assert 0 < int(moved.sum()) < len(start)  # some rows never reached: both left them exactly as they were


@needs_kernel
def test_row_sparse_adam_follows_a_grown_table():
    planes = _planes()
    adam = RowSparseAdam()
    with adam.fresh([planes], lr=0.01):
        _loss(planes, torch.zeros(10, 3), torch.ones(10, 16)).backward()
        adam.step()
    grown = planes.grown(np.array([[-2.0, -0.5, 0.0], [1.0, 0.5, 3.0]]))
    dense = copy.deepcopy(grown)
    optim = torch.optim.Adam([dense.table], lr=0.01, fused=True)
    with adam.fresh([grown], lr=0.01):
        _loss(grown, torch.full((10, 3), 0.25), torch.ones(10, 16)).backward()
        adam.step()
    _loss(dense, torch.full((10, 3), 0.25), torch.ones(10, 16)).backward()
    optim.step()
    torch.testing.assert_close(grown.table.detach(), dense.table.detach(), rtol=1e-5, atol=1e-6)


@needs_kernel
def test_a_snapshot_taken_in_the_middle_of_a_step_leaves_the_optimizer_out():
    import io

    planes = _planes()
    with RowSparseAdam().fresh([planes], lr=0.01):
        _loss(planes, torch.zeros(10, 3), torch.ones(10, 16)).backward()
        buffer = io.BytesIO()
        torch.save(planes, buffer)  # as snapshot_for_meshing saves the field between two iterations
        assert planes.row_gradients is not None
    copy_ = torch.load(io.BytesIO(buffer.getvalue()), weights_only=False)
    assert copy_.row_gradients is None
    torch.testing.assert_close(copy_.table.detach(), planes.table.detach())
