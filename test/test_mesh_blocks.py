"""The map meshed in world blocks (outputs/mesh_blocks.py) and in a low-priority process (runtime/mesher.py):
blocks tile the surface without seams, only changed blocks are reported, a time budget spreads the work, block
addresses survive map growth.

The map is an analytic scene (floor, a ball, a small removable ball) with exact SDF and colours, seen by two
cameras whose depth images are sphere-traced from the same distance function, so every expectation is exact."""
from __future__ import annotations

import time

import numpy as np
import pytest
import torch
import trimesh

from eslam_core.camera import Intrinsics
from eslam_core.outputs.mesh import MeshSettings, extract_mesh
from eslam_core.outputs.mesh_blocks import (BlockLayout, IncrementalMesher, MeshSource, surface_changed, thinning_stride,
                                            triangle_soup, BlockMesh)
from eslam_core.runtime.mesher import BackgroundMesher, MeshSnapshot

T = 0.1  # truncation (m)
FLOOR = 0.013  # height of the floor: off the grid planes
RES = 0.04
BOUND = np.array([[-1.2, -1.2, -0.2], [1.2, 1.2, 1.1]])
BALL = (0.0, 0.0, 0.45, 0.35)
SMALL = (0.62, -0.3, 0.7, 0.11)  # alone in block (1, -1, 1): x in [0.48, 0.96), y in [-0.48, 0), z in [0.48, 0.96)
BLOCK = 0.48  # 12 voxels
INTR = Intrinsics(96, 72, 70.0, 70.0, 47.5, 35.5)


class AnalyticField(torch.nn.Module):
    """A floor (z = FLOOR) and balls: normalised TSDF and a colour that is a function of position."""

    def __init__(self, balls) -> None:
        super().__init__()
        self.register_buffer("balls", torch.tensor(balls, dtype=torch.float64).reshape(-1, 4))

    def distance(self, p: torch.Tensor) -> torch.Tensor:
        p = p.double()
        d = p[:, 2] - FLOOR
        for cx, cy, cz, r in self.balls.tolist():
            d = torch.minimum(d, (p - torch.tensor([cx, cy, cz], dtype=torch.float64)).norm(dim=1) - r)
        return d

    def sdf(self, p: torch.Tensor) -> torch.Tensor:
        return (self.distance(p) / T).clamp(-1, 1).float()

    def color(self, p: torch.Tensor) -> torch.Tensor:
        lo, hi = torch.from_numpy(BOUND[0]), torch.from_numpy(BOUND[1])
        return ((p.double() - lo) / (hi - lo)).clamp(0, 1).float()


def look_at(eye, target) -> np.ndarray:
    """Camera-to-world pose, OpenCV axes (x right, y down, z forward), world z up."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    pose[:3, 3] = eye
    return pose


def traced_depth(field: AnalyticField, pose: np.ndarray) -> np.ndarray:
    """Planar depth image by sphere tracing the exact distance (0 where a ray leaves the bound)."""
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    dirs = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u, float)], -1).reshape(-1, 3)
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    world = unit @ pose[:3, :3].T
    t = np.zeros(len(world))
    for _ in range(200):
        d = field.distance(torch.from_numpy(pose[:3, 3] + t[:, None] * world)).numpy()
        t += d
    hit = np.abs(field.distance(torch.from_numpy(pose[:3, 3] + t[:, None] * world)).numpy()) < 1e-5
    depth = np.where(hit & (t < 6.0), t * unit[:, 2], 0.0)
    return depth.reshape(INTR.height, INTR.width).astype(np.float32)


CAMERAS = [look_at(np.array([0.2, -1.9, 1.3]), [0.2, 0.0, 0.3]), look_at(np.array([-0.3, 1.8, 1.2]), [0.1, 0.0, 0.3])]


def scene_view(balls=(BALL, SMALL), bound=BOUND, depth_balls=None) -> MeshSource:
    """The map of `balls`; the keyframes' depth images of `depth_balls` (default: the same balls)."""
    field = AnalyticField(list(balls))
    seen = AnalyticField(list(depth_balls if depth_balls is not None else balls))
    return MeshSource(field.sdf, field.color, np.asarray(bound, float), T, INTR, [0, 1], np.stack(CAMERAS),
                   [traced_depth(seen, pose) for pose in CAMERAS])


@pytest.fixture(scope="module")
def view() -> MeshSource:
    return scene_view()


def mesher(block_size=BLOCK) -> IncrementalMesher:
    return IncrementalMesher(BlockLayout.of(block_size, RES), MeshSettings(resolution=RES, truncation=T))


def merged(blocks: dict) -> trimesh.Trimesh:
    return trimesh.util.concatenate([trimesh.Trimesh(b.vertices, b.faces, process=False) for b in blocks.values()])


# ------------------------------------------------------------------------------------------------ blocks


def test_blocks_tile_the_observed_surface_without_seams(view):
    m = mesher()
    changes = m.update(view, budget_s=1e9)
    assert changes.pending == 0 and not changes.removed and len(changes.changed) >= 6
    mesh = merged(changes.changed)
    # On the true surface (marching cubes on an exact SDF: well within a voxel).
    distance = AnalyticField([BALL, SMALL]).distance(torch.from_numpy(mesh.vertices)).numpy()
    assert np.abs(distance).max() < 0.2 * RES
    # Exactly the triangles of one extraction over the whole bound (same grid points, same culling), restricted
    # to the boxes the blocks meshed: blocks meet without seam, gap or overlap.
    from scipy.spatial import cKDTree

    from eslam_core.outputs.culling import visible_mask

    whole = extract_mesh(view.sdf, view.color, BOUND, MeshSettings(resolution=RES, truncation=T),
                         visible_fn=lambda p: visible_mask(p, view.poses, INTR, view.depths, T))
    boxes = [m.layout.grid_bound(key, view.bound, m.region(key)) for key in changes.changed]
    centres = whole.triangles_center
    inside = np.logical_or.reduce([np.all((centres > box[0]) & (centres < box[1]), axis=1) for box in boxes])
    assert inside.mean() > 0.9
    block_centres = mesh.triangles_center
    assert len(block_centres) == inside.sum()
    gap, _ = cKDTree(centres[inside]).query(block_centres)
    assert gap.max() < 1e-6  # float32 vertex positions of marching cubes
    # Every block's surface lies inside its own box.
    for key, block in changes.changed.items():
        edge = m.layout.edge
        assert np.all(block.vertices >= np.array(key) * edge - 1e-9)
        assert np.all(block.vertices <= (np.array(key) + 1) * edge + 1e-9)


def test_unchanged_map_reports_nothing_and_a_change_reports_only_its_blocks(view):
    m = mesher()
    first = m.update(view, budget_s=1e9)
    assert m.update(view, budget_s=1e9).meshed == 0  # the same view again: nothing to do
    again = m.update(scene_view(), budget_s=1e9)  # a new view of the same map: every block re-meshed, none reported
    inside_map = [key for key in m.known if m.layout.grid_bound(key, view.bound, m.region(key)) is not None]
    assert again.meshed == len(inside_map) and again.changed == {} and again.removed == []

    # The small ball grows: only the blocks it reaches change, with their addresses; all others stay as they were.
    # (The keyframes stay as they were: only the map changes, as in a mapping step.)
    small_key = (1, -1, 1)
    assert small_key in first.changed
    bigger = (SMALL[0], SMALL[1], SMALL[2], SMALL[3] + 0.03)
    grown = m.update(scene_view((BALL, bigger), depth_balls=(BALL, SMALL)), budget_s=1e9)
    assert set(grown.changed) == {small_key} and grown.removed == []
    for key in set(first.changed) - {small_key}:
        assert m.blocks[key] is first.changed[key]

    # The small ball is taken away: its block becomes empty and is removed; nothing else is reported.
    gone = m.update(scene_view((BALL,), depth_balls=(BALL, SMALL)), budget_s=1e9)
    assert gone.removed == [small_key] and gone.changed == {} and small_key not in m.blocks


def test_a_time_budget_spreads_the_first_mesh_over_several_passes(view):
    complete = mesher().update(view, budget_s=1e9).changed
    m = mesher()
    passes, reported = 0, {}
    while True:
        changes = m.update(view, budget_s=1e-9)  # at least one block per pass
        assert changes.meshed <= 1
        reported.update(changes.changed)
        passes += 1
        if changes.pending == 0:
            break
    inside_map = [key for key in m.known if m.layout.grid_bound(key, view.bound, m.region(key)) is not None]
    assert passes == len(inside_map) and set(reported) == set(complete)
    assert merged(reported).area == pytest.approx(merged(complete).area, rel=1e-9)


def test_blocks_keep_their_address_and_mesh_when_the_map_grows(view):
    m = mesher()
    small = np.array([[-1.2, -1.2, -0.2], [0.4, 1.2, 1.1]])  # the map before it grew: x up to 0.4
    before = m.update(scene_view(bound=small), budget_s=1e9).changed
    assert all(key[0] <= 0 for key in before)
    after = m.update(view, budget_s=1e9)
    # Blocks wholly inside the old bound are not re-sent; the blocks cut by it and the new ones are.
    assert {key for key in after.changed if key[0] < 0} == set()
    assert any(key[0] >= 1 for key in after.changed) and any(key[0] == 0 for key in after.changed)


def test_surface_change_test_tolerates_sub_voxel_drift():
    rng = np.random.default_rng(0)
    vertices = rng.uniform(0, 1, (500, 3))
    faces = rng.integers(0, 500, (800, 3))
    colors = rng.integers(0, 256, (500, 4)).astype(np.uint8)
    old = BlockMesh(vertices, faces, colors)
    tol = RES / 2
    assert not surface_changed(old, BlockMesh(vertices + 0.2 * tol, faces, colors), tol)
    assert surface_changed(old, BlockMesh(vertices + [1.5 * tol, 0, 0], faces, colors), tol)
    recoloured = colors.copy()
    recoloured[7, 0] ^= 0x80
    assert not surface_changed(old, BlockMesh(vertices, faces, recoloured), tol)  # one stray vertex: noise
    recoloured[10:20, 1] ^= 0x80
    assert surface_changed(old, BlockMesh(vertices, faces, recoloured), tol)
    moved = vertices.copy()
    moved[:3] += 3 * tol
    assert not surface_changed(old, BlockMesh(moved, faces, colors), tol)
    moved[:20] += 3 * tol
    assert surface_changed(old, BlockMesh(moved, faces, colors), tol)
    # Surface appearing in a block: a speck of one triangle is noise, a dozen vertices are a change; so is a block
    # that had no surface before, however small its surface.
    def without(n):
        return BlockMesh(vertices[n:], faces[faces.min(1) >= n] - n, colors[n:])

    assert not surface_changed(without(3), old, tol) and surface_changed(without(12), old, tol)
    assert surface_changed(None, BlockMesh(vertices[:3], np.array([[0, 1, 2]]), colors[:3]), tol)
    assert surface_changed(old, BlockMesh(vertices[:250], faces[faces.max(1) < 250], colors[:250]), tol)  # half gone
    assert surface_changed(None, old, tol) and surface_changed(old, None, tol) and not surface_changed(None, None, tol)


def test_thinning_keeps_every_nth_triangle_within_the_budget():
    assert [thinning_stride(n, 100) for n in (0, 100, 101, 400, 401)] == [1, 1, 2, 4, 8]
    rng = np.random.default_rng(1)
    block = BlockMesh(rng.uniform(0, 1, (50, 3)), rng.integers(0, 50, (10, 3)),
                      rng.integers(0, 256, (50, 4)).astype(np.uint8))
    corners, colors = triangle_soup(block, stride=3)
    assert corners.shape == (12, 3) and colors.shape == (12, 4) and corners.dtype == np.dtype("<f8")
    np.testing.assert_array_equal(corners[3:6], block.vertices[block.faces[3]])
    np.testing.assert_allclose(colors[:3], block.colors[block.faces[0]] / 255.0, rtol=1e-6)


# ------------------------------------------------------------------------------------------------ the process


def snapshot_of(balls, have=frozenset(), bound=BOUND) -> MeshSnapshot:
    import io

    buffer = io.BytesIO()
    torch.save(AnalyticField(list(balls)), buffer)
    depths = {i: traced_depth(AnalyticField(list(balls)), pose) for i, pose in enumerate(CAMERAS) if i not in have}
    return MeshSnapshot(buffer.getvalue(), np.asarray(bound, float), T, INTR, [0, 1], np.stack(CAMERAS), depths)


def wait(mesher: BackgroundMesher, timeout: float = 60.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        update = mesher.poll()
        if update is not None:
            return update
        time.sleep(0.01)
    raise AssertionError("the mesh process gave no update")


def test_mesh_process_reports_changes_under_its_budget_and_forgets_on_reset():
    m = BackgroundMesher(RES, 0.5, budget_s=0.05, triangle_budget=10**6, nice=19)
    try:
        m.submit(snapshot_of([BALL, SMALL]))
        first = wait(m)
        assert not first.error, first.error
        blocks = dict(first.changed)
        while m.pending:  # continue on the same map until every dirty block is meshed
            m.submit(None)
            update = wait(m)
            assert not update.removed
            blocks.update(update.changed)
        assert len(blocks) == update.blocks >= 6 and update.stride == 1 and update.cpu_s > 0
        assert sum(len(c) for c, _ in blocks.values()) == 3 * update.triangles
        # Asked for everything, a job with nothing to mesh brings back every block, as first sent (shared memory).
        m.submit(None, everything=True)
        every = wait(m)
        assert every.everything and every.meshed == 0 and set(every.changed) == set(blocks)
        for key, (corners, colors) in every.changed.items():
            np.testing.assert_array_equal(corners, blocks[key][0])
            np.testing.assert_array_equal(colors, blocks[key][1])
        # Depth images are sent once: the next snapshot carries none, and an unchanged map reports nothing.
        assert m.have() == {0, 1}
        m.submit(snapshot_of([BALL, SMALL], have=m.have()))
        quiet = wait(m)
        assert quiet.changed == {} and quiet.removed == [] and not quiet.error
        # After a reset the process starts a new map: everything is new again; an update of before is dropped.
        m.submit(None)
        m.reset()
        assert wait(m).epoch == m.epoch - 1
        m.submit(snapshot_of([BALL]))
        fresh = wait(m)
        assert fresh.epoch == m.epoch and not fresh.error
        # (Under load a job's 50 ms may mesh only blocks without surface: CI once got one such block, 85 pending.)
        changed = dict(fresh.changed)
        while not changed and m.pending:
            m.submit(None)
            changed.update(wait(m).changed)
        assert changed
    finally:
        m.close()
    assert not m.running
