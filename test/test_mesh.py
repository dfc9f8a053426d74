"""Mesh extraction from analytic SDFs whose true surfaces are known exactly."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch
import trimesh

from eslam_core.outputs.mesh import (
    EmptyMeshError,
    GridTooLargeError,
    MeshSettings,
    extract_mesh,
    make_grid,
    save_ply,
)

T = 0.06  # truncation of the normalised SDFs below, as in ESLAM
RADIUS = 0.5
SPHERE_BOUND = np.array([[-0.7, -0.7, -0.7], [0.7, 0.7, 0.7]])


def normalised(distance: torch.Tensor) -> torch.Tensor:
    """Signed distance in metres -> ESLAM's normalised TSDF."""
    return torch.clamp(distance / T, -1.0, 1.0)


def sphere_distance(p: torch.Tensor, centre=(0.0, 0.0, 0.0), radius: float = RADIUS) -> torch.Tensor:
    return (p - torch.tensor(centre)).norm(dim=1) - radius


def sphere_sdf(p: torch.Tensor) -> torch.Tensor:
    return normalised(sphere_distance(p))


def position_color(p: torch.Tensor) -> torch.Tensor:
    return torch.clamp(p + 0.5, 0.0, 1.0)


class CountingSdf:
    """Wraps an SDF and counts the points it decodes."""

    def __init__(self, fn):
        self.fn = fn
        self.points = 0

    def __call__(self, p: torch.Tensor) -> torch.Tensor:
        self.points += len(p)
        return self.fn(p)


def sorted_rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])]


# ---------------------------------------------------------------------------------------------- geometry


def test_sphere_vertices_lie_on_the_true_surface():
    res = 0.02
    mesh = extract_mesh(sphere_sdf, None, SPHERE_BOUND, MeshSettings(resolution=res))
    radial_error = np.abs(np.linalg.norm(mesh.vertices, axis=1) - RADIUS)
    assert radial_error.max() < res / 4
    assert radial_error.mean() < res / 20
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * RADIUS**3, rel=0.01)
    assert mesh.area == pytest.approx(4 * math.pi * RADIUS**2, rel=0.01)


def test_sphere_normals_point_to_free_space():
    mesh = extract_mesh(sphere_sdf, None, SPHERE_BOUND, MeshSettings(resolution=0.02))
    outward = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center)
    assert (outward > 0).mean() > 0.99
    # The only exceptions are slivers too thin to have a normal at all.
    proper = mesh.area_faces > 1e-10
    assert (outward[proper] > 0).all()
    # Inverting the SDF (a spherical cavity in solid matter) must flip the normals inward.
    cavity = extract_mesh(lambda p: -sphere_sdf(p), None, SPHERE_BOUND, MeshSettings(resolution=0.02))
    inward = np.einsum("ij,ij->i", cavity.face_normals, cavity.triangles_center)
    assert (inward[cavity.area_faces > 1e-10] < 0).all()


def test_plane_is_exact_and_faces_up_into_free_space():
    height = 0.237  # between grid points
    bound = np.array([[0.0, 0.0, 0.0], [0.5, 0.4, 0.5]])
    mesh = extract_mesh(lambda p: normalised(p[:, 2] - height), None, bound, MeshSettings(resolution=0.03))
    np.testing.assert_allclose(mesh.vertices[:, 2], height, atol=1e-6)
    # The grid is padded to cover the bound: 0.5 / 0.03 -> 17 voxels, so the plane spans 0.51 x 0.42 m.
    assert mesh.area == pytest.approx(0.51 * 0.42, rel=1e-6)
    assert (mesh.face_normals[:, 2] > 0.999).all()


def test_grid_includes_both_ends_and_covers_the_bound():
    grid = make_grid(np.array([[0.0, -1.0, 2.0], [1.0, 1.0, 2.25]]), 0.3)
    assert grid.shape == (5, 8, 2)  # 1.0 / 0.3 -> 4 voxels, 2.0 / 0.3 -> 7, 0.25 / 0.3 -> 1
    last = grid.points(np.array(grid.shape) - 1)
    np.testing.assert_allclose(last, [1.2, 1.1, 2.3])
    # An extent that is an exact multiple of the resolution gets no extra layer from rounding noise.
    assert make_grid(np.array([[0.0, 0.0, 0.0], [3.0, 3.0, 2.0]]), 0.01).shape == (301, 301, 201)


# ---------------------------------------------------------------------------------------------- coarse to fine


def cluttered_sdf(p: torch.Tensor) -> torch.Tensor:
    """A sphere, a 1.2 cm thick plate and a 1.5 cm bead: thin parts a careless coarse pass would lose."""
    ball = sphere_distance(p, centre=(-0.15, 0.0, 0.0), radius=0.3)
    across = (p[:, 2] - 0.25).abs() - 0.006
    along = (p[:, :2] - torch.tensor([0.1, 0.1])).abs().max(dim=1).values - 0.3
    plate = torch.maximum(across, along)
    bead = sphere_distance(p, centre=(0.33, -0.31, -0.29), radius=0.015)
    return normalised(torch.minimum(torch.minimum(ball, plate), bead))


@pytest.mark.parametrize("res, factor", [(0.01, None), (0.01, 4), (0.02, None)])
def test_coarse_to_fine_equals_dense_evaluation(res, factor):
    bound = np.array([[-0.5, -0.45, -0.4], [0.45, 0.5, 0.4]])
    dense_sdf, fast_sdf = CountingSdf(cluttered_sdf), CountingSdf(cluttered_sdf)
    dense = extract_mesh(dense_sdf, None, bound, MeshSettings(resolution=res, coarse_factor=1))
    fast = extract_mesh(fast_sdf, None, bound, MeshSettings(resolution=res, coarse_factor=factor))
    assert len(fast.vertices) == len(dense.vertices) and len(fast.faces) == len(dense.faces)
    np.testing.assert_array_equal(sorted_rows(fast.vertices), sorted_rows(dense.vertices))
    # The bead survives (it is smaller than a coarse cell) ...
    bead_vertices = np.linalg.norm(fast.vertices - [0.33, -0.31, -0.29], axis=1) < 0.03
    assert bead_vertices.sum() >= 8
    # ... and the coarse pass decodes far fewer points than the dense grid.
    assert fast_sdf.points < 0.6 * dense_sdf.points


def test_coarse_factor_too_wide_for_the_truncation_is_refused():
    with pytest.raises(ValueError, match="coarse_factor=2 or leave it None"):
        MeshSettings(resolution=0.02, coarse_factor=4)


# ---------------------------------------------------------------------------------------------- colour, visibility


def test_vertex_colours_come_from_color_fn():
    mesh = extract_mesh(sphere_sdf, position_color, SPHERE_BOUND, MeshSettings(resolution=0.04))
    colors = mesh.visual.vertex_colors
    assert colors.dtype == np.uint8 and colors.shape == (len(mesh.vertices), 4)
    expected = np.clip(mesh.vertices + 0.5, 0, 1) * 255
    assert np.abs(colors[:, :3] - expected).max() <= 0.5 + 1e-6
    assert (colors[:, 3] == 255).all()
    grey = extract_mesh(sphere_sdf, None, SPHERE_BOUND, MeshSettings(resolution=0.04)).visual.vertex_colors
    assert (grey[:, :3] == 128).all()


def test_visible_fn_keeps_only_the_observed_half():
    res = 0.02
    cut = 0.01  # halfway between the grid planes x = 0 and x = 0.02
    calls = []

    def seen_beyond_cut(points: np.ndarray) -> np.ndarray:
        calls.append(len(points))
        return points[:, 0] > cut

    mesh = extract_mesh(sphere_sdf, None, SPHERE_BOUND, MeshSettings(resolution=res), visible_fn=seen_beyond_cut)
    face_x = mesh.vertices[mesh.faces][:, :, 0]
    assert (face_x > cut).all()
    # Voxels with an unseen corner are masked out, so no vertex lies between the cut and the first seen grid plane.
    assert face_x.min() > 0.02 - 1e-9
    # The rest of the seen cap is kept: at most a strip one voxel wide beyond that plane is missing.
    cap_area = lambda x: 2 * math.pi * RADIUS * (RADIUS - x)
    assert cap_area(0.02 + res) < mesh.area < cap_area(0.02)
    # visible_fn is asked about points near the surface only, not about the whole 71^3 grid.
    assert sum(calls) < 0.2 * 71**3


def test_voxels_with_an_unseen_corner_make_no_surface():
    """A tilted plane crosses voxel edges along x, so a vertex test alone would keep faces from half-seen voxels."""
    normal = torch.tensor([1.0, 0.3, 1.0]) / torch.tensor([1.0, 0.3, 1.0]).norm()
    bound = np.array([[-0.3, -0.3, -0.3], [0.3, 0.3, 0.3]])
    mesh = extract_mesh(
        lambda p: normalised(p @ normal - 0.0523),
        None,
        bound,
        MeshSettings(resolution=0.02),
        visible_fn=lambda p: p[:, 0] > 0.01,  # the grid plane x = 0 is unseen, x = 0.02 is seen
    )
    assert mesh.vertices[:, 0].min() > 0.02 - 1e-9


def test_visible_fn_mask_keeps_holes_out_of_the_seen_part():
    """Faces wholly inside the seen region are all kept: the half mesh equals the full mesh restricted to x > res."""
    res = 0.02
    full = extract_mesh(sphere_sdf, None, SPHERE_BOUND, MeshSettings(resolution=res))
    half = extract_mesh(sphere_sdf, None, SPHERE_BOUND, MeshSettings(resolution=res), visible_fn=lambda p: p[:, 0] > 0)
    far_side = full.vertices[full.faces][:, :, 0].min(axis=1) > res
    expected = full.triangles_center[far_side]
    got = half.triangles_center[half.vertices[half.faces][:, :, 0].min(axis=1) > res]
    np.testing.assert_allclose(sorted_rows(got), sorted_rows(expected), atol=1e-9)


# ---------------------------------------------------------------------------------------------- components


def test_small_components_are_removed():
    def with_speck(p):
        return normalised(torch.minimum(sphere_distance(p), sphere_distance(p, centre=(0.6, 0.6, 0.6), radius=0.03)))

    kept = extract_mesh(with_speck, None, SPHERE_BOUND, MeshSettings(resolution=0.02))
    near_speck = lambda m: (np.linalg.norm(m.vertices - 0.6, axis=1) < 0.05).sum()
    assert near_speck(kept) > 0
    cleaned = extract_mesh(with_speck, None, SPHERE_BOUND, MeshSettings(resolution=0.02, min_component_faces=200))
    assert near_speck(cleaned) == 0
    speck_faces = (np.linalg.norm(kept.triangles_center - 0.6, axis=1) < 0.05).sum()
    assert len(cleaned.faces) == len(kept.faces) - speck_faces
    assert cleaned.area == pytest.approx(4 * math.pi * RADIUS**2, rel=0.01)
    assert cleaned.is_watertight


# ---------------------------------------------------------------------------------------------- errors


@pytest.mark.parametrize("res", [0.05, 0.01])  # dense and coarse-to-fine evaluation
def test_sdf_without_surface_raises_empty_mesh_error(res):
    with pytest.raises(EmptyMeshError, match="no surface inside the bound.*untrained.*bound misses the scene"):
        extract_mesh(lambda p: torch.full((len(p),), 0.9), None, SPHERE_BOUND, MeshSettings(resolution=res))


def test_fully_masked_grid_raises_empty_mesh_error():
    with pytest.raises(EmptyMeshError, match="no grid point is visible from any camera.*camera poses"):
        extract_mesh(
            sphere_sdf, None, SPHERE_BOUND, MeshSettings(resolution=0.05), visible_fn=lambda p: np.zeros(len(p), bool)
        )


def test_grid_too_large_names_a_resolution_that_fits():
    bound = np.array([[0.0, 0.0, 0.0], [40.0, 40.0, 10.0]])
    with pytest.raises(GridTooLargeError, match="use resolution") as info:
        extract_mesh(sphere_sdf, None, bound, MeshSettings(resolution=0.01))
    assert isinstance(info.value, EmptyMeshError)
    suggested = float(str(info.value).split("use resolution ")[1].split()[0])
    grid = make_grid(bound, suggested)  # must not raise
    assert grid.size > 0.9 * 400_000_000  # and is not needlessly coarse


@pytest.mark.parametrize(
    "bound, message",
    [
        (np.zeros((3, 2)), r"\(2, 3\) array"),
        (np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]]), "max > min on every axis; not so on x"),
        (np.array([[0.0, 0.0, np.nan], [1.0, 1.0, 1.0]]), "finite"),
    ],
)
def test_bad_bound_is_refused(bound, message):
    with pytest.raises(ValueError, match=message):
        extract_mesh(sphere_sdf, None, bound, MeshSettings())


@pytest.mark.parametrize("resolution", [0.0, -0.01, float("nan")])
def test_bad_resolution_is_refused(resolution):
    with pytest.raises(ValueError, match="resolution must be a positive number of metres"):
        MeshSettings(resolution=resolution)


def test_nan_from_the_decoder_is_reported():
    with pytest.raises(ValueError, match="NaN or inf.*earlier checkpoint"):
        extract_mesh(lambda p: sphere_sdf(p) / 0.0 * 0.0, None, SPHERE_BOUND, MeshSettings(resolution=0.1))


# ---------------------------------------------------------------------------------------------- PLY


def test_ply_round_trip_keeps_faces_and_colours(tmp_path):
    mesh = extract_mesh(sphere_sdf, position_color, SPHERE_BOUND, MeshSettings(resolution=0.05))
    path = save_ply(mesh, tmp_path / "sphere.ply")
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian")
    loaded = trimesh.load(path, process=False)
    assert len(loaded.faces) == len(mesh.faces)
    np.testing.assert_array_equal(loaded.faces, mesh.faces)
    np.testing.assert_allclose(loaded.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(loaded.visual.vertex_colors, mesh.visual.vertex_colors)


def test_save_ply_refuses_empty_meshes_and_missing_directories(tmp_path):
    with pytest.raises(EmptyMeshError, match="empty mesh"):
        save_ply(trimesh.Trimesh(), tmp_path / "empty.ply")
    assert not (tmp_path / "empty.ply").exists()
    mesh = extract_mesh(sphere_sdf, None, SPHERE_BOUND, MeshSettings(resolution=0.1))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        save_ply(mesh, tmp_path / "missing" / "mesh.ply")


# ---------------------------------------------------------------------------------------------- a room


ROOM_MAX = torch.tensor([3.0, 3.0, 2.0])
BALL_CENTRE = (1.5, 1.5, 0.6)


def room_sdf(p: torch.Tensor) -> torch.Tensor:
    """Inside of a 3 x 3 x 2 m box room (free space) with a 0.4 m ball on a stand-in for furniture."""
    to_wall = torch.minimum(p, ROOM_MAX - p).min(dim=1).values
    return normalised(torch.minimum(to_wall, sphere_distance(p, BALL_CENTRE, 0.4)))


@pytest.mark.parametrize("res", [0.02, 0.01])
def test_box_room(res):
    bound = np.array([[-0.13, -0.13, -0.13], [3.13, 3.13, 2.13]])
    start = time.perf_counter()
    mesh = extract_mesh(room_sdf, position_color, bound, MeshSettings(resolution=res))
    seconds = time.perf_counter() - start
    print(f"\n3x3x2 m room at {res * 100:.0f} cm: {seconds:.2f} s, {len(mesh.faces)} faces")
    v = torch.from_numpy(mesh.vertices)
    distance = torch.minimum(
        torch.minimum(v, ROOM_MAX - v).abs().min(dim=1).values, sphere_distance(v, BALL_CENTRE, 0.4).abs()
    )
    assert distance.max() < res / 2
    walls = 2 * (3 * 3 + 3 * 2 + 3 * 2)
    assert mesh.area == pytest.approx(walls + 4 * math.pi * 0.4**2, rel=0.005)
    assert mesh.is_watertight
