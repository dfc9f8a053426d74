"""3D reconstruction metrics (NICE-SLAM / ESLAM protocol): accuracy, completion, completion ratio.

Both meshes (already culled to what the cameras saw, see eslam_core.outputs.culling) are sampled uniformly by area;
- accuracy   = mean distance from each reconstruction sample to the nearest ground-truth sample,
- completion = mean distance from each ground-truth sample to the nearest reconstruction sample,
- completion ratio = fraction of ground-truth samples closer than 5 cm to the reconstruction,
plus precision / recall / F-score at distance thresholds (Knapitsch et al. 2017). Metres internally.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence, Union

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from eslam_core.evaluation.trajectory_error import umeyama_alignment
from eslam_core.trajectory import TrajectoryError

log = logging.getLogger(__name__)

PathLike = Union[str, Path]


class MeshError(ValueError):
    """A mesh that cannot be evaluated (missing file, no faces, non-finite vertices, zero area)."""


def check_mesh(mesh: trimesh.Trimesh, name: str, warn: bool = True) -> None:
    """Raise MeshError for meshes no metric can use; log a warning (when `warn`) for merely imperfect ones.

    Reconstructions are rarely watertight and often non-manifold (marching cubes at the truncation border), so
    those only warn. The metric functions re-check their input with warn=False: a mesh is reported once, on load.
    """
    vertices = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.faces)
    if len(vertices) == 0 or len(faces) == 0:
        raise MeshError(
            f"{name} is empty ({len(vertices)} vertices, {len(faces)} faces): was mesh extraction skipped, or did "
            "culling remove everything (check the poses and the depth scale)?"
        )
    if not np.isfinite(vertices).all():
        bad = int((~np.isfinite(vertices).all(axis=1)).sum())
        raise MeshError(f"{name} has {bad} vertices with nan/inf coordinates: re-export it or remove those vertices")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{name} has faces that index missing vertices (0..{len(vertices) - 1}): the file is corrupt")
    if not mesh.area > 0:
        raise MeshError(f"{name} has {len(faces)} faces but zero total area: all its triangles are degenerate")
    if not warn:
        return
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1).astype(np.int64)
    _, uses = np.unique(edges[:, 0] * len(vertices) + edges[:, 1], return_counts=True)
    if (uses > 2).any():
        log.warning("%s is non-manifold: %d edges are shared by more than two faces", name, int((uses > 2).sum()))
    if (uses == 1).any():
        log.warning("%s is not watertight: %d boundary edges (normal for a partial reconstruction)",
                    name, int((uses == 1).sum()))


def load_mesh(path: PathLike, name: str = "mesh") -> trimesh.Trimesh:
    """Load a triangle mesh as stored (no vertex merging or cleaning, which would hide defects) and check it."""
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{name} file not found: {path}")
    try:
        mesh = trimesh.load(path, process=False, force="mesh")
    except Exception as error:  # trimesh raises many unrelated types for unreadable files
        raise MeshError(f"cannot read {name} {path}: {error}") from None
    check_mesh(mesh, f"{name} ({path})")
    return mesh


def sample_surface(mesh: trimesh.Trimesh, n: int = 450_000, seed: int = 0) -> np.ndarray:
    """`n` points (n, 3) uniformly distributed over the surface area, reproducible for a given seed.

    The same seed on the same mesh gives the same points, so a mesh compared with itself scores exactly 0.
    """
    if n <= 0:
        raise MeshError(f"number of sample points must be positive, got {n}")
    areas = np.asarray(mesh.area_faces, dtype=np.float64)
    cumulative = np.cumsum(areas)
    if not cumulative[-1] > 0:
        raise MeshError("cannot sample a mesh whose total area is zero")
    rng = np.random.default_rng(seed)
    face = np.searchsorted(cumulative, rng.random(n) * cumulative[-1], side="right")
    face = np.minimum(face, len(areas) - 1)
    triangles = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)[face]]
    # Uniform barycentric sampling: sqrt on the first variable makes the density uniform over the triangle.
    r1 = np.sqrt(rng.random(n))[:, None]
    r2 = rng.random(n)[:, None]
    return (1 - r1) * triangles[:, 0] + r1 * (1 - r2) * triangles[:, 1] + r1 * r2 * triangles[:, 2]


@dataclass(frozen=True)
class ThresholdScore:
    threshold: float  # metres
    precision: float  # fraction of reconstruction samples within `threshold` of the ground truth
    recall: float  # fraction of ground-truth samples within `threshold` of the reconstruction
    fscore: float  # harmonic mean of precision and recall


@dataclass(frozen=True)
class ReconstructionResult:
    accuracy: float  # metres, reconstruction -> ground truth
    completion: float  # metres, ground truth -> reconstruction
    completion_ratio: float  # fraction of ground-truth samples within `completion_threshold`
    completion_threshold: float  # metres (5 cm in the protocol)
    scores: tuple[ThresholdScore, ...]
    n_points: int  # samples per mesh


def reconstruction_metrics(
    rec_mesh: trimesh.Trimesh,
    gt_mesh: trimesh.Trimesh,
    n_points: int = 450_000,
    seed: int = 0,
    thresholds: Sequence[float] = (0.01, 0.05),
    completion_threshold: float = 0.05,
) -> ReconstructionResult:
    """Accuracy, completion (metres), completion ratio and precision / recall / F-score of `rec_mesh` vs `gt_mesh`."""
    check_mesh(rec_mesh, "reconstructed mesh", warn=False)
    check_mesh(gt_mesh, "ground-truth mesh", warn=False)
    rec_points = sample_surface(rec_mesh, n_points, seed)
    gt_points = sample_surface(gt_mesh, n_points, seed)
    to_gt, _ = cKDTree(gt_points).query(rec_points, workers=-1)
    to_rec, _ = cKDTree(rec_points).query(gt_points, workers=-1)
    scores = []
    for threshold in thresholds:
        precision = float(np.mean(to_gt < threshold))
        recall = float(np.mean(to_rec < threshold))
        fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
        scores.append(ThresholdScore(float(threshold), precision, recall, fscore))
    return ReconstructionResult(
        accuracy=float(to_gt.mean()),
        completion=float(to_rec.mean()),
        completion_ratio=float(np.mean(to_rec < completion_threshold)),
        completion_threshold=float(completion_threshold),
        scores=tuple(scores),
        n_points=int(n_points),
    )


def icp_align(
    rec_mesh: trimesh.Trimesh,
    gt_mesh: trimesh.Trimesh,
    max_iterations: int = 50,
    max_distance: float = 0.1,
    n_points: int = 50_000,
    seed: int = 0,
    tolerance: float = 1e-7,
) -> np.ndarray:
    """4x4 rigid transform that moves `rec_mesh` onto `gt_mesh` (point-to-point ICP, Besl & McKay 1992).

    Each iteration pairs every reconstruction sample with its nearest ground-truth sample, ignores pairs further
    than `max_distance` (surface the other mesh lacks), and solves the rigid fit in closed form (Umeyama). The
    ground truth is sampled 4x denser so that its sampling gaps do not bias the fit. Stops when the mean pair
    distance changes by less than `tolerance` metres.
    """
    check_mesh(rec_mesh, "reconstructed mesh", warn=False)
    check_mesh(gt_mesh, "ground-truth mesh", warn=False)
    source = sample_surface(rec_mesh, n_points, seed)
    target = sample_surface(gt_mesh, 4 * n_points, seed + 1)
    tree = cKDTree(target)
    transform = np.eye(4)
    previous = np.inf
    for _ in range(max_iterations):
        moved = source @ transform[:3, :3].T + transform[:3, 3]
        distance, nearest = tree.query(moved, distance_upper_bound=max_distance, workers=-1)
        paired = np.isfinite(distance)
        if paired.sum() < 3:
            raise MeshError(
                f"ICP found {int(paired.sum())} point pairs closer than {max_distance} m: the meshes are too far "
                "apart to align; check that both are in the same world frame, or raise max_distance"
            )
        try:
            rotation, translation, _ = umeyama_alignment(moved[paired], target[nearest[paired]])
        except TrajectoryError as error:
            raise MeshError(f"ICP step failed: {error}") from None
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = rotation, translation
        transform = step @ transform
        mean_distance = float(distance[paired].mean())
        if abs(previous - mean_distance) < tolerance:
            break
        previous = mean_distance
    return transform
