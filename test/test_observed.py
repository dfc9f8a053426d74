"""Observed space: the voxels near surface a keyframe saw, which the fast tracker restricts itself to."""
import numpy as np
import torch

from eslam_core.mapping.observed import ObservedSpace


def test_points_near_observed_surface_are_inside_and_far_ones_are_not():
    space = ObservedSpace(np.array([[-1.0, -1.0, 0.0], [1.0, 1.0, 2.0]]), voxel=0.06)
    # A wall at z = 1.5 seen over x, y in [-0.3, 0.3].
    g = torch.linspace(-0.3, 0.3, 40)
    wall = torch.stack(torch.meshgrid(g, g, indexing="ij") + (torch.full((40, 40), 1.5),), -1).reshape(-1, 3)
    space.add(wall)
    queries = torch.tensor([
        [0.0, 0.0, 1.5],    # on the wall
        [0.1, -0.2, 1.56],  # 6 cm in front of it: within the one-voxel margin
        [0.0, 0.0, 1.3],    # 20 cm in front: never observed
        [0.8, 0.8, 1.5],    # beside the seen part of the wall
        [5.0, 0.0, 1.5],    # outside the bound
    ])
    assert space.contains(queries).tolist() == [True, True, False, False, False]


def test_adding_more_surface_grows_observed_space():
    space = ObservedSpace(np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), voxel=0.1)
    probe = torch.tensor([[0.85, 0.85, 0.85]])
    assert not space.contains(probe).item()
    space.add(torch.tensor([[0.8, 0.8, 0.8]]))
    assert space.contains(probe).item()
    space.add(torch.tensor([[2.0, 2.0, 2.0], [-1.0, 0.5, 0.5]]))  # outside the bound: ignored, no error
    assert int(space.seen.sum()) == 1


def test_growing_by_one_voxel_equals_a_3x3x3_max_pool():
    import torch.nn.functional as F

    from eslam_core.mapping.observed import grow_by_one_voxel

    g = torch.Generator().manual_seed(0)
    grid = torch.rand(17, 9, 12, generator=g) > 0.97
    grid[0, 0, 0] = grid[-1, -1, -1] = True  # corners: the growth must stop at the edges
    expected = F.max_pool3d(grid[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    assert torch.equal(grow_by_one_voxel(grid), expected)
    assert grid.sum() < expected.sum() < grid.numel()
