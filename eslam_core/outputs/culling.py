"""Mesh culling: keep only the surface that the cameras of a run actually observed.

Reconstruction metrics are only comparable when both meshes are cut to the same observed region (NICE-SLAM / ESLAM
protocol; Azinovic et al. 2022, Wang et al. 2022): a vertex survives if at least one camera sees it, i.e. it lies in
front of the camera, projects inside the image, and is not hidden behind the surface the sensor measured at that
pixel (up to the truncation distance T, so the far side of a thin surface that the SDF legitimately models is kept).
A face survives if enough of its vertices survive.

The same code culls the mesh extracted after a run, so it is vectorised over cameras (in chunks, bounded memory) and
only tests the vertices that no camera has seen yet.
"""
from __future__ import annotations

from typing import Optional, Sequence, Union

import numpy as np
import trimesh

from eslam_core.camera import Intrinsics

# A depth stack (K, H, W) or any sequence of K depth images (H, W); sliced per chunk of cameras.
DepthImages = Union[np.ndarray, Sequence[np.ndarray]]


class CullingError(ValueError):
    """Inconsistent culling input (shapes, non-finite poses, no cameras)."""


def _checked_points(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise CullingError(f"points must be an (N, 3) array, got shape {points.shape}")
    return points


def _checked_poses(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim == 2:
        poses = poses[None]
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise CullingError(f"poses must be a (K, 4, 4) array of camera-to-world matrices, got shape {poses.shape}")
    if len(poses) == 0:
        raise CullingError("no cameras given: culling needs at least one camera pose (and its depth image)")
    bad = np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2)))
    if bad.size:
        raise CullingError(f"camera pose {bad[0]} (of {len(poses)}) contains nan/inf: drop that camera before culling")
    return poses


def _camera_coordinates(points: np.ndarray, world_to_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y, z (each K x N) of N world points in each of K cameras.

    One (K x 3) @ (3 x N) product per axis keeps every result contiguous, which the element-wise tests that
    follow need to be fast (this function is the inner loop of culling).
    """
    points_t = points.T
    rotation, translation = world_to_camera[:, :3, :3], world_to_camera[:, :3, 3]
    return tuple(rotation[:, axis, :] @ points_t + translation[:, axis, None] for axis in range(3))


def _seen_by_any_camera(
    points: np.ndarray,
    world_to_camera: np.ndarray,
    intr: Intrinsics,
    depths: Optional[np.ndarray],
    truncation: float,
    near: float,
) -> np.ndarray:
    """(N,) bool: seen by at least one of the K cameras of this chunk."""
    n = len(points)
    x, y, z = _camera_coordinates(points, world_to_camera)
    # Points at or behind the camera give inf/nan here; `in_front` masks them out (nan compares False anyway).
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * (x / z) + intr.cx
        v = intr.fy * (y / z) + intr.cy
    # Pixel p covers [p - 0.5, p + 0.5): the nearest pixel exists iff the projection is inside the image rectangle.
    inside = (z > near) & (u >= -0.5) & (u < intr.width - 0.5) & (v >= -0.5) & (v < intr.height - 0.5)
    hits = np.flatnonzero(inside)  # flat (camera, point) indices
    seen = np.zeros(n, dtype=bool)
    if depths is None:
        seen[hits % n] = True
        return seen
    # u + 0.5 >= 0 for these, so truncation towards zero is the floor: the nearest pixel.
    col = np.minimum((u.ravel()[hits] + 0.5).astype(np.int64), intr.width - 1)
    row = np.minimum((v.ravel()[hits] + 0.5).astype(np.int64), intr.height - 1)
    camera = hits // n
    observed = depths.reshape(-1)[(camera * intr.height + row) * intr.width + col]
    # A point is hidden when it lies deeper than the measured surface plus the truncation band.
    # Pixels without a measurement (0 or nan) prove nothing, so they do not make a point visible.
    not_occluded = (observed > 0) & (z.ravel()[hits] <= observed + truncation)
    seen[hits[not_occluded] % n] = True
    return seen


def visible_mask(
    points: np.ndarray,
    poses: np.ndarray,
    intr: Intrinsics,
    depths: Optional[DepthImages],
    truncation: float,
    near: float = 0.0,
    cameras_per_chunk: int = 8,
    points_per_chunk: int = 65_536,
) -> np.ndarray:
    """(N,) bool: True where at least one camera sees the point.

    A camera sees a point when it is in front of it (z > near), its nearest pixel is inside the image, and, when
    `depths` are given, that pixel has a measurement (> 0) and the point is not behind it: z <= depth + truncation.
    `depths` is a (K, H, W) stack in metres or a sequence of K (H, W) images, or None to test only the frusta.
    """
    points = _checked_points(points)
    poses = _checked_poses(poses)
    if not np.isfinite(points).all():
        raise CullingError("points contain nan/inf: clean the mesh (its vertices) before culling")
    if truncation < 0 or not np.isfinite(truncation):
        raise CullingError(f"truncation must be a finite distance >= 0 in metres, got {truncation}")
    if depths is not None and len(depths) != len(poses):
        raise CullingError(f"got {len(poses)} poses but {len(depths)} depth images: give one depth image per pose")

    world_to_camera = np.linalg.inv(poses)
    visible = np.zeros(len(points), dtype=bool)
    for first in range(0, len(poses), cameras_per_chunk):
        last = min(first + cameras_per_chunk, len(poses))
        chunk_depths = None
        if depths is not None:
            try:
                chunk_depths = np.ascontiguousarray(depths[first:last], dtype=np.float32)
            except ValueError:
                raise CullingError(f"depth images of cameras {first}-{last - 1} differ in size: give "
                                   f"{intr.height}x{intr.width} images, one per pose") from None
            expected = (last - first, intr.height, intr.width)
            if chunk_depths.shape != expected:
                raise CullingError(
                    f"depth images of cameras {first}-{last - 1} have shape {chunk_depths.shape[1:]}, "
                    f"but the intrinsics are {intr.width}x{intr.height}: use the intrinsics of the depth images"
                )
        # Points some earlier camera already saw need no further test: the cost shrinks as coverage grows.
        pending = np.flatnonzero(~visible)
        if pending.size == 0:
            break
        for start in range(0, pending.size, points_per_chunk):
            idx = pending[start : start + points_per_chunk]
            visible[idx] = _seen_by_any_camera(
                points[idx], world_to_camera[first:last], intr, chunk_depths, truncation, near
            )
    return visible


def keep_visible_faces(
    mesh: trimesh.Trimesh, vertex_visible: np.ndarray, min_visible_vertices: int = 3
) -> trimesh.Trimesh:
    """The sub-mesh of faces with at least `min_visible_vertices` visible vertices; unused vertices are dropped and
    vertex (or face) colours follow their vertices (faces)."""
    if not 1 <= min_visible_vertices <= 3:
        raise CullingError(f"min_visible_vertices must be 1, 2 or 3, got {min_visible_vertices}")
    vertex_visible = np.asarray(vertex_visible, dtype=bool)
    if vertex_visible.shape != (len(mesh.vertices),):
        raise CullingError(
            f"vertex mask has shape {vertex_visible.shape} but the mesh has {len(mesh.vertices)} vertices"
        )
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    keep_face = vertex_visible[faces].sum(axis=1) >= min_visible_vertices
    kept_faces = faces[keep_face]
    used_vertices = np.unique(kept_faces)
    new_index = np.full(len(mesh.vertices), -1, dtype=np.int64)
    new_index[used_vertices] = np.arange(used_vertices.size)

    kwargs = {}
    if mesh.visual.kind == "vertex":
        kwargs["vertex_colors"] = np.asarray(mesh.visual.vertex_colors)[used_vertices]
    elif mesh.visual.kind == "face":
        kwargs["face_colors"] = np.asarray(mesh.visual.face_colors)[keep_face]
    return trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices)[used_vertices],
        faces=new_index[kept_faces].reshape(-1, 3),
        process=False,
        **kwargs,
    )


def cull_mesh(
    mesh: trimesh.Trimesh,
    poses: np.ndarray,
    intr: Intrinsics,
    depths: Optional[DepthImages],
    truncation: float,
    min_visible_vertices: int = 3,
    near: float = 0.0,
) -> trimesh.Trimesh:
    """The part of `mesh` the cameras observed: faces with at least `min_visible_vertices` (default: all three)
    vertices seen by some camera (see `visible_mask`)."""
    vertex_visible = visible_mask(np.asarray(mesh.vertices), poses, intr, depths, truncation, near=near)
    return keep_visible_faces(mesh, vertex_visible, min_visible_vertices)
