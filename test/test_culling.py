"""Mesh culling against hand-placed cameras: the exact faces a camera sees survive, hidden ones do not.

Scene (all distances in metres, camera looking along +z from the origin):
- a 40x30 camera with fx = fy = 20, cx = 19.5, cy = 14.5: at z = 2 one pixel is 10 cm wide;
- a grid of vertices on the plane z = 2 at x_i = -3.075 + 0.4 i (i = 0..15), y_j = -2.075 + 0.4 j (j = 0..10).
  Vertex (i, j) projects to u = 4 i - 11.25, v = 4 j - 6.25 (never on a pixel border), so it is inside the image
  for i = 3..12 and j = 2..8;
- an occluder square at z = 1 covering x in [-0.25, 0.35], y in [-0.1, 0.25], i.e. pixel columns 15..26 and rows
  13..19: it hides the plane vertices i = 7, 8, 9 (columns 17, 21, 25) and j = 5, 6 (rows 14, 18).
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from eslam_core.camera import Intrinsics
from eslam_core.outputs.culling import CullingError, cull_mesh, keep_visible_faces, visible_mask
from eslam_core.rendering.raycast import render_depth

INTR = Intrinsics(width=40, height=30, fx=20.0, fy=20.0, cx=19.5, cy=14.5)
NI, NJ = 16, 11


def grid_plane() -> trimesh.Trimesh:
    i, j = np.meshgrid(np.arange(NI), np.arange(NJ), indexing="ij")
    vertices = np.stack([-3.075 + 0.4 * i, -2.075 + 0.4 * j, np.full(i.shape, 2.0)], -1).reshape(-1, 3)
    faces = []
    for a in range(NI - 1):
        for b in range(NJ - 1):
            v00, v10, v01, v11 = a * NJ + b, (a + 1) * NJ + b, a * NJ + b + 1, (a + 1) * NJ + b + 1
            faces += [[v00, v10, v11], [v00, v11, v01]]
    colours = np.zeros((len(vertices), 4), dtype=np.uint8)
    colours[:, 0] = np.arange(len(vertices)) % 256  # a distinct colour per vertex, to follow them through culling
    colours[:, 1] = np.arange(len(vertices)) // 256
    colours[:, 3] = 255
    return trimesh.Trimesh(vertices, np.array(faces), vertex_colors=colours, process=False)


def occluder() -> trimesh.Trimesh:
    corners = np.array([[-0.25, -0.1, 1.0], [0.35, -0.1, 1.0], [0.35, 0.25, 1.0], [-0.25, 0.25, 1.0]])
    return trimesh.Trimesh(corners, [[0, 1, 2], [0, 2, 3]], process=False)


def pose(translation=(0.0, 0.0, 0.0), rotation=np.eye(3)) -> np.ndarray:
    p = np.eye(4)
    p[:3, :3] = rotation
    p[:3, 3] = translation
    return p


def sensor_depth(camera_pose: np.ndarray) -> np.ndarray:
    scene = trimesh.util.concatenate([grid_plane(), occluder()])
    depth, _ = render_depth(scene, INTR, camera_pose)
    return depth


def vertex_set(columns, rows, minus=()) -> set[int]:
    hidden = set(minus)
    return {i * NJ + j for i in columns for j in rows if (i, j) not in hidden}


def faces_with_all_vertices_in(mesh: trimesh.Trimesh, vertices: set[int]) -> set[tuple]:
    return {tuple(sorted(map(tuple, mesh.vertices[f].round(4)))) for f in mesh.faces if set(f) <= vertices}


def face_keys(mesh: trimesh.Trimesh) -> set[tuple]:
    return {tuple(sorted(map(tuple, mesh.vertices[f].round(4)))) for f in mesh.faces}


HIDDEN = [(i, j) for i in (7, 8, 9) for j in (5, 6)]


def test_frustum_only_keeps_the_vertices_that_project_inside_the_image():
    plane = grid_plane()
    mask = visible_mask(plane.vertices, pose()[None], INTR, None, truncation=0.06)
    assert set(np.flatnonzero(mask)) == vertex_set(range(3, 13), range(2, 9))


def test_occluder_hides_exactly_the_vertices_behind_it():
    plane = grid_plane()
    camera = pose()
    mask = visible_mask(plane.vertices, camera[None], INTR, sensor_depth(camera)[None], truncation=0.06)
    assert set(np.flatnonzero(mask)) == vertex_set(range(3, 13), range(2, 9), minus=HIDDEN)


def test_cull_mesh_keeps_exactly_the_faces_seen_by_the_camera():
    plane = grid_plane()
    camera = pose()
    culled = cull_mesh(plane, camera[None], INTR, sensor_depth(camera)[None], truncation=0.06)
    expected = faces_with_all_vertices_in(plane, vertex_set(range(3, 13), range(2, 9), minus=HIDDEN))
    # 9 x 6 visible grid cells (2 faces each) minus the 22 faces with a hidden corner (counted by hand: the 12
    # cells around the hidden block lose both faces except 2 corner cells that keep one).
    assert len(expected) == 2 * 9 * 6 - 22
    assert face_keys(culled) == expected
    # Only referenced vertices remain, and each keeps its colour.
    assert len(culled.vertices) == len(np.unique(culled.faces))
    original = {tuple(v.round(4)): c for v, c in zip(plane.vertices, plane.visual.vertex_colors)}
    for vertex, colour in zip(culled.vertices, culled.visual.vertex_colors):
        np.testing.assert_array_equal(colour, original[tuple(vertex.round(4))])


def test_min_visible_vertices_one_keeps_faces_touching_the_visible_region():
    plane = grid_plane()
    camera = pose()
    visible = vertex_set(range(3, 13), range(2, 9), minus=HIDDEN)
    culled = cull_mesh(plane, camera[None], INTR, sensor_depth(camera)[None], truncation=0.06, min_visible_vertices=1)
    expected = {tuple(sorted(map(tuple, plane.vertices[f].round(4)))) for f in plane.faces if set(f) & visible}
    assert face_keys(culled) == expected


def test_truncation_band_keeps_surface_just_behind_the_observed_depth():
    # The plane is 1 m behind the occluder: a truncation of 1.5 m no longer treats it as hidden.
    plane = grid_plane()
    camera = pose()
    mask = visible_mask(plane.vertices, camera[None], INTR, sensor_depth(camera)[None], truncation=1.5)
    assert set(np.flatnonzero(mask)) == vertex_set(range(3, 13), range(2, 9))


def test_several_cameras_see_the_union_and_chunking_does_not_change_it():
    plane = grid_plane()
    # Camera 2 is 2 m to the right: columns shift by 5 (i = 8..15 project inside its image) and the occluder
    # leaves its view, so of the hidden vertices only column 7 stays hidden. Its pixel of the edge column i = 15
    # (x = 2.925) looks at x = 2.95, past the plane's edge: no depth there, so i = 15 is not seen.
    # Camera 3 looks back from z = 4 (rotated 180 deg about y): the occluder is behind the plane for it, and it sees
    # i = 3..12 again, including the two vertices of column 7 hidden from camera 1.
    poses = np.stack([pose(), pose((2.0, 0.0, 0.0)), pose((0.0, 0.0, 4.0), np.diag([-1.0, 1.0, -1.0]))])
    depths = np.stack([sensor_depth(p) for p in poses])
    expected_two = vertex_set(range(3, 15), range(2, 9), minus=[(7, 5), (7, 6)])
    mask = visible_mask(plane.vertices, poses[:2], INTR, depths[:2], truncation=0.06)
    assert set(np.flatnonzero(mask)) == expected_two
    mask_all = visible_mask(plane.vertices, poses, INTR, depths, truncation=0.06)
    assert set(np.flatnonzero(mask_all)) == vertex_set(range(3, 15), range(2, 9))
    tiny_chunks = visible_mask(plane.vertices, poses, INTR, list(depths), 0.06, cameras_per_chunk=1, points_per_chunk=7)
    np.testing.assert_array_equal(tiny_chunks, mask_all)


def test_points_behind_the_camera_or_closer_than_near_are_not_visible():
    points = np.array([[0.0, 0.0, -2.0], [0.05, 0.05, 0.3], [0.05, 0.05, 2.0]])
    depth = np.full((1, INTR.height, INTR.width), 5.0, dtype=np.float32)
    np.testing.assert_array_equal(visible_mask(points, pose()[None], INTR, depth, 0.06), [False, True, True])
    np.testing.assert_array_equal(visible_mask(points, pose()[None], INTR, depth, 0.06, near=0.5), [False, False, True])


def test_pixels_without_depth_do_not_make_points_visible():
    plane = grid_plane()
    depth = sensor_depth(pose())
    depth[:, :20] = 0.0  # left half of the image has no measurement (vertex columns i <= 7 project to u <= 17)
    mask = visible_mask(plane.vertices, pose()[None], INTR, depth[None], truncation=0.06)
    assert set(np.flatnonzero(mask)) == vertex_set(range(8, 13), range(2, 9), minus=HIDDEN)


def test_keep_visible_faces_of_nothing_is_an_empty_mesh():
    plane = grid_plane()
    culled = keep_visible_faces(plane, np.zeros(len(plane.vertices), dtype=bool))
    assert len(culled.faces) == 0 and len(culled.vertices) == 0


def test_bad_input_names_the_problem():
    plane = grid_plane()
    bad_pose = pose()
    bad_pose[0, 3] = np.nan
    with pytest.raises(CullingError, match="nan"):
        visible_mask(plane.vertices, bad_pose[None], INTR, None, 0.06)
    with pytest.raises(CullingError, match="intrinsics"):
        visible_mask(plane.vertices, pose()[None], INTR, np.ones((1, 10, 10), np.float32), 0.06)
    with pytest.raises(CullingError, match="no cameras"):
        visible_mask(plane.vertices, np.zeros((0, 4, 4)), INTR, None, 0.06)
    with pytest.raises(CullingError, match="one depth image per pose"):
        visible_mask(plane.vertices, np.stack([pose(), pose()]), INTR, np.ones((1, 30, 40), np.float32), 0.06)
