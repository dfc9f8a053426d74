"""The map meshed in fixed world blocks, re-meshed and re-sent only where it changed (the live mesh preview).

Blocks. Block (i, j, k) is the cube [i, i+1) x [j, j+1) x [k, k+1) * `edge` in map coordinates, `edge` a whole
number of mesh voxels. A block is addressed by these integer coordinates, never by an index into a grid over the
current bound, so when the map grows every existing block keeps its address (and a viewer its marker). Grid points
are integer multiples of the resolution, so two neighbouring blocks sample the SDF at the same points on their
common face and their meshes meet without a seam; each block is meshed like the whole map is (`extract_mesh`:
coarse-to-fine SDF volume, culled to what the keyframes saw).

Which blocks to mesh (`IncrementalMesher.update`), in this order and within a time budget per pass, so that a
large map is spread over several passes instead of stalling one:
1. dirty blocks, newest first: blocks within 2T of the depth points of a keyframe that is new or whose pose moved
   since it was last looked at. That is where the map's features change most: mapping optimises the planes with
   rays of the keyframe window, which overlaps the newest keyframe, and culling (which surface counts as seen)
   changes exactly where keyframes are added or moved;
2. the other blocks, least recently meshed first, if they were meshed from an older view of the map: the decoders are
   shared by the whole map, so every mapping step moves the surface everywhere a little, and this sweep lets those
   changes show up eventually.

When a block changed (`surface_changed`): a re-meshed block counts as changed, and is reported, only if a viewer
would see a difference from the version last reported: vertices moved by more than `tolerance` (half a voxel by
default), a part of the surface appeared or vanished, or colours changed by more than `color_tolerance` (at least
MIN_CHANGED_VERTICES vertices each time: single stray vertices are noise). Deciding
from the mesh rather than from which plane features changed is what makes "unchanged" mean unchanged for the
viewer: the optimiser (Adam with momentum, decoders shared by the whole map) changes every parameter a little at
every step, so a feature-level test would call almost every block changed; the mesh test does not, and a block
whose map did not change at all re-meshes to the very same arrays.
"""
from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Container, Hashable, Optional

import numpy as np
import torch
from scipy.spatial import cKDTree

from eslam_core.camera import Intrinsics, backproject
from eslam_core.outputs.culling import visible_mask
from eslam_core.outputs.mesh import ColorFn, EmptyMeshError, MeshSettings, SdfFn, extract_mesh

Key = tuple[int, int, int]  # integer block coordinates

# Depth pixels used to find the blocks a keyframe observed: every OBSERVATION_STRIDE-th row and column (blocks are
# a metre wide; a 640x480 keyframe still gives 19k points).
OBSERVATION_STRIDE = 4
# Colour difference (of 1 = full scale, per channel) a viewer notices on a live preview.
COLOR_TOLERANCE = 16 / 255
# Vertices that must differ for a block to count as changed (fewer are noise where the observed region ends).
MIN_CHANGED_VERTICES = 8


class BlockLayoutError(ValueError):
    """Impossible block size or resolution."""


@dataclass(frozen=True)
class BlockLayout:
    """World-aligned blocks of `voxels` mesh voxels of `resolution` metres per edge."""

    resolution: float
    voxels: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise BlockLayoutError(f"mesh resolution must be a positive number of metres, got {self.resolution}")
        if not (isinstance(self.voxels, int) and self.voxels >= 1):
            raise BlockLayoutError(f"a block must be at least one voxel wide, got {self.voxels} voxels")

    @staticmethod
    def of(block_size: float, resolution: float) -> "BlockLayout":
        """Blocks of about `block_size` metres: the nearest whole number of voxels (at least 2)."""
        if not (math.isfinite(block_size) and block_size > 0):
            raise BlockLayoutError(f"mesh block size must be a positive number of metres, got {block_size}")
        if not (math.isfinite(resolution) and resolution > 0):
            raise BlockLayoutError(f"mesh resolution must be a positive number of metres, got {resolution}")
        return BlockLayout(float(resolution), max(2, round(block_size / resolution)))

    @property
    def edge(self) -> float:
        return self.resolution * self.voxels

    def observed_boxes(self, points: np.ndarray, margin: float) -> dict[Key, np.ndarray]:
        """The blocks within `margin` (< edge) of any of the (N, 3) points, each with the box (2, 3) around its
        points, grown by `margin`: where in the block there is something observed to mesh."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            return {}
        low = np.floor((points - margin) / self.edge).astype(np.int64)
        high = np.floor((points + margin) / self.edge).astype(np.int64)
        # With margin < edge a point's neighbourhood spans at most two blocks per axis: the 8 low/high combinations.
        keys = np.concatenate([np.stack([(high if pick[a] else low)[:, a] for a in range(3)], axis=1)
                               for pick in itertools.product((0, 1), repeat=3)])
        # One int64 per key (21 bits per axis) makes the grouping a 1-D sort instead of a row-wise unique.
        code = ((keys[:, 0] + _KEY_OFFSET) << 42) | ((keys[:, 1] + _KEY_OFFSET) << 21) | (keys[:, 2] + _KEY_OFFSET)
        order = np.argsort(code, kind="stable")
        code, owner = code[order], np.tile(points, (8, 1))[order]
        first = np.flatnonzero(np.r_[True, code[1:] != code[:-1]])
        lo = np.minimum.reduceat(owner, first, axis=0) - margin
        hi = np.maximum.reduceat(owner, first, axis=0) + margin
        return {tuple(k): np.stack([a, b]) for k, a, b in zip(keys[order][first].tolist(), lo, hi)}

    def grid_bound(self, key: Key, map_bound: np.ndarray, region: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
        """The block's box on grid points, cut to the map's bound and to `region` (grown to grid points): (2, 3)
        metres, or None if nothing is left."""
        key_arr = np.asarray(key, dtype=np.int64)
        bound = np.asarray(map_bound, dtype=np.float64)
        # Grid indices (multiples of the resolution), so that cut blocks stay aligned with their neighbours.
        low = np.maximum(key_arr * self.voxels, np.ceil(bound[0] / self.resolution - 1e-9).astype(np.int64))
        high = np.minimum((key_arr + 1) * self.voxels, np.floor(bound[1] / self.resolution + 1e-9).astype(np.int64))
        if region is not None:
            low = np.maximum(low, np.floor(region[0] / self.resolution).astype(np.int64))
            high = np.minimum(high, np.ceil(region[1] / self.resolution).astype(np.int64))
        if np.any(high <= low):
            return None
        return np.stack([low, high]).astype(np.float64) * self.resolution


_KEY_OFFSET = 1 << 20  # block coordinates from -2^20 to 2^20 - 1 (a million blocks each way)


@dataclass
class BlockMesh:
    """The surface inside one block."""

    vertices: np.ndarray  # (V, 3) float64 map coordinates
    faces: np.ndarray  # (F, 3) int64, normals towards free space
    colors: np.ndarray  # (V, 4) uint8 RGBA

    @property
    def triangles(self) -> int:
        return len(self.faces)


# ------------------------------------------------------------------------------------------------ the map to mesh


@dataclass
class MeshSource:
    """What meshing needs of a map: its decoders and bound, and the keyframes for culling and change tracking."""

    sdf: SdfFn
    color: Optional[ColorFn]
    bound: np.ndarray  # (2, 3)
    truncation: float  # T (metres)
    intrinsics: Intrinsics  # of the keyframes' depth images
    keyframe_ids: list[Hashable]  # a stable id per keyframe and depth image
    poses: np.ndarray  # (K, 4, 4) float64 camera-to-world
    depths: list[np.ndarray]  # K depth images (H, W) float32 metres, 0 = none
    _world_to_camera: Optional[np.ndarray] = field(default=None, repr=False)
    _far: Optional[np.ndarray] = field(default=None, repr=False)

    def cameras_seeing(self, box: np.ndarray) -> np.ndarray:
        """Indices of the keyframes whose view (frustum, up to their farthest depth + T) may reach into `box`.

        Conservative: a keyframe left out sees no point of the box, so culling with only these gives the same
        result as culling with all of them, at a fraction of the cost.
        """
        if len(self.poses) == 0:
            return np.zeros(0, dtype=np.int64)
        if self._world_to_camera is None:
            self._world_to_camera = np.linalg.inv(self.poses)
            self._far = np.array([float(d.max()) if d.size else 0.0 for d in self.depths]) + self.truncation
        corners = np.array([[box[i][0], box[j][1], box[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        w2c = self._world_to_camera
        p = np.einsum("kij,nj->kni", w2c[:, :3, :3], corners) + w2c[:, None, :3, 3]  # (K, 8, 3)
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        i = self.intrinsics
        # The view is the intersection of half-spaces; a box entirely outside one of them is not seen.
        outside = [
            z <= 0,
            i.fx * x + (i.cx + 0.5) * z < 0,  # u < -0.5
            (i.width - 0.5 - i.cx) * z - i.fx * x <= 0,  # u >= width - 0.5
            i.fy * y + (i.cy + 0.5) * z < 0,
            (i.height - 0.5 - i.cy) * z - i.fy * y <= 0,
            z > self._far[:, None],
        ]
        hidden = np.logical_or.reduce([half.all(axis=1) for half in outside])
        return np.flatnonzero(~hidden)

    def observed_boxes(self, k: int, layout: BlockLayout) -> dict[Key, np.ndarray]:
        """The blocks within 2T of keyframe k's depth points (the band where its depth shapes the SDF), each with
        the box around those points."""
        points = backproject(self.depths[k], self.intrinsics, self.poses[k], stride=OBSERVATION_STRIDE)
        return layout.observed_boxes(points, 2 * self.truncation)


def mesh_source(scene, skip_depths: Container = ()) -> MeshSource:
    """The MeshSource of a scene map (`SLAM.map`, a runtime's snapshot's, or the mapping process's own): the field in
    eval mode, the keyframes' poses and depth images at the frame's resolution (None for the ids in
    `skip_depths`). A keyframe's id is (number, stride): a keyframe the store reduced has another depth image, so it
    counts as a new keyframe."""
    if scene.field is None:
        raise EmptyMeshError("the map is empty: no frame has been processed")
    field_ = scene.field.eval()
    keyframes, (h, w) = list(scene.keyframes), (scene.intr.height, scene.intr.width)
    ids = [(int(kf.number), int(kf.stride)) for kf in keyframes]
    return MeshSource(
        sdf=field_.sdf, color=field_.color, bound=np.asarray(scene.extent, dtype=np.float64),
        truncation=float(scene.cfg.model.truncation), intrinsics=scene.intr, keyframe_ids=ids,
        poses=np.stack([kf.pose.double().numpy() for kf in keyframes]) if keyframes else np.zeros((0, 4, 4)),
        depths=[None if i in skip_depths else kf.frame_depth_image(h, w).numpy() for i, kf in zip(ids, keyframes)],
    )


def mesh_block(view: MeshSource, layout: BlockLayout, key: Key, settings: MeshSettings,
               region: Optional[np.ndarray] = None) -> Optional[BlockMesh]:
    """The observed surface inside block `key` (and inside `region`, the box around what was observed there), or
    None where there is none."""
    box = layout.grid_bound(key, view.bound, region)
    if box is None:
        return None
    cameras = view.cameras_seeing(box)
    if len(cameras) == 0:
        return None  # no keyframe sees into the block: culling would remove everything
    poses, depths = view.poses[cameras], [view.depths[c] for c in cameras]

    def visible(points: np.ndarray) -> np.ndarray:
        return visible_mask(points, poses, view.intrinsics, depths, view.truncation)

    try:
        with torch.no_grad():
            mesh = extract_mesh(view.sdf, view.color, box, settings, visible_fn=visible)
    except EmptyMeshError:
        return None
    return BlockMesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64),
                     np.asarray(mesh.visual.vertex_colors, dtype=np.uint8))


# ------------------------------------------------------------------------------------------------ change test


def surface_changed(old: Optional[BlockMesh], new: Optional[BlockMesh], tolerance: float,
                    color_tolerance: float = COLOR_TOLERANCE, old_tree: Optional[cKDTree] = None,
                    min_vertices: int = MIN_CHANGED_VERTICES) -> bool:
    """Whether a viewer of `old` would see `new` differ: `min_vertices` vertices of either further than `tolerance`
    from every vertex of the other (the surface moved, appeared or vanished), or that many colours off by more than
    `color_tolerance` from that of the nearest old vertex. (A mesh smaller than `min_vertices` needs all of its
    vertices to count; fewer stray vertices are noise at the edge of the observed region, not a change.)"""
    if old is None or new is None:
        return (old is None) != (new is None)
    if (old.vertices.shape == new.vertices.shape and np.array_equal(old.vertices, new.vertices)
            and np.array_equal(old.colors, new.colors) and np.array_equal(old.faces, new.faces)):
        return False
    tree = cKDTree(old.vertices) if old_tree is None else old_tree
    distance, nearest = tree.query(new.vertices, distance_upper_bound=2 * tolerance)
    far = distance > tolerance
    if far.sum() >= min(min_vertices, len(new.vertices)):
        return True
    close = ~far
    color_step = np.abs(new.colors[close, :3].astype(np.int16) - old.colors[nearest[close], :3].astype(np.int16))
    if (color_step.max(axis=1) > color_tolerance * 255).sum() >= min(min_vertices, len(new.vertices)):
        return True
    back, _ = cKDTree(new.vertices).query(old.vertices, distance_upper_bound=2 * tolerance)
    return (back > tolerance).sum() >= min(min_vertices, len(old.vertices))


# ------------------------------------------------------------------------------------------------ incremental


@dataclass
class BlockChanges:
    """One meshing pass: the blocks whose surface changed (their new mesh) and those that became empty."""

    changed: dict[Key, BlockMesh]
    removed: list[Key]
    meshed: int  # blocks meshed in this pass (blocks outside the map's bound are skipped, not counted)
    pending: int  # dirty blocks left for the next pass
    seconds: float  # wall time of the pass


@dataclass
class _Observation:
    pose: np.ndarray
    boxes: dict[Key, np.ndarray]  # the blocks the keyframe observes, and the box of its points in each


@dataclass
class _Reported:
    mesh: BlockMesh
    tree: Optional[cKDTree] = None  # built at the first comparison


class IncrementalMesher:
    """Keeps the block meshes of a live map up to date, a time budget at a time (see the module docstring).

    `blocks` is the state a viewer has after applying every BlockChanges returned so far, in order.
    """

    def __init__(self, layout: BlockLayout, settings: MeshSettings, tolerance: Optional[float] = None,
                 color_tolerance: float = COLOR_TOLERANCE, clock: Callable[[], float] = time.monotonic) -> None:
        if abs(settings.resolution - layout.resolution) > 1e-12:
            raise BlockLayoutError(f"mesh settings resolution {settings.resolution} differs from the block layout's "
                                   f"{layout.resolution}")
        self.layout = layout
        self.settings = settings
        self.tolerance = layout.resolution / 2 if tolerance is None else float(tolerance)
        self.color_tolerance = color_tolerance
        self.clock = clock
        self._reported: dict[Key, _Reported] = {}
        self._observations: dict[Hashable, _Observation] = {}
        self._observers: dict[Key, set] = {}  # block -> the keyframes observing it
        self._dirty: dict[Key, int] = {}  # block -> when it became dirty (larger = more recent)
        self._meshed_at: dict[Key, int] = {}  # block -> the pass that last meshed it
        self._boxes: dict[Key, Optional[np.ndarray]] = {}  # block -> the grid box it was last meshed over
        self._grid_boxes: dict[Key, Optional[np.ndarray]] = {}  # block -> the grid box it would be meshed over now
        self._bound: Optional[np.ndarray] = None
        self._meshed_in: dict[Key, int] = {}  # block -> the view (number) it was last meshed from
        self._view: Optional[MeshSource] = None
        self._views = 0
        self._tick = itertools.count()
        self._passes = 0

    @property
    def blocks(self) -> dict[Key, BlockMesh]:
        return {key: reported.mesh for key, reported in self._reported.items()}

    @property
    def pending(self) -> int:
        return len(self._dirty)

    @property
    def known(self) -> set[Key]:
        """Every block some keyframe observes: the candidates for meshing."""
        return set(self._observers)

    def update(self, view: MeshSource, budget_s: float) -> BlockChanges:
        """Mesh dirty blocks, then stale ones, until `budget_s` seconds are spent (at least one block per pass)."""
        start = self.clock()
        self._observe(view)
        changed: dict[Key, BlockMesh] = {}
        removed: list[Key] = []
        # Blocks outside the map's bound have nothing to mesh: settled at once, at no cost to the budget.
        for key in [key for key in self._dirty if self._box(view, key) is None]:
            self._record(key, None, None, changed, removed)
        if view is not self._view:
            self._view, self._views = view, self._views + 1
        # Stale: meshed from an older view of the map (one meshed from this view would come out the same).
        stale = sorted((key for key in self._observers if key not in self._dirty and self._box(view, key) is not None
                        and self._meshed_in.get(key) != self._views), key=lambda key: self._meshed_at.get(key, -1))
        order = sorted(self._dirty, key=self._dirty.__getitem__, reverse=True) + stale
        meshed = 0
        for key in order:
            if meshed and self.clock() - start >= budget_s:
                break
            box = self._box(view, key)
            self._record(key, box, mesh_block(view, self.layout, key, self.settings, self.region(key)), changed,
                         removed)
            meshed += 1
        # Blocks no keyframe observes any more (their keyframes were dropped).
        for key in [key for key in self._reported if key not in self._observers]:
            del self._reported[key]
            removed.append(key)
        self._passes += 1
        return BlockChanges(changed, removed, meshed, len(self._dirty), self.clock() - start)

    def region(self, key: Key) -> Optional[np.ndarray]:
        """The box around everything observed in block `key`: the union of its keyframes' boxes."""
        boxes = [self._observations[k].boxes[key] for k in self._observers.get(key, ())]
        if not boxes:
            return None
        return np.stack([np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)])

    def _box(self, view: MeshSource, key: Key) -> Optional[np.ndarray]:
        """The grid box block `key` is meshed over now (cached until its observations or the bound change)."""
        if key not in self._grid_boxes:
            self._grid_boxes[key] = self.layout.grid_bound(key, view.bound, self.region(key))
        return self._grid_boxes[key]

    def _observe(self, view: MeshSource) -> None:
        """New, moved and dropped keyframes make the blocks they observe dirty; so does a change of the map's bound
        (a grown map: blocks at its old border get more room, blocks beyond it become meshable)."""
        present = set(view.keyframe_ids)
        for keyframe in [k for k in self._observations if k not in present]:
            self._forget(keyframe)
        for k, keyframe in enumerate(view.keyframe_ids):
            pose = view.poses[k]
            seen = self._observations.get(keyframe)
            if seen is not None and not self._moved(seen.pose, pose):
                continue
            if seen is not None:
                self._forget(keyframe)
            boxes = view.observed_boxes(k, self.layout)
            self._observations[keyframe] = _Observation(np.array(pose, dtype=np.float64), boxes)
            for key in boxes:
                self._observers.setdefault(key, set()).add(keyframe)
                self._grid_boxes.pop(key, None)
            self._mark_dirty(boxes)
        if self._bound is None or not np.array_equal(self._bound, view.bound):
            self._bound = np.array(view.bound, dtype=np.float64)
            self._grid_boxes.clear()
            for key in self._observers:
                before, now = self._boxes.get(key, "never"), self._box(view, key)
                if isinstance(before, str):
                    continue  # never meshed: dirty anyway
                if (now is None) != (before is None) or (now is not None and not np.array_equal(now, before)):
                    self._mark_dirty((key,))

    def _forget(self, keyframe: Hashable) -> None:
        seen = self._observations.pop(keyframe)
        for key in seen.boxes:
            self._grid_boxes.pop(key, None)
            observers = self._observers[key]
            observers.discard(keyframe)
            if not observers:
                del self._observers[key]
                self._dirty.pop(key, None)
        self._mark_dirty([key for key in seen.boxes if key in self._observers])

    def _moved(self, before: np.ndarray, after: np.ndarray) -> bool:
        """Whether the keyframe's depth points moved by more than the tolerance (at 5 m for the rotation)."""
        shift = np.linalg.norm(after[:3, 3] - before[:3, 3])
        cos = np.clip((np.trace(before[:3, :3].T @ after[:3, :3]) - 1) / 2, -1.0, 1.0)
        return shift + 5.0 * math.acos(cos) > self.tolerance

    def _mark_dirty(self, keys) -> None:
        tick = next(self._tick)
        for key in keys:
            self._dirty[key] = tick

    def _record(self, key: Key, box: Optional[np.ndarray], new: Optional[BlockMesh], changed: dict,
                removed: list) -> None:
        """A block was meshed (over `box`, None: outside the map): report it if its surface changed."""
        self._dirty.pop(key, None)
        self._meshed_at[key] = self._passes
        self._meshed_in[key] = self._views
        self._boxes[key] = box
        old = self._reported.get(key)
        if new is None:
            if old is not None:
                del self._reported[key]
                removed.append(key)
            return
        if old is not None:
            if old.tree is None:
                old.tree = cKDTree(old.mesh.vertices)
            if not surface_changed(old.mesh, new, self.tolerance, self.color_tolerance, old.tree):
                return
        self._reported[key] = _Reported(new)
        changed[key] = new


# ------------------------------------------------------------------------------------------------ for viewers


def thinning_stride(total_triangles: int, triangle_budget: int) -> int:
    """Keep every n-th triangle of each block, n the smallest power of two that brings the total within the budget.

    Powers of two: the stride (and with it every block) changes only when the map doubles, not at every publication.
    """
    if triangle_budget < 1:
        raise ValueError(f"triangle budget must be >= 1, got {triangle_budget}")
    stride = 1
    while total_triangles > stride * triangle_budget:
        stride *= 2
    return stride


def triangle_soup(mesh: BlockMesh, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Every `stride`-th face as three corners: (3T, 3) float64 positions and (3T, 4) float32 RGBA in [0, 1].

    Marching cubes lists a block's faces in spatial order, so a stride thins the surface evenly.
    """
    kept = mesh.faces[::stride]
    corners = np.ascontiguousarray(mesh.vertices[kept].reshape(-1, 3), dtype="<f8")
    colors = np.ascontiguousarray((mesh.colors.astype(np.float32) / 255.0)[kept].reshape(-1, 4), dtype="<f4")
    return corners, colors
