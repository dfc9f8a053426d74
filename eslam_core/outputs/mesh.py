"""Mesh extraction from the neural TSDF: marching cubes on a grid of decoded SDF values.

The map decodes, for any world point, a normalised truncated SDF phi in [-1, 1] (units of the truncation T;
positive in free space, negative inside objects, zero on surfaces) and an RGB colour. The mesh is the zero level
set of phi sampled on a regular grid (Sec. 3 of the paper: "an implicit TSDF that can be used in marching cubes").

Pipeline of `extract_mesh`:
1. Grid: regular points over the bound with spacing `resolution`, both ends included.
2. SDF volume, coarse to fine: phi on a coarse grid first; only coarse cells that can hold surface are decoded at
   full resolution, the others are filled with their sign (+1 / -1). A cell can hold surface only if one of its
   corners is close to it, and |phi| * T bounds that distance (section "Coarse to fine" below).
3. Observed region: with `visible_fn`, voxels with a corner no camera saw produce no triangle, and faces with a
   vertex no camera saw are removed afterwards.
4. Marching cubes at level 0, faces wound so that normals point to free space; vertex colours from `color_fn`;
   optionally small connected components dropped.

Every way of ending up with no triangle raises `EmptyMeshError` with the reason, never an empty file.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Integral
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.measure import marching_cubes

from eslam_core.atomic import write_atomic

SdfFn = Callable[[torch.Tensor], torch.Tensor]  # (N, 3) float32 world points -> (N,) normalised SDF
ColorFn = Callable[[torch.Tensor], torch.Tensor]  # (N, 3) float32 world points -> (N, 3) RGB in [0, 1]
VisibleFn = Callable[[np.ndarray], np.ndarray]  # (N, 3) float64 world points -> (N,) bool "seen by a camera"

# A float32 volume of this many points takes 1.6 GB; beyond it a run would rather be told to mesh coarser.
MAX_GRID_POINTS = 400_000_000

# A decoder is not an exact distance function: where cameras saw a surface obliquely, the TSDF learned along rays
# is steeper than 1/T (distance along the ray > distance to the surface). The coarse pass assumes slopes up to
# LIPSCHITZ_SAFETY / T, which covers viewing angles up to about 48 degrees from the normal even if every view of a
# surface were that oblique.
LIPSCHITZ_SAFETY = 1.5

# Coarse spacings tried by the automatic choice, in fine voxels, largest first.
COARSE_FACTORS = (8, 4, 2, 1)

GREY = np.array([128, 128, 128, 255], dtype=np.uint8)  # vertex colour when the map has no colour decoder

# The 8 corners of a voxel (cube) relative to its minimum corner.
CUBE_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)


class EmptyMeshError(ValueError):
    """Extraction would yield no triangle; the message says why and what to try."""


class GridTooLargeError(EmptyMeshError):
    """The requested resolution needs more grid points than MAX_GRID_POINTS; the message names a coarser one."""


@dataclass
class MeshSettings:
    resolution: float = 0.02  # voxel size in metres (> 0)
    chunk: int = 65536  # points per decoder call: bounds the memory of decoder activations
    min_component_faces: int = 0  # drop connected components with fewer faces (0 = keep all)
    truncation: float = 0.06  # the map's truncation T in metres: |phi| * T bounds the distance to the surface
    coarse_factor: Optional[int] = None  # coarse pass spacing in voxels; None = automatic, 1 = dense evaluation

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"mesh resolution must be a positive number of metres, got {self.resolution}")
        if not isinstance(self.chunk, Integral) or self.chunk < 1:
            raise ValueError(f"mesh chunk must be a positive number of points, got {self.chunk}")
        if not isinstance(self.min_component_faces, Integral) or self.min_component_faces < 0:
            raise ValueError(
                f"min_component_faces must be 0 (keep all) or a positive face count, got {self.min_component_faces}"
            )
        if not (math.isfinite(self.truncation) and self.truncation > 0):
            raise ValueError(f"truncation must be the map's positive truncation T in metres, got {self.truncation}")
        if self.coarse_factor is not None:
            if not isinstance(self.coarse_factor, Integral) or self.coarse_factor < 1:
                raise ValueError(
                    "coarse_factor must be a positive integer (1 = dense) or None (automatic), "
                    f"got {self.coarse_factor}"
                )
            if self.coarse_factor > 1 and coarse_threshold(self.coarse_factor, self.resolution, self.truncation) > 1:
                raise ValueError(
                    f"coarse_factor={self.coarse_factor} at resolution {self.resolution} m makes coarse cells too wide "
                    f"for the truncation T={self.truncation} m: the coarse pass could miss thin surfaces. Use "
                    f"coarse_factor={auto_coarse_factor(self.resolution, self.truncation)} or leave it None (automatic)"
                )


# --------------------------------------------------------------------------------------------------------------
# Grid
# --------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Grid:
    """Regular grid: point (i, j, k) lies at origin + (i, j, k) * spacing."""

    origin: np.ndarray  # (3,) world position of point (0, 0, 0): the bound's minimum corner
    spacing: float  # metres between neighbouring points
    shape: tuple[int, int, int]  # points per axis

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    def points(self, index: np.ndarray) -> np.ndarray:
        """World positions (N, 3) of integer grid indices (N, 3)."""
        return self.origin + index * self.spacing

    def flat_points(self, flat_index: np.ndarray) -> np.ndarray:
        """World positions (N, 3) of flat (C-order) grid indices (N,)."""
        return self.points(np.stack(np.unravel_index(flat_index, self.shape), axis=1))


def validate_bound(bound: np.ndarray) -> np.ndarray:
    """The bound as a float64 (2, 3) array [min corner, max corner]; ValueError naming the problem otherwise."""
    b = np.asarray(bound, dtype=np.float64)
    if b.shape != (2, 3):
        raise ValueError(
            f"mesh bound must be a (2, 3) array [[xmin, ymin, zmin], [xmax, ymax, zmax]], got shape {b.shape}"
        )
    if not np.isfinite(b).all():
        raise ValueError(f"mesh bound must be finite, got {b.tolist()}")
    if not (b[1] > b[0]).all():
        axes = [name for name, lo, hi in zip("xyz", b[0], b[1]) if not hi > lo]
        raise ValueError(
            f"mesh bound must be [min corner, max corner] with max > min on every axis; not so on {', '.join(axes)}: "
            f"{b.tolist()} (swap the rows if they are reversed)"
        )
    return b


def grid_shape(extent: np.ndarray, resolution: float) -> tuple[int, int, int]:
    """Points per axis so that the grid starting at the minimum corner reaches the maximum corner."""
    # Rounding first keeps 3.0 / 0.01 = 300.00000000000006 from adding a whole extra layer of points.
    cells = np.ceil(np.round(extent / resolution, 6)).astype(np.int64)
    return tuple(int(c) + 1 for c in cells)


def suggest_resolution(extent: np.ndarray, max_points: int = MAX_GRID_POINTS) -> float:
    """The finest resolution (two significant digits, rounded up) whose grid over `extent` has <= max_points."""
    r = float(np.prod(extent) / max_points) ** (1 / 3)
    while True:
        digits = 1 - math.floor(math.log10(r))
        r_nice = math.ceil(r * 10**digits) / 10**digits
        if math.prod(grid_shape(extent, r_nice)) <= max_points:
            return r_nice
        r = r_nice * 1.01


def make_grid(bound: np.ndarray, resolution: float) -> Grid:
    b = validate_bound(bound)
    extent = b[1] - b[0]
    shape = grid_shape(extent, resolution)
    if math.prod(shape) > MAX_GRID_POINTS:
        better = suggest_resolution(extent)
        raise GridTooLargeError(
            f"resolution {resolution} m over a {extent[0]:.2f} x {extent[1]:.2f} x {extent[2]:.2f} m bound needs "
            f"{math.prod(shape):,} grid points (limit {MAX_GRID_POINTS:,}): use resolution {better} or coarser, "
            f"or a smaller bound"
        )
    return Grid(origin=b[0], spacing=float(resolution), shape=shape)


# --------------------------------------------------------------------------------------------------------------
# Decoder evaluation
# --------------------------------------------------------------------------------------------------------------


def _decode(fn: Callable[[torch.Tensor], torch.Tensor], points: np.ndarray, width: int, name: str) -> np.ndarray:
    """fn on one chunk of points, as a float32 (N,) or (N, width) array; clear error on a wrong output."""
    with torch.no_grad():
        out = fn(torch.from_numpy(points.astype(np.float32)))
    out = torch.as_tensor(out).detach().to(device="cpu", dtype=torch.float32).numpy()
    expected = (len(points),) if width == 1 else (len(points), width)
    if out.shape != expected and not (width == 1 and out.shape == (len(points), 1)):
        raise ValueError(f"{name} must map (N, 3) points to shape {expected}, got {out.shape} for N={len(points)}")
    out = out.reshape(expected)
    if not np.isfinite(out).all():
        raise ValueError(
            f"{name} returned NaN or inf for {int((~np.isfinite(out)).any(axis=-1).sum())} of {len(points)} points: "
            f"the map parameters are corrupt (diverged optimisation?); mesh an earlier checkpoint"
        )
    return out


def _decode_flat(sdf_fn: SdfFn, grid: Grid, flat_index: np.ndarray, chunk: int) -> np.ndarray:
    """phi at the given flat grid indices, `chunk` points per decoder call."""
    values = np.empty(len(flat_index), dtype=np.float32)
    for start in range(0, len(flat_index), chunk):
        idx = flat_index[start : start + chunk]
        values[start : start + len(idx)] = _decode(sdf_fn, grid.flat_points(idx), 1, "sdf_fn")
    return values


# --------------------------------------------------------------------------------------------------------------
# Coarse to fine
#
# Coarse cells are blocks of k x k x k voxels whose corners are every k-th grid point (the last block of an axis may
# be shorter). If a surface point p lies in a cell, the nearest corner is at most the half-diagonal h = k*s*sqrt(3)/2
# away, so with a slope of phi at most L/T that corner has |phi| <= L*h/T =: tau. A cell whose corners all have
# |phi| > tau and the same sign therefore holds no surface, and every grid point in it has that sign. The bound is
# only usable while tau <= 1, since |phi| saturates at 1 beyond the truncation band.
# --------------------------------------------------------------------------------------------------------------


def coarse_threshold(factor: int, resolution: float, truncation: float) -> float:
    """tau: the largest corner |phi| of a coarse cell that may still contain surface."""
    half_diagonal = factor * resolution * math.sqrt(3) / 2
    return LIPSCHITZ_SAFETY * half_diagonal / truncation


def auto_coarse_factor(resolution: float, truncation: float) -> int:
    """Largest coarse spacing (in voxels) whose cells fit the truncation band (tau <= 1)."""
    return next(k for k in COARSE_FACTORS if k == 1 or coarse_threshold(k, resolution, truncation) <= 1)


def _coarse_indices(n: int, k: int) -> np.ndarray:
    """Grid indices of the coarse points along one axis: every k-th point, and always the last one."""
    return np.minimum(np.arange(math.ceil((n - 1) / k) + 1) * k, n - 1)


def _cells_to_points(cells: np.ndarray, shape: tuple[int, int, int], k: int) -> np.ndarray:
    """Boolean grid (shape) marking every point of every marked coarse cell, its boundary included."""
    out = cells
    for axis, n in enumerate(shape):
        p = np.arange(n)
        m = cells.shape[axis]
        # Point p belongs to cell p // k and, on a cell boundary, also to cell (p - 1) // k.
        own = np.minimum(p // k, m - 1)
        previous = np.maximum(p - 1, 0) // k
        out = np.take(out, own, axis=axis) | np.take(out, previous, axis=axis)
    return out


def _corner_views(values: np.ndarray) -> list[np.ndarray]:
    """The 8 corner values of every cell of a point grid, as 8 arrays of the cell grid's shape."""
    nx, ny, nz = (n - 1 for n in values.shape)
    return [values[i : i + nx, j : j + ny, l : l + nz] for i, j, l in CUBE_CORNERS]


def sdf_volume(sdf_fn: SdfFn, grid: Grid, settings: MeshSettings) -> np.ndarray:
    """phi on every grid point (float32 volume): exact near the surface, +1 / -1 elsewhere (see above)."""
    k = settings.coarse_factor or auto_coarse_factor(grid.spacing, settings.truncation)
    if k == 1:
        return _decode_flat(sdf_fn, grid, np.arange(grid.size), settings.chunk).reshape(grid.shape)

    axes = [_coarse_indices(n, k) for n in grid.shape]
    coarse_index = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    coarse = np.empty(len(coarse_index), dtype=np.float32)
    for start in range(0, len(coarse_index), settings.chunk):
        idx = coarse_index[start : start + settings.chunk]
        coarse[start : start + len(idx)] = _decode(sdf_fn, grid.points(idx), 1, "sdf_fn")
    coarse = coarse.reshape([len(a) for a in axes])

    corners = _corner_views(coarse)
    nearest = np.minimum.reduce([np.abs(c) for c in corners])
    has_free = np.logical_or.reduce([c > 0 for c in corners])
    has_inside = np.logical_or.reduce([c < 0 for c in corners])
    tau = coarse_threshold(k, grid.spacing, settings.truncation)
    refine = (nearest <= tau) | (has_free & has_inside)

    volume = np.ones(grid.shape, dtype=np.float32)
    volume[_cells_to_points(~refine & has_inside, grid.shape, k)] = -1.0
    fine = np.flatnonzero(_cells_to_points(refine, grid.shape, k))
    volume.reshape(-1)[fine] = _decode_flat(sdf_fn, grid, fine, settings.chunk)
    return volume


# --------------------------------------------------------------------------------------------------------------
# Surface voxels and the observed region
# --------------------------------------------------------------------------------------------------------------


def surface_voxels(volume: np.ndarray, slab: int = 64) -> np.ndarray:
    """Minimum-corner indices (M, 3) of the voxels whose corners do not all have the same sign (phi > 0 or not)."""
    free = volume > 0
    found = []
    # Slabs along x keep the 8 corner views small for a room-size volume.
    for x0 in range(0, free.shape[0] - 1, slab):
        corners = _corner_views(free[x0 : x0 + slab + 1])
        mixed = np.logical_or.reduce(corners) & ~np.logical_and.reduce(corners)
        idx = np.argwhere(mixed)
        idx[:, 0] += x0
        found.append(idx)
    return np.concatenate(found)


def _visible(visible_fn: VisibleFn, points: np.ndarray) -> np.ndarray:
    # One call for all points: a culling function has per-call set-up (per-camera depth images) and chunks itself.
    seen = np.asarray(visible_fn(points))
    if seen.shape != (len(points),):
        raise ValueError(f"visible_fn must map (N, 3) points to (N,) booleans, got {seen.shape} for N={len(points)}")
    return seen.astype(bool)


def observed_voxel_mask(voxels: np.ndarray, grid: Grid, visible_fn: VisibleFn) -> np.ndarray:
    """Marching-cubes mask that lets through only surface voxels whose 8 corners are all seen by a camera.

    Only the corners of surface voxels are asked about: elsewhere marching cubes emits nothing anyway, and a
    culling function (frustum + depth test over many cameras) is far too slow for every point of a room grid.
    """
    corner_points = np.zeros(grid.shape, dtype=bool)
    for offset in CUBE_CORNERS:
        c = voxels + offset
        corner_points[c[:, 0], c[:, 1], c[:, 2]] = True
    flat = np.flatnonzero(corner_points)
    seen = np.zeros(grid.size, dtype=bool)
    seen[flat] = _visible(visible_fn, grid.flat_points(flat))
    if not seen.any():
        raise EmptyMeshError(
            "no grid point is visible from any camera (visible_fn rejected all of them): check the camera poses "
            "and that the bound covers the region they observed"
        )
    seen = seen.reshape(grid.shape)
    voxel_seen = np.logical_and.reduce([seen[tuple((voxels + o).T)] for o in CUBE_CORNERS])
    if not voxel_seen.any():
        raise EmptyMeshError(
            "no surface voxel lies entirely in the region seen by the cameras: check the camera poses and bound, "
            "or mesh at a finer resolution"
        )
    # scikit-image reads the mask of a voxel at its MAXIMUM corner (voxel [i-1, i] x [j-1, j] x [l-1, l] is
    # processed when mask[i, j, l]); the vertex test in `extract_mesh` catches any face this lets through.
    mask = np.zeros(grid.shape, dtype=bool)
    kept = voxels[voxel_seen] + 1
    mask[kept[:, 0], kept[:, 1], kept[:, 2]] = True
    return mask


# --------------------------------------------------------------------------------------------------------------
# Mesh clean-up
# --------------------------------------------------------------------------------------------------------------


def component_face_counts(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """For each face, the number of faces in its connected component (faces connected through shared vertices)."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges), dtype=np.int32), (edges[:, 0], edges[:, 1])), shape=(n_vertices,) * 2)
    _, vertex_label = connected_components(graph, directed=False)
    face_label = vertex_label[faces[:, 0]]
    return np.bincount(face_label)[face_label]


def compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices no face uses and renumber the faces."""
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    new_index = np.cumsum(used) - 1
    return vertices[used], new_index[faces]


def vertex_colors(color_fn: Optional[ColorFn], vertices: np.ndarray, chunk: int) -> np.ndarray:
    """RGBA uint8 (N, 4) colours: color_fn at the vertices, or grey without a colour decoder."""
    rgba = np.tile(GREY, (len(vertices), 1))
    if color_fn is None:
        return rgba
    for start in range(0, len(vertices), chunk):
        rgb = _decode(color_fn, vertices[start : start + chunk], 3, "color_fn")
        rgba[start : start + len(rgb), :3] = np.round(np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)
    return rgba


# --------------------------------------------------------------------------------------------------------------
# Extraction
# --------------------------------------------------------------------------------------------------------------


def extract_mesh(
    sdf_fn: SdfFn,
    color_fn: Optional[ColorFn],
    bound: np.ndarray,
    settings: MeshSettings,
    visible_fn: Optional[VisibleFn] = None,
) -> trimesh.Trimesh:
    """Zero level set of the map's SDF inside `bound` as a coloured triangle mesh (see the module docstring).

    Normals point to free space (positive SDF). Raises EmptyMeshError when no triangle would remain.
    """
    grid = make_grid(bound, settings.resolution)
    volume = sdf_volume(sdf_fn, grid, settings)

    voxels = surface_voxels(volume)
    if len(voxels) == 0:
        lo, hi = float(volume.min()), float(volume.max())
        raise EmptyMeshError(
            f"the map has no surface inside the bound (sampled SDF between {lo:.3f} and {hi:.3f}, no sign change): "
            f"the map may be untrained (too few mapping iterations) or the bound misses the scene"
        )
    mask = None if visible_fn is None else observed_voxel_mask(voxels, grid, visible_fn)

    # With a positive-outside SDF, scikit-image's default 'descent' winding makes face normals point outwards.
    try:
        verts, faces, _, _ = marching_cubes(volume, level=0.0, mask=mask, allow_degenerate=False)
    except RuntimeError as err:  # "No surface found": every crossing was masked or degenerate
        raise EmptyMeshError(
            "marching cubes found no triangle in the observed surface voxels: check the camera poses and bound, "
            "or mesh at a finer resolution"
        ) from err
    vertices = grid.origin + verts.astype(np.float64) * grid.spacing
    faces = faces.astype(np.int64)

    if visible_fn is not None:
        seen = _visible(visible_fn, vertices)
        faces = faces[seen[faces].all(axis=1)]
        if len(faces) == 0:
            raise EmptyMeshError(
                "every extracted face has a vertex outside the region seen by the cameras: check the camera poses "
                "and bound"
            )
    if settings.min_component_faces > 0:
        n_before = len(faces)
        faces = faces[component_face_counts(faces, len(vertices)) >= settings.min_component_faces]
        if len(faces) == 0:
            raise EmptyMeshError(
                f"every connected component has fewer than min_component_faces={settings.min_component_faces} "
                f"faces ({n_before} faces in all): lower min_component_faces"
            )
    vertices, faces = compact(vertices, faces)
    colors = vertex_colors(color_fn, vertices, settings.chunk)
    return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colors, process=False)


def save_ply(mesh: trimesh.Trimesh, path) -> Path:
    """Write the mesh as binary PLY with its vertex colours; returns the path written."""
    path = Path(path)
    if len(mesh.faces) == 0:
        raise EmptyMeshError(f"refusing to write an empty mesh to {path}: extraction produced no triangle")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"cannot write {path}: directory {path.parent} does not exist (create it first)")
    return write_atomic(path, trimesh.exchange.ply.export_ply(mesh, encoding="binary"))
