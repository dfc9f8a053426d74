"""Observed space: the voxels near surface a keyframe saw, which the fast tracker restricts itself to."""
import numpy as np
import torch

from eslam_core.mapping.observed import ObservedSpace, ObservedSurfaces


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


def test_a_grown_grid_keeps_every_observed_voxel_where_it_was():
    """A map grows by whole coarse cells (0.24 m here, 4 voxels), again and again: the grid must keep its voxels in
    place. Bounds then fall on voxel edges, and the float32 origin's rounding once made the grown grid a voxel short
    on one axis (the mapper crashed)."""
    rng = np.random.default_rng(0)
    cell = 0.24
    for _ in range(40):
        bound = np.stack([rng.integers(-20, 0, 3), rng.integers(1, 20, 3)]).astype(np.float64) * cell
        space = ObservedSpace(bound, voxel=0.06)
        surface = space.origin + torch.rand(200, 3) * torch.tensor(space.shape) * space.voxel * 0.999
        space.add(surface)
        seen = int(space.seen.sum())
        for _ in range(8):
            bound = bound + np.stack([-rng.integers(0, 3, 3), rng.integers(0, 3, 3)]) * cell
            before = space.shape
            space = space.grown(bound)
            needed = np.ceil((bound[1] - bound[0]) / space.voxel - 1e-6)
            assert all(s <= g == n for g, s, n in zip(space.shape, before, needed))
            assert bool(space.contains(surface).all()) and int(space.seen.sum()) == seen


def test_settled_space_waits_for_newer_keyframes():
    """With observed_after = 3 a keyframe's surface joins observed space once the next keyframe is mapped, and
    settled space once the third after it is; the tracker aligns to settled space unless it holds too little."""
    def point(k):  # on keyframe k's surface: voxel (2k + 1, 0, 0), two voxels from the next one's
        return torch.tensor([[0.15 + 0.2 * k, 0.05, 0.05]])

    observed = ObservedSurfaces(np.array([[0.0, 0.0, 0.0], [1.2, 1.0, 1.0]]), 0.1, after=3)
    for k in range(6):
        observed.add_keyframe(point(k))
    joined, settled = [], []
    for mapped in range(1, 7):
        observed.mapped(mapped)
        joined.append(observed.joined)
        settled.append(observed.settled_count)
    assert joined == [1, 1, 2, 3, 4, 5]  # the first after its warm-up; keyframe 1 once keyframe 2 is mapped
    assert settled == [1, 1, 1, 1, 2, 3]  # keyframe 1 once keyframe 4 is mapped
    assert bool(observed.settled.seen[5, 0, 0]) and not bool(observed.settled.seen[7, 0, 0])
    assert bool(observed.space.seen[9, 0, 0]) and not bool(observed.space.seen[11, 0, 0])
    used, seen = observed.alignable(torch.cat([point(0), point(1), point(3), point(5)]))
    assert seen.tolist() == [True, True, True, False] and used.tolist() == [True, True, False, False]
    used, seen = observed.alignable(torch.cat([point(3), point(4), point(4), point(0)]))  # settled: 1 of 4
    assert used.tolist() == seen.tolist() == [True, True, True, True]
    observed.settle_all()
    assert observed.settled_count == observed.joined == 6 and not observed.pending
