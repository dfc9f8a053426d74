"""Headless CPU ray casting against triangle meshes (Embree through trimesh).

Used to render the synthetic scene and, in evaluation, the depth of meshes from arbitrary views.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from eslam_core.camera import Intrinsics


@dataclass
class RayHits:
    distance: np.ndarray  # (N,) distance along the (unit) ray to the first hit, inf where nothing is hit
    face: np.ndarray  # (N,) index of the hit face, -1 where nothing is hit
    location: np.ndarray  # (N, 3) hit point, nan where nothing is hit


def _intersector(mesh: trimesh.Trimesh):
    if not trimesh.ray.has_embree:
        raise RuntimeError("ray casting needs Embree: pip install embreex (a dependency of eslam_core)")
    return mesh.ray  # trimesh picks the Embree intersector and caches it on the mesh


def cast_rays(mesh: trimesh.Trimesh, origins: np.ndarray, directions: np.ndarray) -> RayHits:
    """First intersection of each ray with the mesh. `directions` must be unit vectors."""
    n = len(origins)
    dist = np.full(n, np.inf)
    face = np.full(n, -1, dtype=np.int64)
    loc = np.full((n, 3), np.nan)
    if n == 0 or len(mesh.faces) == 0:
        return RayHits(dist, face, loc)
    locations, ray_idx, tri_idx = _intersector(mesh).intersects_location(origins, directions, multiple_hits=False)
    if len(ray_idx):
        dist[ray_idx] = np.einsum("ij,ij->i", locations - origins[ray_idx], directions[ray_idx])
        face[ray_idx] = tri_idx
        loc[ray_idx] = locations
    return RayHits(dist, face, loc)


def camera_rays(intr: Intrinsics, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World-space origins, unit directions and the per-pixel z of a unit-length ray (row-major pixels).

    The planar depth of a hit at distance t is t * z_of_unit_ray.
    """
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    dirs_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u, dtype=np.float64)], -1)
    dirs_cam = dirs_cam.reshape(-1, 3)
    norm = np.linalg.norm(dirs_cam, axis=1, keepdims=True)
    dirs_cam = dirs_cam / norm
    dirs = dirs_cam @ pose[:3, :3].T
    origins = np.broadcast_to(pose[:3, 3], dirs.shape).copy()
    return origins, dirs, dirs_cam[:, 2]


def render_depth(mesh: trimesh.Trimesh, intr: Intrinsics, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planar depth image (metres, 0 where no surface) and the hit face index per pixel (-1 = none)."""
    origins, dirs, z_unit = camera_rays(intr, pose)
    hits = cast_rays(mesh, origins, dirs)
    depth = np.where(np.isfinite(hits.distance), hits.distance * z_unit, 0.0)
    shape = (intr.height, intr.width)
    return depth.reshape(shape).astype(np.float32), hits.face.reshape(shape)
